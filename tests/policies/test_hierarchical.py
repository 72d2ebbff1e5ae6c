import pytest
import torch

from hireps_torch.features import QuadraticFeatures
from hireps_torch.policies import HierarchicalPolicy


def make(gen, O=3, S=1, D=2):
    return HierarchicalPolicy.create(
        O, S, D, init_std=1.0, spread=2.0, gating_features=QuadraticFeatures(S), generator=gen
    )


def test_marginal_log_prob_is_logsumexp_of_joint(gen):
    pol = make(gen)
    pol.gating.weight.data = torch.randn(3, 2, generator=gen, dtype=torch.float64)
    s = torch.randn(30, 1, generator=gen, dtype=torch.float64)
    th, opt = pol.sample(s, gen)
    assert th.shape == (30, 2) and opt.shape == (30,)
    gate = pol.gating.probs(pol.gating_features(s))
    dens = torch.stack([o.log_prob(s, th).exp() for o in pol.options], -1)
    assert torch.allclose(pol.log_prob(s, th), torch.log((gate * dens).sum(-1)), atol=1e-10)
    resp = pol.responsibilities(s, th)
    assert torch.allclose(resp, gate * dens / (gate * dens).sum(-1, keepdim=True), atol=1e-10)


def test_sampling_follows_gating(gen):
    pol = make(gen, O=2, S=0)
    pol.gating.bias.data = torch.log(torch.tensor([0.2, 0.8], dtype=torch.float64))
    _, opt = pol.sample(torch.zeros(20000, 0), gen)
    assert float((opt == 1).double().mean()) == pytest.approx(0.8, abs=0.02)


def test_weighted_fit_with_hard_assignments_fits_each_option(gen):
    pol = make(gen, O=2, S=0)
    a = torch.randn(100, 2, generator=gen, dtype=torch.float64) * 0.1 + 3.0
    b = torch.randn(100, 2, generator=gen, dtype=torch.float64) * 0.1 - 3.0
    th = torch.cat([a, b])
    w = torch.zeros(200, 2, dtype=torch.float64)
    w[:100, 0] = 1.0
    w[100:, 1] = 3.0
    pol.weighted_fit(torch.zeros(200, 0), th, w)
    assert torch.allclose(pol.options[0].bias, a.mean(0), atol=1e-10)
    assert torch.allclose(pol.options[1].bias, b.mean(0), atol=1e-10)
    prior = pol.gating.probs(torch.zeros(1, 0))[0]
    assert torch.allclose(prior, torch.tensor([0.25, 0.75], dtype=torch.float64), atol=1e-12)


def test_prune_removes_low_mass_options_but_keeps_shapes(gen):
    pol = make(gen, O=3, S=0)
    pol.gating.bias.data = torch.log(torch.tensor([1e-6, 0.5, 0.5], dtype=torch.float64))
    sd_keys = {k: v.shape for k, v in pol.state_dict().items()}
    assert pol.prune(torch.zeros(1, 0), threshold=1e-4) == [0]
    assert pol.active.tolist() == [False, True, True]
    th, opt = pol.sample(torch.zeros(500, 0), gen)
    assert bool((opt != 0).all())
    assert bool(torch.isfinite(pol.log_prob(torch.zeros(500, 0), th)).all())
    assert {k: v.shape for k, v in pol.state_dict().items()} == sd_keys


def test_state_dict_round_trips_exactly(gen):
    pol = make(gen)
    s = torch.randn(50, 1, generator=gen, dtype=torch.float64)
    th, _ = pol.sample(s, gen)
    pol.weighted_fit(s, th, torch.rand(50, 3, generator=gen, dtype=torch.float64))
    pol.gating.active[2] = False
    fresh = make(torch.Generator().manual_seed(99))
    fresh.load_state_dict(pol.state_dict())
    for k, v in pol.state_dict().items():
        assert torch.equal(v, fresh.state_dict()[k]), k
    assert torch.equal(pol.log_prob(s, th), fresh.log_prob(s, th))


def test_mean_action_uses_most_probable_option(gen):
    pol = make(gen, O=2, S=0)
    pol.gating.bias.data = torch.tensor([0.0, 1.0], dtype=torch.float64)
    th, opt = pol.mean_action(torch.zeros(4, 0))
    assert opt.tolist() == [1, 1, 1, 1]
    assert torch.allclose(th, pol.options[1].bias.expand(4, 2))


def test_bad_input_raises(gen):
    pol = make(gen)
    with pytest.raises(ValueError, match=r"context must have shape \(N, C\)"):
        pol.sample(torch.zeros(3), gen)
    with pytest.raises(ValueError, match="non-finite"):
        pol.sample(torch.tensor([[float("nan")]]), gen)
    with pytest.raises(ValueError, match=r"weights must have shape \(2, 3\)"):
        pol.weighted_fit(torch.zeros(2, 1), torch.zeros(2, 2), torch.ones(2, 2))


def test_create_refuses_more_options_than_it_can_build_quickly():
    # before: 2e9 options were built one module at a time, for hours, without a word
    with pytest.raises(ValueError, match="n_options must be at most 10,000 .* got 2,000,000,000"):
        HierarchicalPolicy.create(2 * 10**9, 1, 1)
    with pytest.raises(ValueError, match="at most 10,000"):
        HierarchicalPolicy.create(10**4 + 1, 1, 1)


def test_per_option_initial_means_are_used_exactly(gen):
    means = torch.tensor([[-1.0, 0.5], [2.0, 3.0], [0.0, -4.0]], dtype=torch.float64)
    pol = HierarchicalPolicy.create(3, 1, 2, init_mean=means, init_std=0.3, generator=gen)
    assert torch.equal(torch.stack([o.bias for o in pol.sub_policies]), means)
    with pytest.raises(ValueError, match=r"init_mean must have shape \(D,\) = \(2,\) or \(O, D\)"):
        HierarchicalPolicy.create(3, 1, 2, init_mean=torch.zeros(2, 2))


@pytest.mark.parametrize("O,D,N", [(3, 1, 5), (5, 2, 40), (100, 1, 20)])
def test_sample_draws_the_option_then_one_normal_per_sample(O, D, N):
    # the stream a run's reproducibility rests on: torch.multinomial's option, then one (N, D)
    # standard normal, theta = mean_o + L_o noise for the chosen o (nothing else drawn)
    pol = HierarchicalPolicy.create(
        O,
        2,
        D,
        init_std=0.5,
        gating_features=QuadraticFeatures(2),
        generator=torch.Generator().manual_seed(1),
    )
    g0 = torch.Generator().manual_seed(0)
    pol.gating.weight.data = torch.randn(pol.gating.weight.shape, generator=g0, dtype=torch.float64)
    for o in pol.sub_policies:  # options of distinct shapes
        o.set_covariance(torch.diag(torch.rand(D, generator=g0, dtype=torch.float64) + 0.1))
    ctx = torch.randn(N, 2, generator=g0, dtype=torch.float64)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    theta, option = pol.sample(ctx, g1)
    gf, pf = pol.gating_features(ctx), pol.policy_features(ctx)
    ref_opt = torch.multinomial(pol.gating.probs(gf), 1, generator=g2).squeeze(-1)
    noise = torch.randn(N, D, generator=g2, dtype=torch.float64)
    subs = pol.sub_policies
    ref = torch.stack(
        [subs[o].mean(pf[i : i + 1])[0] + subs[o].chol @ noise[i] for i, o in enumerate(ref_opt)]
    )
    assert torch.equal(option, ref_opt)
    torch.testing.assert_close(theta, ref, rtol=1e-12, atol=1e-12)
    assert torch.equal(g1.get_state(), g2.get_state())
