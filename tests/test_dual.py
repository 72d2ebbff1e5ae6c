"""The episodic HiREPS dual: gradients, constraints at the optimum, invariances, bad input."""

import math
import warnings

import pytest
import torch

from hireps_torch.dual import (
    DegenerateWeightsWarning,
    InfeasibleConstraintsWarning,
    solve_episodic_dual,
    solve_infinite_horizon_dual,
    solve_reps_dual,
)
from hireps_torch.dual.problem import DualProblem


def random_problem(gen, N=200, O=1, F=0, scale=3.0):
    R = torch.randn(N, generator=gen, dtype=torch.float64) * scale + 5.0
    lr = None
    if O > 1:
        lr = torch.log_softmax(2.0 * torch.randn(N, O, generator=gen, dtype=torch.float64), -1)
    phi = torch.randn(N, F, generator=gen, dtype=torch.float64) if F else None
    if phi is not None:  # make returns depend on the context, as in a contextual task
        R = R + 2.0 * phi[:, 0]
    return R, lr, phi


def mean_entropy(lr):
    return float(-(lr.exp() * lr).sum(-1).mean())


# ---- hand-checked tiny case -----------------------------------------------------------------
def test_two_samples_closed_form():
    # One option, no context: w ∝ exp(R/eta) and KL(w || uniform) = epsilon.
    R = torch.tensor([0.0, 1.0], dtype=torch.float64)
    sol = solve_episodic_dual(R, epsilon=0.1)
    w = sol.sample_weights
    assert torch.allclose(w, torch.softmax(R / sol.eta, 0), atol=1e-10)
    kl = float((w * torch.log(2 * w)).sum())
    assert kl == pytest.approx(0.1, abs=1e-6)
    assert w[1] > w[0]


# ---- gradient vs finite differences ---------------------------------------------------------
def make_problem(gen, K=2, N=40, O=3, P=4, xi_on=True, S=2):
    """S independent random problems (the population form DualProblem holds)."""
    R = torch.randn(S, K, N, generator=gen, dtype=torch.float64)
    lr = torch.log_softmax(torch.randn(S, K, N, O, generator=gen, dtype=torch.float64), -1)
    D = torch.randn(S, K, N, P, generator=gen, dtype=torch.float64) if P else None
    c = torch.randn(S, P, generator=gen, dtype=torch.float64) if P else None
    eps = torch.linspace(0.3, 0.7, K, dtype=torch.float64).repeat(S, 1)
    kap = torch.linspace(0.5, 0.6, K, dtype=torch.float64).repeat(S, 1)
    prob = DualProblem(R, D, c, lr, eps, kap)
    prob.xi_on[:] = xi_on
    return prob


@pytest.mark.parametrize("O,P,xi_on", [(1, 0, False), (3, 4, False), (3, 4, True), (2, 0, True)])
def test_dual_gradient_matches_finite_differences(gen, O, P, xi_on):
    # each problem's gradient is the derivative of its own dual (and of no other's)
    prob = make_problem(gen, O=O, P=P, xi_on=xi_on)
    x = 0.5 * torch.randn(prob.S, 2 * prob.K + prob.P, generator=gen, dtype=torch.float64)
    _, grad, _ = prob.evaluate(x)
    h = 1e-6
    fd = torch.zeros(prob.S, *x.shape, dtype=torch.float64)  # d g_s / d x_tj
    for t in range(prob.S):
        for j in range(x.shape[1]):
            e = torch.zeros_like(x)
            e[t, j] = h
            fd[:, t, j] = (prob.evaluate(x + e)[0] - prob.evaluate(x - e)[0]) / (2 * h)
    own = torch.stack([fd[s, s] for s in range(prob.S)])
    assert torch.allclose(grad, own, atol=1e-7, rtol=1e-6)
    for s in range(prob.S):
        others = torch.cat([fd[s, :s], fd[s, s + 1 :]])
        assert float(others.abs().max()) == 0.0


def test_curvature_matches_finite_difference_hessian_at_optimum(gen):
    # At the optimum the first-order term of the log-parametrisation vanishes, so the
    # preconditioner equals the true Hessian there.
    R, lr, phi = random_problem(gen, N=60, O=3, F=2)
    sol = solve_episodic_dual(
        R, epsilon=0.5, log_responsibilities=lr, context_features=phi, kappa=0.6 * mean_entropy(lr)
    )
    Rs = (R - R.mean()) / (R - R.mean()).std()
    D = -(phi - phi.mean(0))[None]
    prob = DualProblem(
        Rs[None, None],
        D[None],
        None,
        lr[None, None],
        torch.tensor([[0.5]], dtype=torch.float64),
        torch.tensor([[0.6 * mean_entropy(lr)]], dtype=torch.float64),
    )
    prob.xi_on[:] = True
    scale = float((R - R.mean()).std())
    x = torch.cat(
        [torch.tensor([math.log(sol.eta / scale), math.log(sol.xi / scale)]), sol.v / scale]
    ).to(torch.float64)[None]
    H = torch.zeros(4, 4, dtype=torch.float64)
    h = 1e-5
    for j in range(4):
        e = torch.zeros(1, 4, dtype=torch.float64)
        e[0, j] = h
        H[:, j] = (prob.evaluate(x + e)[1] - prob.evaluate(x - e)[1])[0] / (2 * h)
    assert torch.allclose(prob.curvature(x)[0], H, atol=1e-5, rtol=1e-4)


def test_dual_derivatives_are_the_constraint_residuals(gen):
    # dg/d(eta) = eps - KL and dg/d(xi) = kappa - cross-entropy: the optimum sits on the bounds.
    prob = make_problem(gen, K=1, N=50, O=3, P=0, S=1)
    x = torch.tensor([[0.3, -0.5]], dtype=torch.float64)
    _, grad, _ = prob.evaluate(x)
    w = prob.evaluate(x)[2]
    lr = prob.lr
    kl = float((w * (torch.log(w) - lr + math.log(50))).sum())
    ce = float(-(w * lr).sum())
    eta, xi = math.exp(0.3), math.exp(-0.5)
    assert float(grad[0, 0]) / eta == pytest.approx(float(prob.eps[0, 0]) - kl, abs=1e-10)
    assert float(grad[0, 1]) / xi == pytest.approx(float(prob.kappa[0, 0]) - ce, abs=1e-10)


# ---- constraint satisfaction ----------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    "O,F,use_kappa", [(1, 0, False), (1, 3, False), (4, 0, False), (4, 0, True), (4, 3, True)]
)
def test_constraints_hold_at_optimum(seed, O, F, use_kappa):
    gen = torch.Generator().manual_seed(seed)
    N = 300
    R, lr, phi = random_problem(gen, N=N, O=O, F=F)
    eps = [0.1, 0.5, 1.0, 2.0][seed]
    kappa = 0.6 * mean_entropy(lr) if use_kappa else None
    sol = solve_episodic_dual(
        R, epsilon=eps, log_responsibilities=lr, context_features=phi, kappa=kappa
    )
    assert sol.converged
    assert sol.weights.shape == (N, O)
    assert float(sol.weights.sum()) == pytest.approx(1.0, abs=1e-12)
    assert bool((sol.weights >= 0).all())
    assert sol.kl == pytest.approx(eps, abs=1e-3)
    if use_kappa:
        assert sol.xi > 0  # 0.6 of the prior entropy is always binding here
        assert sol.cross_entropy == pytest.approx(kappa, abs=1e-3)
    else:
        assert sol.xi == 0.0
    if F:
        err = (sol.sample_weights @ phi - phi.mean(0)).abs().max()
        assert float(err) < 1e-5
        assert sol.feature_error < 1e-5
    assert 1.0 <= sol.effective_sample_size <= N


def test_inactive_entropy_bound_gives_xi_zero(gen):
    R, lr, _ = random_problem(gen, N=200, O=3)
    free = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr)
    loose = solve_episodic_dual(
        R, epsilon=0.5, log_responsibilities=lr, kappa=free.cross_entropy + 0.1
    )
    assert loose.xi == 0.0
    assert torch.allclose(loose.weights, free.weights, atol=1e-10)
    tight = solve_episodic_dual(
        R, epsilon=0.5, log_responsibilities=lr, kappa=free.cross_entropy - 0.1
    )
    assert tight.xi > 0
    assert tight.cross_entropy == pytest.approx(float(free.cross_entropy - 0.1), abs=1e-3)


def test_one_option_no_kappa_is_contextual_reps(gen):
    # Contextual REPS written out independently: minimise eta eps + eta log mean exp(delta/eta)
    # with delta = R - v^T (phi - phi_hat), then w ∝ exp(delta/eta).
    R, _, phi = random_problem(gen, N=150, F=2)
    eps = 0.7
    sol = solve_episodic_dual(R, epsilon=eps, context_features=phi)
    sol1 = solve_episodic_dual(
        R,
        epsilon=eps,
        context_features=phi,
        log_responsibilities=torch.zeros(150, 1, dtype=torch.float64),
    )
    assert torch.allclose(sol.weights, sol1.weights, atol=1e-12)

    x = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    phic = phi - phi.mean(0)

    def reps_dual():
        eta = x[0].exp()
        delta = R - phic @ x[1:]
        return eta * eps + eta * (torch.logsumexp(delta / eta, 0) - math.log(150))

    opt = torch.optim.LBFGS([x], max_iter=500, tolerance_grad=1e-12, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        g = reps_dual()
        g.backward()
        return g

    opt.step(closure)
    with torch.no_grad():
        w = torch.softmax((R - phic @ x[1:]) / x[0].exp(), 0)
    assert torch.allclose(sol.sample_weights, w, atol=1e-6)
    assert sol.eta == pytest.approx(float(x[0].detach().exp()), rel=1e-5)
    assert torch.allclose(sol.v, x[1:].detach(), atol=1e-4)


@pytest.mark.parametrize("O,F,use_kappa", [(1, 0, False), (3, 2, True)])
def test_weights_invariant_to_return_shift_and_scale(gen, O, F, use_kappa):
    R, lr, phi = random_problem(gen, N=120, O=O, F=F)
    kappa = 0.7 * mean_entropy(lr) if use_kappa else None
    kw = dict(epsilon=0.5, log_responsibilities=lr, context_features=phi, kappa=kappa)
    base = solve_episodic_dual(R, **kw)
    shifted = solve_episodic_dual(R + 1234.5, **kw)
    scaled = solve_episodic_dual(R * 37.0, **kw)
    assert torch.allclose(base.weights, shifted.weights, atol=1e-9)
    assert torch.allclose(base.weights, scaled.weights, atol=1e-9)
    assert scaled.eta == pytest.approx(float(37.0 * base.eta), rel=1e-6)
    assert scaled.xi == pytest.approx(float(37.0 * base.xi), rel=1e-6, abs=1e-12)


def test_pruned_option_columns_get_zero_weight(gen):
    R, lr, _ = random_problem(gen, N=100, O=3)
    lr2 = torch.log_softmax(lr[:, :2], -1)
    lr3 = torch.cat([lr2, torch.full((100, 1), -math.inf, dtype=torch.float64)], 1)
    sol = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr3, kappa=0.3)
    ref = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr2, kappa=0.3)
    assert sol.converged and ref.converged
    assert bool(torch.isfinite(sol.weights).all())
    assert float(sol.weights[:, 2].abs().max()) == 0.0
    assert torch.allclose(sol.weights[:, :2], ref.weights, atol=1e-9)


# ---- degenerate and bad input ---------------------------------------------------------------
def test_epsilon_beyond_log_n_warns_and_stays_finite(gen):
    R = torch.randn(20, generator=gen, dtype=torch.float64)
    with pytest.warns(DegenerateWeightsWarning) as record:
        sol = solve_episodic_dual(R, epsilon=5.0)
    messages = [str(r.message) for r in record]
    # one warning before the solve (epsilon >= log N), one after it (the weights collapsed)
    assert any("log N" in m for m in messages) and any("collapsed onto" in m for m in messages)
    assert bool(torch.isfinite(sol.weights).all())
    assert sol.effective_sample_size < 1.5
    assert int(sol.sample_weights.argmax()) == int(R.argmax())


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nonfinite_returns_raise(bad):
    R = torch.zeros(5)
    R[3] = bad
    with pytest.raises(ValueError, match=r"returns contains 1 non-finite value.*index \(3,\)"):
        solve_episodic_dual(R, epsilon=0.5)


@pytest.mark.parametrize("eps", [0.0, -1.0, math.nan, math.inf])
def test_bad_epsilon_raises(eps):
    with pytest.raises(ValueError, match="epsilon"):
        solve_episodic_dual(torch.arange(10.0), epsilon=eps)


def test_shape_mismatches_raise():
    with pytest.raises(ValueError, match=r"returns must have shape \(N,\)"):
        solve_episodic_dual(torch.zeros(4, 2), epsilon=0.5)
    with pytest.raises(ValueError, match=r"log_responsibilities must have shape \(N, O\) = \(4"):
        solve_episodic_dual(torch.arange(4.0), epsilon=0.5, log_responsibilities=torch.zeros(5, 2))
    with pytest.raises(ValueError, match=r"context_features must have shape \(N, F\) = \(4"):
        solve_episodic_dual(torch.arange(4.0), epsilon=0.5, context_features=torch.zeros(3, 2))
    with pytest.raises(ValueError, match="normalised over options"):
        solve_episodic_dual(torch.arange(4.0), epsilon=0.5, log_responsibilities=torch.zeros(4, 2))
    with pytest.raises(ValueError, match="kappa"):
        solve_episodic_dual(torch.arange(4.0), epsilon=0.5, kappa=-0.1)


def test_single_sample_raises():
    with pytest.raises(ValueError, match="at least 2 samples, got N = 1"):
        solve_episodic_dual(torch.tensor([1.0]), epsilon=0.5)


def test_generic_solver_matches_episodic_wrapper(gen):
    R, lr, phi = random_problem(gen, N=80, O=2, F=2)
    sol = solve_episodic_dual(R, epsilon=0.4, log_responsibilities=lr, context_features=phi)
    D = -(phi - phi.mean(0))[None]
    gen_sol = solve_reps_dual(R[None], lr[None], torch.tensor([0.4]), D=D)
    assert torch.allclose(gen_sol.weights[0], sol.weights, atol=1e-12)


def test_no_warning_in_regular_use(gen):
    R, lr, _ = random_problem(gen, N=100, O=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr)


@pytest.mark.parametrize("seed", range(4))
def test_features_that_explain_the_returns_almost_exactly(seed):
    # A converged policy: theta = (2 - s) / 2 + 0.003 noise, R = -(s + theta - 2)^2 - theta^2,
    # so phi = [s, s^2] explains all but ~1e-5 of the returns, and s lies in a narrow range
    # (corr(s, s^2) ≈ 0.9999). Scaled by the returns, eta was ~1e-5 with the v-curvature
    # ~1/eta and nearly singular; the solver ran off (KL ~3 for epsilon 0.5) in 17 of 20 such
    # problems before it scaled by the Bellman residual and whitened the features.
    gen = torch.Generator().manual_seed(seed)
    s = 1.67 + 0.05 * torch.randn(50, generator=gen, dtype=torch.float64)
    theta = (2 - s) / 2 + 0.003 * torch.randn(50, generator=gen, dtype=torch.float64)
    R = -((s + theta - 2) ** 2) - theta**2
    phi = torch.stack([s, s**2], 1)
    lr = torch.log_softmax(4.0 * torch.randn(50, 3, generator=gen, dtype=torch.float64), -1)
    kappa = 0.9 * mean_entropy(lr)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = solve_episodic_dual(
            R, epsilon=0.5, log_responsibilities=lr, context_features=phi, kappa=kappa
        )
    assert sol.converged
    assert sol.kl == pytest.approx(0.5, abs=1e-3)
    assert sol.cross_entropy <= kappa + 1e-6
    assert float((sol.sample_weights @ phi - phi.mean(0)).abs().max()) < 1e-5
    assert sol.effective_sample_size > 10


# ---- infinite-horizon dual ------------------------------------------------------------------
def random_chain(gen, N=400, O=3, F=6):
    """Transitions of a random 1-D chain (s' follows s) with Fourier-like features."""
    s = torch.cumsum(0.3 * torch.randn(N + 1, generator=gen, dtype=torch.float64), 0)
    freq = torch.arange(1, F + 1, dtype=torch.float64)
    phi_all = torch.cos(0.5 * freq * s[:, None])
    r = -(s[:-1] ** 2) + torch.randn(N, generator=gen, dtype=torch.float64)
    lr = torch.log_softmax(2.0 * torch.randn(N, O, generator=gen, dtype=torch.float64), -1)
    phi0 = torch.cos(0.5 * freq * 0.1 * torch.randn(50, 1, generator=gen, dtype=torch.float64))
    return r, phi_all[:-1], phi_all[1:], phi0.mean(0), lr


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("use_options", [False, True])
def test_infinite_horizon_constraints_hold_at_optimum(seed, use_options):
    gen = torch.Generator().manual_seed(seed)
    r, phi, phi_next, phi0, lr = random_chain(gen)
    gamma, eps = [0.95, 0.98, 0.996][seed], [1.0, 0.2, 0.5][seed]
    kappa = 0.6 * mean_entropy(lr) if use_options else None
    sol = solve_infinite_horizon_dual(
        r,
        phi,
        phi_next,
        phi0,
        gamma=gamma,
        epsilon=eps,
        log_responsibilities=lr if use_options else None,
        kappa=kappa,
    )
    assert sol.converged
    assert sol.kl == pytest.approx(eps, abs=1e-3)
    if use_options:
        assert sol.cross_entropy == pytest.approx(kappa, abs=1e-3)
    # stationarity under restarts: sum_i w_i (phi_i - gamma phi'_i) = (1 - gamma) phi_hat_0
    w = sol.sample_weights
    resid = w @ (phi - gamma * phi_next) - (1 - gamma) * phi0
    assert float(resid.abs().max()) < 1e-5
    assert sol.feature_error < 1e-5
    # the weights are the Bellman-error softmax with the returned v and eta
    delta = r + gamma * phi_next @ sol.v - phi @ sol.v
    if not use_options:
        expected = torch.softmax(delta / sol.eta, 0)
        assert torch.allclose(w, expected, atol=1e-8)


def test_stationarity_needing_more_kl_than_epsilon_is_relaxed_and_reported():
    # seed 0 with gamma = 0.9: meeting the stationarity constraint exactly needs KL ~0.57
    r, phi, phi_next, phi0, _ = random_chain(torch.Generator().manual_seed(0))
    with pytest.warns(InfeasibleConstraintsWarning, match="cannot be met"):
        sol = solve_infinite_horizon_dual(r, phi, phi_next, phi0, gamma=0.9, epsilon=0.2)
    assert not sol.converged
    assert sol.kl == pytest.approx(0.2, abs=1e-4)  # the KL bound is kept
    assert 1e-4 < sol.feature_error < 0.2  # the constraints are met approximately
    assert sol.effective_sample_size > 50
    assert bool(torch.isfinite(sol.weights).all())
    # with the KL it needs the same data are feasible and solved exactly
    ok = solve_infinite_horizon_dual(r, phi, phi_next, phi0, gamma=0.9, epsilon=0.8)
    assert ok.converged and ok.feature_error < 1e-5


@pytest.mark.parametrize("O", [1, 3])
def test_conflicting_constraints_give_finite_weights_within_the_kl_bound(O):
    # Every sample has phi - gamma phi' > 0 in feature 0 while (1 - gamma) phi_hat_0 < 0 there:
    # no reweighting meets stationarity, the unregularised dual is unbounded below (it used to
    # run off to NaN weights).
    gen = torch.Generator().manual_seed(3)
    N, F, gamma = 120, 4, 0.95
    phi = torch.randn(N, F, generator=gen, dtype=torch.float64)
    phi_next = torch.randn(N, F, generator=gen, dtype=torch.float64)
    phi_next[:, 0] = (phi[:, 0] - 0.1 - torch.rand(N, generator=gen, dtype=torch.float64)) / gamma
    phi0 = torch.randn(F, generator=gen, dtype=torch.float64)
    phi0[0] = -1.0
    r = torch.randn(N, generator=gen, dtype=torch.float64)
    lr = None
    kappa = None
    if O > 1:
        lr = torch.log_softmax(torch.randn(N, O, generator=gen, dtype=torch.float64), -1)
        kappa = 0.8 * mean_entropy(lr)
    with pytest.warns(InfeasibleConstraintsWarning, match="cannot be met"):
        sol = solve_infinite_horizon_dual(
            r,
            phi,
            phi_next,
            phi0,
            gamma=gamma,
            epsilon=0.5,
            log_responsibilities=lr,
            kappa=kappa,
        )
    assert not sol.converged
    assert bool(torch.isfinite(sol.weights).all())
    assert sol.kl == pytest.approx(0.5, abs=1e-4)
    assert sol.effective_sample_size > 10
    if kappa is not None:
        assert sol.cross_entropy <= kappa + 1e-4


def test_infinite_horizon_dual_bad_input(gen):
    r, phi, phi_next, phi0, _ = random_chain(gen, N=50, F=3)
    with pytest.raises(ValueError, match="gamma"):
        solve_infinite_horizon_dual(r, phi, phi_next, phi0, gamma=1.0, epsilon=0.5)
    with pytest.raises(ValueError, match="next_features"):
        solve_infinite_horizon_dual(r, phi, phi_next[:, :2], phi0, gamma=0.9, epsilon=0.5)
    with pytest.raises(ValueError, match="initial_features"):
        solve_infinite_horizon_dual(r, phi, phi_next, phi0[:2], gamma=0.9, epsilon=0.5)
    bad = r.clone()
    bad[3] = math.nan
    with pytest.raises(ValueError, match="rewards"):
        solve_infinite_horizon_dual(bad, phi, phi_next, phi0, gamma=0.9, epsilon=0.5)


def test_without_an_entropy_bound_the_options_factor_out_of_the_dual():
    # xi = 0: P_io = w_i p~_io with w the one-option solution, for soft and for hard gating
    g = torch.Generator().manual_seed(11)
    N, O = 400, 6
    R = torch.randn(N, generator=g, dtype=torch.float64) * 3
    phi = torch.randn(N, 2, generator=g, dtype=torch.float64)
    soft = torch.log_softmax(torch.randn(N, O, generator=g, dtype=torch.float64) * 2, dim=-1)
    hard = torch.full((N, O), float("-inf"), dtype=torch.float64)
    hard[torch.arange(N), torch.arange(N) % O] = 0.0
    one = solve_infinite_horizon_dual(R, phi, phi.roll(1, 0), phi.mean(0), gamma=0.9, epsilon=0.5)
    for lr in (soft, hard):
        sol = solve_infinite_horizon_dual(
            R, phi, phi.roll(1, 0), phi.mean(0), gamma=0.9, epsilon=0.5, log_responsibilities=lr
        )
        assert sol.kl == pytest.approx(0.5, abs=1e-6)
        assert torch.allclose(sol.sample_weights, one.sample_weights, atol=1e-12)
        expect = sol.sample_weights[:, None] * lr.exp()
        assert torch.allclose(sol.weights, expect, atol=1e-12)
        # the general multi-option solve, forced by a bound that never binds, agrees
        slack = solve_infinite_horizon_dual(
            R,
            phi,
            phi.roll(1, 0),
            phi.mean(0),
            gamma=0.9,
            epsilon=0.5,
            log_responsibilities=lr,
            kappa=50.0,
        )
        assert slack.xi == 0.0
        assert torch.allclose(slack.weights, sol.weights, atol=1e-7)
        assert slack.eta == pytest.approx(float(sol.eta), rel=1e-5)
        assert slack.dual_value == pytest.approx(float(sol.dual_value), rel=1e-6)


# ---- the start and the dual value with a linear term ----------------------------------------
def _linear_term_problem(seed):
    gen = torch.Generator().manual_seed(seed)
    K, N, P, O = 1, 200, 4, 3
    R = 3.0 * torch.randn(K, N, generator=gen, dtype=torch.float64) + 5.0
    D = torch.randn(K, N, P, generator=gen, dtype=torch.float64)
    c = -D.mean(1).sum(0) + 0.05 * torch.randn(P, generator=gen, dtype=torch.float64)
    lr = torch.log_softmax(torch.randn(K, N, O, generator=gen, dtype=torch.float64), -1)
    return R, D, c, lr


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_dual_value_with_a_linear_term_is_the_dual_at_the_returned_eta_and_v(seed):
    # v starts at the least-squares fit v0 also with a linear term c: c^T v0 must stay in the
    # reported dual value
    R, D, c, lr = _linear_term_problem(seed)
    sol = solve_reps_dual(R, lr, 0.5, D=D, c=c)
    assert sol.converged
    eta, v = sol.eta.reshape(-1), sol.v.reshape(-1)
    z = (R + D @ v) / eta[:, None] + torch.logsumexp(lr, -1)
    lse = torch.logsumexp(z, -1) - math.log(R.shape[-1])
    direct = float((eta * 0.5 + eta * lse).sum() + c @ v)
    assert float(sol.dual_value) == pytest.approx(direct, rel=1e-9, abs=1e-12)


def test_returns_the_features_explain_have_the_dual_value_c_v():
    # R = -D v*: every distribution that meets the constraints has E[R] = c^T v*
    R, D, c, lr = _linear_term_problem(3)
    v_star = torch.tensor([1.0, 2.0, -1.0, 0.5], dtype=torch.float64)
    sol = solve_reps_dual(-(D @ v_star), lr, 0.5, D=D, c=c)
    assert float(sol.dual_value) == pytest.approx(float(c @ v_star), rel=1e-9)
    assert torch.allclose(sol.v.reshape(-1), v_star, rtol=1e-9, atol=1e-12)


def test_the_block_start_temperatures_are_the_plain_reps_temperatures():
    from hireps_torch.dual.solver import LbfgsSettings
    from hireps_torch.dual.temperature import log_temperatures, solve_temperature

    gen = torch.Generator().manual_seed(7)
    R = torch.randn(2, 3, 50, generator=gen, dtype=torch.float64)
    R[1, 2] = 4.0  # no spread: no temperature (the default start)
    eps = torch.tensor([[0.1, 0.5, 1.0], [0.2, 0.3, 0.4]], dtype=torch.float64)
    got = log_temperatures(R, eps)
    assert got.shape == (2, 3) and bool(got[1, 2].isnan())
    for s, k in [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1)]:
        sol = solve_temperature(R[s, k], float(eps[s, k]), LbfgsSettings())
        assert sol is not None
        assert float(got[s, k]) == pytest.approx(math.log(float(sol.eta.reshape(-1)[0])), rel=1e-12)
