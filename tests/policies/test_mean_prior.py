"""The coefficient prior of the linear-Gaussian options (``mean_prior``): its posterior mode
against the objective it claims to minimise, its limits, its invariance to the features' units
and its plumbing through the hierarchical policy and the algorithms."""

import pytest
import torch

from hireps_torch.algorithms import REPS, EpisodicHiREPS
from hireps_torch.policies import HierarchicalPolicy, LinearGaussian
from hireps_torch.policies.linear_gaussian import map_linear_regression


def _data(gen, N=12, F=3, D=2):
    x = 5.0 + 3.0 * torch.randn(N, F, generator=gen, dtype=torch.float64)
    y = x @ torch.randn(D, F, generator=gen, dtype=torch.float64).T + torch.randn(
        N, D, generator=gen, dtype=torch.float64
    )
    w = torch.rand(N, generator=gen, dtype=torch.float64) ** 3  # few effective samples
    W0 = torch.randn(D, F, generator=gen, dtype=torch.float64)
    b0 = torch.randn(D, generator=gen, dtype=torch.float64)
    return x, y, w, W0, b0


def _objective(W, b, x, y, w, W0, b0, k, ridge):
    """The MAP objective written out in the original units (not the code's coordinates)."""
    wn = w / w.sum()
    n_eff = 1.0 / (wn**2).sum()
    m = (wn[:, None] * x).sum(0)
    s = (wn[:, None] * (x - m) ** 2).sum(0).sqrt()
    beta = torch.cat([(b + W @ m)[None], (W * s).T])
    beta0 = torch.cat([(b0 + W0 @ m)[None], (W0 * s).T])
    fit = (wn * ((y - x @ W.T - b) ** 2).sum(1)).sum()
    return fit + k / n_eff * ((beta - beta0) ** 2).sum() + ridge * (W**2).sum()


@pytest.mark.parametrize("k, ridge", [(0.5, 0.0), (4.0, 0.0), (4.0, 1e-3)])
def test_map_fit_is_the_minimiser_of_its_objective(gen, k, ridge):
    x, y, w, W0, b0 = _data(gen)
    W, b = map_linear_regression(x, y, w, W0, b0, k, ridge)
    Wg, bg = W.clone().requires_grad_(True), b.clone().requires_grad_(True)
    J = _objective(Wg, bg, x, y, w, W0, b0, k, ridge)
    gW, gb = torch.autograd.grad(J, (Wg, bg))
    # the objective is convex: a zero gradient makes the closed form its minimiser
    scale = float(J.detach()) + 1.0
    assert float(gW.abs().max()) < 1e-9 * scale * float(x.abs().max())
    assert float(gb.abs().max()) < 1e-9 * scale
    # and moving away in any direction raises it
    for _ in range(5):
        dW = 1e-3 * torch.randn(W.shape, generator=gen, dtype=torch.float64)
        assert float(_objective(W + dW, b, x, y, w, W0, b0, k, ridge)) > float(J.detach())


def test_map_fit_limits(gen):
    x, y, w, W0, b0 = _data(gen)
    W, b = map_linear_regression(x, y, w, W0, b0, 1e12)  # the prior wins: nothing moves
    assert torch.allclose(W, W0, atol=1e-8) and torch.allclose(b, b0, atol=1e-8)
    W, b = map_linear_regression(x, y, w, W0, b0, 1e-12)  # the data win: least squares
    X = torch.cat([torch.ones(len(x), 1, dtype=torch.float64), x], 1)
    beta = torch.linalg.lstsq(X * w.sqrt()[:, None], y * w.sqrt()[:, None]).solution
    assert torch.allclose(W, beta[1:].T, atol=1e-6) and torch.allclose(b, beta[0], atol=1e-6)


def test_map_fit_does_not_depend_on_the_features_units(gen):
    """Centred and scaled features: shifting and rescaling an input (and the prior with it)
    gives the same predicted means."""
    x, y, w, W0, b0 = _data(gen)
    W, b = map_linear_regression(x, y, w, W0, b0, 3.0)
    a = torch.tensor([100.0, 0.01, -2.0], dtype=torch.float64)
    c = torch.tensor([-7.0, 1e3, 0.5], dtype=torch.float64)
    x2 = x * a + c  # W2 x2 + b2 = W x + b  <=>  W2 = W / a, b2 = b - W2 c
    W02, b02 = W0 / a, b0 - (W0 / a) @ c
    W2, b2 = map_linear_regression(x2, y, w, W02, b02, 3.0)
    assert torch.allclose(x2 @ W2.T + b2, x @ W.T + b, rtol=1e-9, atol=1e-9)


def test_an_input_without_spread_keeps_its_old_slope(gen):
    x, y, w, W0, b0 = _data(gen)
    x[:, 1] = 2.5
    W, _ = map_linear_regression(x, y, w, W0, b0, 1.0)
    assert torch.allclose(W[:, 1], W0[:, 1], atol=1e-12)
    assert not torch.allclose(W[:, 0], W0[:, 0], atol=1e-3)


def test_prior_shrinks_with_more_effective_samples(gen):
    """The step toward the data is n_eff / (n_eff + k) along each scaled direction: with many
    samples the prior hardly matters, with few it holds the option in place."""
    F, D, k = 2, 1, 5.0
    W0, b0 = torch.zeros(D, F, dtype=torch.float64), torch.zeros(D, dtype=torch.float64)
    steps = []
    for N in (4, 400):
        x = torch.randn(N, F, generator=gen, dtype=torch.float64)
        y = x @ torch.tensor([[1.0, -2.0]], dtype=torch.float64).T + 3.0
        w = torch.ones(N, dtype=torch.float64)
        W, b = map_linear_regression(x, y, w, W0, b0, k)
        centre = float(b + W @ x.mean(0))  # the mean at the samples' centre
        assert centre == pytest.approx(float(y.mean()) * N / (N + k), rel=1e-9)
        steps.append(centre / float(y.mean()))
    assert steps[0] < 0.5 < 0.98 < steps[1]


def test_option_refit_uses_the_prior_and_zero_is_plain_least_squares(gen):
    x, y, w, _, _ = _data(gen)
    plain, zero, prior = LinearGaussian(3, 2), LinearGaussian(3, 2, mean_prior=0.0), None
    prior = LinearGaussian(3, 2, mean_prior=10.0)
    for p in (plain, zero, prior):
        p.weighted_fit(x, y, w)
    assert torch.equal(plain.weight, zero.weight) and torch.equal(plain.bias, zero.bias)
    W, b = map_linear_regression(x, y, w, torch.zeros(2, 3), torch.zeros(2), 10.0, 1e-6)
    assert torch.allclose(prior.weight, W, atol=1e-12) and torch.allclose(prior.bias, b)
    assert float(prior.weight.abs().max()) < float(plain.weight.abs().max())
    with pytest.raises(ValueError, match="mean_prior must be finite and >= 0, got -1"):
        LinearGaussian(3, 2, mean_prior=-1.0)


def test_mean_prior_reaches_every_option_through_create():
    pol = HierarchicalPolicy.create(3, 2, 1, mean_prior=7.0)
    assert [o.mean_prior for o in pol.sub_policies] == [7.0, 7.0, 7.0]
    algo = EpisodicHiREPS.create(2, context_dim=1, n_options=2, mean_prior=2.0, seed=0)
    assert {o.mean_prior for o in algo.policy.sub_policies} == {2.0}
    assert REPS.create(2, mean_prior=3.0).policy.sub_policies[0].mean_prior == 3.0
    with pytest.raises(ValueError, match="mean_prior"):
        HierarchicalPolicy.create(2, 1, 1, mean_prior=float("nan"))
