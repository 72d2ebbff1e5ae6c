"""Time-indexed HiREPS: the per-step dual's constraints, its reduction to the episodic dual,
bad input."""

import math

import pytest
import torch

from hireps_torch import solve_episodic_dual, solve_time_indexed_dual
from hireps_torch.dual import DegenerateWeightsWarning
from hireps_torch.features import QuadraticFeatures

EPS = torch.tensor([0.3, 0.5, 0.8], dtype=torch.float64)


def random_episodes(gen, N=60, K=3, O=3):
    """N episodes of K steps in 2-D: s_{k+1} = s_k + 0.5 theta_k, rewards depend on both."""
    s = torch.zeros(N, K, 2, dtype=torch.float64)
    s[:, 0] = torch.randn(N, 2, generator=gen, dtype=torch.float64)
    theta = torch.randn(N, K, 2, generator=gen, dtype=torch.float64)
    for k in range(1, K):
        s[:, k] = s[:, k - 1] + 0.5 * theta[:, k - 1]
    noise = 0.1 * torch.randn(N, K, generator=gen, dtype=torch.float64)
    rewards = -(s + theta - 1.0).pow(2).sum(-1) + noise
    phi = QuadraticFeatures(2)(s)  # (N, K, 5)
    lr = torch.log_softmax(2.0 * torch.randn(N, K, O, generator=gen, dtype=torch.float64), -1)
    return rewards, phi, lr


def mean_entropy(lr):
    """Mean responsibility entropy per step: (N, K, O) -> (K,)."""
    return -(lr.exp() * lr).sum(-1).mean(0)


def chained_violation(w, phi, phi1):
    """max |sum_i w_1i phi_1i - phi_hat_1|, |sum_i w_ki phi_ki - sum_i w_{k-1,i} phi_ki|."""
    errs = [(w[0] @ phi[:, 0] - phi1).abs().max()]
    errs += [(w[k] @ phi[:, k] - w[k - 1] @ phi[:, k]).abs().max() for k in range(1, w.shape[0])]
    return float(torch.stack(errs).max())


# ---- the dual -------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(3))
def test_dual_meets_per_step_kl_entropy_and_chained_features(seed):
    R, phi, lr = random_episodes(torch.Generator().manual_seed(seed))
    kappa = 0.7 * mean_entropy(lr)
    sol = solve_time_indexed_dual(R, phi, epsilon=EPS, log_responsibilities=lr, kappa=kappa)
    assert sol.converged
    assert sol.weights.shape == (3, 60, 3) and sol.v.shape == (3, 5)
    assert bool((sol.weights >= 0).all())
    assert torch.allclose(sol.weights.sum((1, 2)), torch.ones(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(sol.sample_weights, sol.weights.sum(-1))
    # every step gets its own epsilon, and the realised KL is recomputed here
    kl = (sol.weights * (sol.weights.log() - lr.transpose(0, 1) + math.log(60))).sum((1, 2))
    assert torch.allclose(kl, EPS, atol=1e-3)
    assert torch.allclose(sol.kl, kl, atol=1e-10)
    assert bool((sol.cross_entropy <= kappa + 1e-3).all())
    err = chained_violation(sol.sample_weights, phi, phi[:, 0].mean(0))
    assert err < 1e-5 and sol.feature_error < 1e-5
    assert bool((sol.effective_sample_size >= 1).all() and (sol.effective_sample_size <= 60).all())


def test_weights_are_the_bellman_error_softmax_and_the_dual_value_is_the_formula(gen):
    R, phi, lr = random_episodes(gen)
    kappa = 0.7 * mean_entropy(lr)
    sol = solve_time_indexed_dual(R, phi, epsilon=EPS, log_responsibilities=lr, kappa=kappa)
    v, eta, xi = sol.v, sol.eta, sol.xi
    assert bool((xi > 0).all())  # 0.7 of the prior entropy binds on every step here
    # delta_k,i = R_k,i + v_{k+1}^T phi(s_{k+1,i}) - v_k^T phi(s_k,i), V_{K+1} = 0
    values = torch.einsum("nkf,kf->nk", phi, v)  # V_k(s_k,i)
    next_values = torch.cat([values[:, 1:], torch.zeros(60, 1, dtype=torch.float64)], 1)
    delta = R + next_values - values
    A = delta[..., None] + (eta + xi)[None, :, None] * lr  # (N, K, O)
    for k in range(3):
        expected = torch.softmax((A[:, k] / eta[k]).flatten(), 0).reshape(60, 3)
        assert torch.allclose(sol.weights[k], expected, atol=1e-9)
    # g = v_1^T phi_hat_1 + sum_k [eta_k eps_k + xi_k kappa_k + eta_k log mean_io exp(A/eta_k)]
    lse = torch.stack([torch.logsumexp((A[:, k] / eta[k]).flatten(), 0) for k in range(3)])
    g = v[0] @ phi[:, 0].mean(0) + (eta * EPS + xi * kappa + eta * (lse - math.log(60))).sum()
    assert sol.dual_value == pytest.approx(float(g), rel=1e-9, abs=1e-9)


def test_one_step_is_the_episodic_dual(gen):
    R, phi, lr = random_episodes(gen, K=1)
    kappa = 0.7 * float(mean_entropy(lr)[0])
    kw = dict(epsilon=0.5, log_responsibilities=lr[:, 0], kappa=kappa)
    ep = solve_episodic_dual(R[:, 0], context_features=phi[:, 0], **kw)
    for phi1 in (None, phi[:, 0].mean(0)):
        ti = solve_time_indexed_dual(
            R, phi, epsilon=0.5, log_responsibilities=lr, kappa=kappa, initial_features=phi1
        )
        assert torch.allclose(ti.weights[0], ep.weights, atol=1e-6)
        assert float(ti.eta[0]) == pytest.approx(ep.eta, rel=1e-5)
        assert ti.dual_value == pytest.approx(ep.dual_value, rel=1e-6)
        step = ti.step(0)
        assert torch.allclose(step.v, ep.v, atol=1e-4) and step.kl == pytest.approx(ep.kl)


def test_given_initial_features_are_matched(gen):
    R, phi, _ = random_episodes(gen)
    phi1 = phi[:, 0].mean(0) + 0.05 * phi[:, 0].std(0)  # a start distribution the data can reach
    sol = solve_time_indexed_dual(R, phi, epsilon=0.5, initial_features=phi1)
    assert sol.converged
    assert torch.allclose(sol.kl, torch.full((3,), 0.5, dtype=torch.float64), atol=1e-3)
    assert chained_violation(sol.sample_weights, phi, phi1) < 1e-5


def test_infinite_kappa_leaves_that_step_unbounded(gen):
    R, phi, lr = random_episodes(gen)
    H = mean_entropy(lr)
    free = solve_time_indexed_dual(R, phi, epsilon=EPS, log_responsibilities=lr)
    # step 1 without a bound and with a loose one (inactive: xi = 0) agree; the others bind
    tight = 0.7 * H
    loose = tight.clone()
    loose[1] = free.cross_entropy[1] + 0.1
    unbounded = tight.clone()
    unbounded[1] = math.inf
    a = solve_time_indexed_dual(R, phi, epsilon=EPS, log_responsibilities=lr, kappa=loose)
    b = solve_time_indexed_dual(R, phi, epsilon=EPS, log_responsibilities=lr, kappa=unbounded)
    assert float(a.xi[1]) == 0.0 and float(b.xi[1]) == 0.0
    assert bool((b.xi[[0, 2]] > 0).all())
    assert torch.allclose(a.weights, b.weights, atol=1e-8)


def test_no_reward_information_keeps_the_old_distribution(gen):
    _, phi, lr = random_episodes(gen)
    sol = solve_time_indexed_dual(torch.ones(60, 3), phi, epsilon=0.5, log_responsibilities=lr)
    assert bool(torch.isinf(sol.eta).all())
    assert torch.allclose(sol.weights, lr.transpose(0, 1).exp() / 60)


def test_epsilon_beyond_log_n_warns_naming_the_step(gen):
    R, phi, _ = random_episodes(gen, N=20)
    with pytest.warns(DegenerateWeightsWarning, match=r"epsilon\[1\] = 5 >= log N"):
        sol = solve_time_indexed_dual(R, phi, epsilon=torch.tensor([0.3, 5.0, 0.3]))
    assert bool(torch.isfinite(sol.weights).all())


def test_dual_bad_input_names_the_value(gen):
    R, phi, lr = random_episodes(gen)
    with pytest.raises(ValueError, match=r"rewards must have shape \(N, K\)"):
        solve_time_indexed_dual(R[:, 0], phi, epsilon=0.5)
    with pytest.raises(ValueError, match=r"features must have shape \(N, K, F\) = \(60, 3, F\)"):
        solve_time_indexed_dual(R, phi[:, :2], epsilon=0.5)
    with pytest.raises(ValueError, match=r"log_responsibilities must have shape \(N, K, O\)"):
        solve_time_indexed_dual(R, phi, epsilon=0.5, log_responsibilities=lr[:, 0])
    with pytest.raises(ValueError, match=r"initial_features must have shape \(5,\)"):
        solve_time_indexed_dual(R, phi, epsilon=0.5, initial_features=torch.zeros(4))
    with pytest.raises(ValueError, match=r"epsilon must be a float or have shape \(3,\)"):
        solve_time_indexed_dual(R, phi, epsilon=torch.tensor([0.5, 0.5]))
    with pytest.raises(ValueError, match="epsilon must be finite and > 0"):
        solve_time_indexed_dual(R, phi, epsilon=torch.tensor([0.5, 0.0, 0.5]))
    with pytest.raises(ValueError, match="kappa must be >= 0"):
        solve_time_indexed_dual(R, phi, epsilon=0.5, log_responsibilities=lr, kappa=-0.1)
    with pytest.raises(ValueError, match=r"K >= 1"):
        solve_time_indexed_dual(R[:, :0], phi[:, :0], epsilon=0.5)
    with pytest.raises(ValueError, match="at least 2 samples, got N = 1"):
        solve_time_indexed_dual(R[:1], phi[:1], epsilon=0.5)
    bad = R.clone()
    bad[4, 1] = math.nan
    with pytest.raises(ValueError, match=r"rewards contains 1 non-finite value.*\(4, 1\)"):
        solve_time_indexed_dual(bad, phi, epsilon=0.5)
    bad_phi = phi.clone()
    bad_phi[2, 2, 3] = math.inf
    with pytest.raises(ValueError, match=r"features contains 1 non-finite value.*\(2, 2, 3\)"):
        solve_time_indexed_dual(R, bad_phi, epsilon=0.5)
    with pytest.raises(ValueError, match=r"step must be in \[0, 3\)"):
        solve_time_indexed_dual(R, phi, epsilon=0.5).step(3)
