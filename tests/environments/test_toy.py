import math

import pytest
import torch

from hireps_torch.envs.toy import ContextualTwoGaussians, TwoGaussians


def test_bumps_peak_at_the_modes():
    task = TwoGaussians()
    r = task(task.modes.clone())
    assert torch.allclose(r, torch.ones(2), atol=1e-6)
    assert float(task(torch.zeros(1, 2))) < 1e-3  # the average of the modes is bad
    # hand computed: one width away from mode 1 along x
    th = task.modes[:1] + torch.tensor([[task.width, 0.0]])
    assert float(task(th)) == pytest.approx(math.exp(-0.5), abs=1e-6)


def test_contextual_modes_move_with_the_context():
    task = ContextualTwoGaussians()
    s = torch.tensor([[-1.0], [0.0], [0.5]], dtype=torch.float64)
    modes = task.modes(s)
    assert modes.shape == (3, 2, 2)
    for m in range(2):
        assert torch.allclose(task(s, modes[:, m]), torch.ones(3, dtype=torch.float64), atol=1e-6)
    g = torch.Generator().manual_seed(0)
    c = task.sample_contexts(1000, g)
    assert float(c.min()) >= -1 and float(c.max()) <= 1


def test_bad_input_raises():
    with pytest.raises(ValueError, match=r"theta must have shape \(\[S,\] N, 2\)"):
        TwoGaussians()(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="non-finite"):
        TwoGaussians()(torch.tensor([[math.nan, 0.0]]))
    with pytest.raises(ValueError, match=r"context must have shape \(\[S,\] N, 1\)"):
        ContextualTwoGaussians()(torch.zeros(3, 2), torch.zeros(3, 2))


def test_a_population_of_parameters_scores_as_each_member_alone():
    g = torch.Generator().manual_seed(1)
    theta = torch.randn(3, 5, 2, generator=g, dtype=torch.float64)  # (S, N, 2)
    s = torch.rand(3, 5, 1, generator=g, dtype=torch.float64)
    flat, contextual = TwoGaussians(), ContextualTwoGaussians()
    r, rc = flat(theta), contextual(s, theta)
    assert r.shape == rc.shape == (3, 5)
    for m in range(3):
        assert torch.equal(r[m], flat(theta[m]))
        assert torch.equal(rc[m], contextual(s[m], theta[m]))
    with pytest.raises(ValueError, match=r"contexts of shape \(3, 4, 1\) for parameters"):
        contextual(s[:, :4], theta)
    with pytest.raises(ValueError, match="theta must have shape"):
        flat(theta[None])  # (1, S, N, 2): too many dimensions


def test_bad_widths_and_counts_are_named():
    for width in (0.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="width must be finite and > 0"):
            TwoGaussians(width=width)
        with pytest.raises(ValueError, match="width must be finite and > 0"):
            ContextualTwoGaussians(width=width)
    with pytest.raises(ValueError, match="context_low < context_high"):
        ContextualTwoGaussians(context_low=1.0, context_high=1.0)
    with pytest.raises(ValueError, match="n must be >= 0"):
        ContextualTwoGaussians().sample_contexts(-1)
    assert ContextualTwoGaussians().sample_contexts(0).shape == (0, 1)
    ints = torch.zeros(3, 2, dtype=torch.long)
    assert torch.equal(TwoGaussians()(ints), TwoGaussians()(ints.double()))


def test_two_gaussians_classes_are_the_mode_within_one_width():
    import torch

    from hireps_torch.envs.toy import ContextualTwoGaussians, TwoGaussians

    task = TwoGaussians(width=0.5)
    theta = torch.tensor([[-2.0, -2.0], [2.3, 2.3], [2.4, 2.4], [0.0, 0.0]], dtype=torch.float64)
    # 0.3 * sqrt(2) = 0.42 from (2, 2) is within 0.5; 0.4 * sqrt(2) = 0.57 is not
    assert task.solution_class(None, theta).tolist() == [0, 1, -1, -1]
    assert task.n_classes == 2
    ctx_task = ContextualTwoGaussians(width=0.5)
    ctx = torch.tensor([[0.5], [0.5]], dtype=torch.float64)
    at = torch.tensor([[-1.5, -2.5], [2.5, 1.5]], dtype=torch.float64)  # mu_m(0.5)
    assert ctx_task.solution_class(ctx, at).tolist() == [0, 1]
    assert ctx_task.solution_class(-ctx, at).tolist() == [-1, -1]  # the modes moved away
