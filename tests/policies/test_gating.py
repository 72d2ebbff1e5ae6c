import pytest
import torch

from hireps_torch.policies import ConstantGating, HierarchicalPolicy, LinearGaussian, SoftmaxGating


def test_context_free_fit_is_weighted_mean_of_targets(gen):
    g = SoftmaxGating(0, 3)
    t = torch.softmax(torch.randn(40, 3, generator=gen, dtype=torch.float64), -1)
    w = torch.rand(40, generator=gen, dtype=torch.float64)
    g.weighted_fit(torch.zeros(40, 0), t, w)
    expected = (w[:, None] * t).sum(0) / w.sum()
    assert torch.allclose(g.probs(torch.zeros(1, 0))[0], expected, atol=1e-12)


def test_fit_is_stationary_point_of_weighted_cross_entropy(gen):
    x = torch.randn(200, 2, generator=gen, dtype=torch.float64)
    true_w = torch.tensor([[2.0, 0.0], [-2.0, 1.0], [0.0, -1.0]], dtype=torch.float64)
    t = torch.softmax(x @ true_w.T, -1)
    w = torch.rand(200, generator=gen, dtype=torch.float64)
    g = SoftmaxGating(2, 3, l2=1e-6)
    g.weighted_fit(x, t, w)
    W = g.weight.detach().clone().requires_grad_()
    b = g.bias.detach().clone().requires_grad_()
    wn = w / w.sum()
    loss = -(wn[:, None] * t * torch.log_softmax(x @ W.T + b, -1)).sum() + 0.5e-6 * (W**2).sum()
    loss.backward()
    assert float(W.grad.abs().max()) < 1e-6 and float(b.grad.abs().max()) < 1e-6
    # soft targets from a softmax model are recovered
    assert torch.allclose(g.probs(x), t, atol=1e-3)


def test_pruned_options_have_zero_probability():
    g = SoftmaxGating(1, 3)
    g.active[1] = False
    p = g.probs(torch.linspace(-2, 2, 5, dtype=torch.float64)[:, None])
    assert bool((p[:, 1] == 0).all())
    assert torch.allclose(p.sum(-1), torch.ones(5, dtype=torch.float64))


def test_bad_shapes_raise():
    g = SoftmaxGating(2, 3)
    with pytest.raises(ValueError, match=r"gating features must have shape \(N, 2\)"):
        g.probs(torch.zeros(4, 1))
    with pytest.raises(ValueError, match=r"targets must have shape \(4, 3\)"):
        g.weighted_fit(torch.zeros(4, 2), torch.zeros(4, 2), torch.ones(4))
    with pytest.raises(ValueError, match="n_options must be >= 1"):
        SoftmaxGating(2, 0)


def test_constant_gating_assigns_the_nearest_kmeans_centroid_and_never_changes(gen):
    box = torch.tensor([3.14, 50.0], dtype=torch.float64)
    pts = (2 * torch.rand(1000, 2, generator=gen, dtype=torch.float64) - 1) * box
    g = ConstantGating.from_kmeans(pts, 5, seed=0)
    assert g.centroids.shape == (5, 2)
    x = torch.randn(200, 2, generator=gen, dtype=torch.float64) * box
    lp = g.log_probs(x)
    nearest = torch.cdist(x, g.centroids).argmin(-1)
    assert torch.equal(lp.argmax(-1), nearest)
    assert torch.equal(lp.exp().sum(-1), torch.ones(200, dtype=torch.float64))
    before = {k: v.clone() for k, v in g.state_dict().items()}
    g.weighted_fit(x, torch.softmax(torch.randn(200, 5, generator=gen), -1), torch.ones(200))
    assert all(torch.equal(before[k], v) for k, v in g.state_dict().items())
    # in a hierarchical policy, each option only learns from its own region
    opts = [LinearGaussian(2, 1, torch.zeros(1), torch.ones(1)) for _ in range(5)]
    pol = HierarchicalPolicy(g, opts)
    a = torch.randn(200, 1, generator=gen, dtype=torch.float64)
    resp = pol.responsibilities(x, a)
    assert torch.equal(resp.argmax(-1), nearest)
    assert float(resp.max(-1).values.min()) == 1.0


def test_constant_gating_needs_enough_points():
    with pytest.raises(ValueError, match=r"M >= n_options = 5, got \(3, 2\)"):
        ConstantGating.from_kmeans(torch.zeros(3, 2), 5)


def test_newton_hessian_is_the_weighted_cross_entropys_hessian(gen):
    """The gating fit's Newton Hessian (each option pair and feature pair computed once) equals
    autograd's Hessian of sum_i w_i sum_o t_io (-log pi(o | x_i)), also with a leading S."""
    from hireps_torch.policies.gating import _entries, _feature_pairs, _hessian

    S, N, F, O = 2, 60, 3, 4
    x = torch.randn(S, N, F, generator=gen, dtype=torch.float64)
    X = torch.cat([torch.ones(S, N, 1, dtype=torch.float64), x], -1)
    t = torch.softmax(torch.randn(S, N, O, generator=gen, dtype=torch.float64), -1)
    w = torch.rand(S, N, generator=gen, dtype=torch.float64)
    theta = torch.randn(S, O, F + 1, generator=gen, dtype=torch.float64)
    p = torch.softmax(X @ theta.mT, -1)
    H = _hessian(_feature_pairs(X), w, p, _entries(O, F + 1, x.device))
    assert H.shape == (S, O, F + 1, O, F + 1)
    for s in range(S):

        def loss(th, s=s):
            return -(w[s, :, None] * t[s] * torch.log_softmax(X[s] @ th.T, -1)).sum()

        expected = torch.autograd.functional.hessian(loss, theta[s])
        assert torch.allclose(H[s], expected, rtol=1e-10, atol=1e-12)
