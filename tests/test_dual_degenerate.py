"""The duals keep their promises on every input a user can produce.

The KL bound holds by construction, ``converged`` means what it says (or a warning names the
failure), constant features and constant returns are handled, the weights do not depend on the
scale of the returns over the whole float64 range, nonsensical options are rejected, and a
random-problem property test runs every variant with and without options, entropy bounds and
features, with few and many samples.
"""

import math
import warnings

import pytest
import torch

from hireps_torch.checks import as_f64
from hireps_torch.dual import (
    DualConvergenceWarning,
    InfeasibleConstraintsWarning,
    solve_episodic_dual,
    solve_infinite_horizon_dual,
    solve_reps_dual,
    solve_time_indexed_dual,
)

F64 = torch.float64
KL_TOL = 1 + 1e-6


def randn(gen, *shape):
    return torch.randn(*shape, generator=gen, dtype=F64)


def soft(gen, *lead, O=3, sharp=2.0):
    """Random log responsibilities (*lead, O)."""
    return torch.log_softmax(sharp * randn(gen, *lead, O), -1)


def entropy(lr):
    """Mean responsibility entropy over the samples: (N, O) -> float, (N, K, O) -> (K,)."""
    return -(lr.exp() * lr).sum(-1).mean(0)


def quadratic(s):
    """[s, s^2, s_1 s_2] features of 2-D states (..., 2) -> (..., 5)."""
    return torch.cat([s, s**2, s[..., :1] * s[..., 1:]], -1)


def solve_quietly(fn, *args, **kwargs):
    """(solution, warnings) of one call, every warning recorded."""
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        sol = fn(*args, **kwargs)
    return sol, record


def assert_kept_promises(sol, eps, record):
    """KL bound, normalised non-negative weights, finite multipliers, and a warning whenever
    the solve is not converged."""
    w = sol.weights
    eps = torch.as_tensor(eps, dtype=F64)
    kl = torch.as_tensor(sol.kl, dtype=F64)
    assert bool(torch.isfinite(w).all()) and bool((w >= 0).all())
    blocks = w.reshape(-1, *w.shape[-2:]).sum((1, 2))
    assert torch.allclose(blocks, torch.ones_like(blocks), rtol=0, atol=1e-12)
    assert bool((kl <= eps * KL_TOL).all()), (kl.tolist(), eps.tolist())
    eta, xi = torch.as_tensor(sol.eta), torch.as_tensor(sol.xi)
    assert not bool(eta.isnan().any()) and bool((eta > 0).all())
    assert not bool(xi.isnan().any()) and bool((xi >= 0).all())
    assert math.isfinite(sol.dual_value)
    if not sol.converged:
        assert any(issubclass(r.category, RuntimeWarning) for r in record)


# ---- problems of every variant ----------------------------------------------------------
def episodic(gen, N=40, O=3, F=2, kappa_rel=0.7):
    R = 2.0 * randn(gen, N) + 1.0
    lr = soft(gen, N, O=O) if O > 1 else None
    phi = randn(gen, N, F) if F else None
    if phi is not None:
        R = R + phi[:, 0]
    kappa = None if lr is None or kappa_rel is None else kappa_rel * float(entropy(lr))

    def solve(returns, **kw):
        args = dict(epsilon=0.5, log_responsibilities=lr, context_features=phi, kappa=kappa)
        return solve_episodic_dual(returns, **{**args, **kw})

    return R, solve


def infinite_horizon(gen, N=40, O=3, F=3, kappa_rel=0.7):
    s = torch.cumsum(0.3 * randn(gen, N + 1), 0)
    phi_all = torch.cos(0.5 * torch.arange(1, F + 1, dtype=F64) * s[:, None])
    r = -(s[:-1] ** 2) + randn(gen, N)
    lr = soft(gen, N, O=O) if O > 1 else None
    kappa = None if lr is None or kappa_rel is None else kappa_rel * float(entropy(lr))

    def solve(rewards, **kw):
        args = dict(gamma=0.9, epsilon=0.5, log_responsibilities=lr, kappa=kappa)
        return solve_infinite_horizon_dual(
            rewards, phi_all[:-1], phi_all[1:], phi_all[0], **{**args, **kw}
        )

    return r, solve


def time_indexed(gen, N=40, K=3, O=3, kappa_rel=0.7):
    s = randn(gen, N, K, 2)
    R = randn(gen, N, K) - (s**2).sum(-1)
    lr = soft(gen, N, K, O=O) if O > 1 else None
    kappa = None if lr is None or kappa_rel is None else kappa_rel * entropy(lr)

    def solve(rewards, **kw):
        args = dict(epsilon=0.5, log_responsibilities=lr, kappa=kappa)
        return solve_time_indexed_dual(rewards, s, **{**args, **kw})

    return R, solve


VARIANTS = {
    "episodic": lambda gen: episodic(gen, O=1, F=0),
    "episodic-options-context": lambda gen: episodic(gen),
    "infinite-horizon": lambda gen: infinite_horizon(gen, O=1),
    "infinite-horizon-options": lambda gen: infinite_horizon(gen),
    "time-indexed": lambda gen: time_indexed(gen, O=1),
    "time-indexed-options": lambda gen: time_indexed(gen),
}


# ---- the KL bound by construction -------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("quad", [False, True])
@pytest.mark.parametrize("options", [False, True])
def test_time_indexed_zero_rewards_before_contact_keep_the_kl_bound(seed, quad, options):
    # Robot hockey without contact: the rewards of steps 1-2 are exactly 0, only step 3
    # varies. Steps 1-2 have an inactive KL bound (eta -> 0); the solver used to stall there
    # with v running off, and step 1-2 weights collapsed onto one episode (KL 3.4 = log 30
    # against epsilon 1, ESS 1).
    gen = torch.Generator().manual_seed(seed)
    N, K = 30, 3
    s = randn(gen, N, K, 2)
    R = torch.zeros(N, K, dtype=F64)
    R[:, 2] = randn(gen, N)
    lr = soft(gen, N, K) if options else None
    kappa = 0.8 * entropy(lr) if options else None
    phi = quadratic(s) if quad else s
    sol, record = solve_quietly(
        solve_time_indexed_dual, R, phi, epsilon=1.0, log_responsibilities=lr, kappa=kappa
    )
    assert_kept_promises(sol, 1.0, record)
    assert bool((sol.effective_sample_size > 5).all())
    assert float(sol.kl[2]) == pytest.approx(1.0, rel=1e-6)  # the step with the reward binds
    if not (quad and options):  # (these few converge; with both, some stop short, warned)
        assert sol.converged and not record


def test_a_solve_cut_short_keeps_the_kl_bound_and_says_what_failed():
    # one LBFGS iteration and a tolerance no solve can meet (the Newton polish after LBFGS
    # rescues max_iter = 1 alone)
    gen = torch.Generator().manual_seed(0)
    K, N, P = 2, 30, 3
    D, lr = randn(gen, K, N, P), soft(gen, K, N)
    eps = torch.tensor([0.5, 0.5], dtype=F64)
    sol, record = solve_quietly(
        solve_reps_dual, randn(gen, K, N), lr, eps, D=D, max_iter=1, converged_grad=1e-30
    )
    assert_kept_promises(sol, eps, record)
    assert not sol.converged
    [w] = record
    assert issubclass(w.category, DualConvergenceWarning)
    assert "feature constraints are off by" in str(w.message)


def test_generic_solver_keeps_the_kl_bound_when_the_constraints_conflict():
    # every sample has D > 0 in feature 0 while c > 0 there: no reweighting meets it
    gen = torch.Generator().manual_seed(1)
    K, N, P = 2, 25, 3
    D = randn(gen, K, N, P)
    D[..., 0] = D[..., 0].abs() + 0.1
    c = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    lr = soft(gen, K, N)
    eps = torch.tensor([0.3, 0.6], dtype=F64)
    sol, record = solve_quietly(
        solve_reps_dual,
        randn(gen, K, N),
        lr,
        eps,
        D=D,
        c=c,
        kappa=0.8 * entropy(lr.transpose(0, 1)),
    )
    assert_kept_promises(sol, eps, record)
    assert not sol.converged
    assert any(issubclass(r.category, InfeasibleConstraintsWarning) for r in record)


@pytest.mark.parametrize("size", [1e-310, 1e-320])
def test_subnormal_features_give_the_scaled_values(size):
    """Features in float64's subnormal range: v scales as 1 / size (the SVD of non-finite
    values failed; then v came back inf, its scale multiplied before it was divided)."""
    gen = torch.Generator().manual_seed(0)
    phi = randn(gen, 200, 2)
    R = (randn(gen, 200) + phi @ torch.tensor([1.0, -0.5], dtype=F64)) * 1e-300
    lr = torch.log_softmax(randn(gen, 200, 3), -1)
    solve = lambda f: solve_episodic_dual(  # noqa: E731
        R, epsilon=0.5, log_responsibilities=lr, kappa=0.9, context_features=phi * f
    )
    unit, tiny = solve(1e-305), solve(size)
    assert bool(tiny.converged.all()) and float(tiny.kl.max()) <= 0.5 * KL_TOL
    assert torch.allclose(tiny.v * (size / 1e-305), unit.v, rtol=1e-2)


@pytest.mark.parametrize("size", [1e-310, 1e-320])
def test_subnormal_returns_give_the_scaled_solution(size):
    """Returns in float64's subnormal range: eta scales with them and the bound holds (the
    entropy-bounded solve's power-of-2 prescale overflowed to inf: eta NaN, 'converged')."""
    gen = torch.Generator().manual_seed(0)
    R = randn(gen, 100)
    lr = torch.log_softmax(randn(gen, 100, 3), -1)
    unit = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr, kappa=0.9)
    tiny = solve_episodic_dual(R * size, epsilon=0.5, log_responsibilities=lr, kappa=0.9)
    assert bool(tiny.converged.all())
    assert float(tiny.kl.max()) <= 0.5 * KL_TOL
    rel = float(tiny.eta.reshape(-1)[0]) / (size * float(unit.eta.reshape(-1)[0]))
    assert abs(rel - 1) < 1e-2


# ---- converged means every constraint holds ---------------------------------------------
@pytest.mark.parametrize("seed", range(3))
def test_converged_means_kl_entropy_and_features_hold(seed):
    gen = torch.Generator().manual_seed(seed)
    N = 60
    R, lr, phi = randn(gen, N), soft(gen, N), randn(gen, N, 2)
    kappa = 0.7 * float(entropy(lr))
    sol, record = solve_quietly(
        solve_episodic_dual,
        R,
        epsilon=0.4,
        log_responsibilities=lr,
        context_features=phi,
        kappa=kappa,
    )
    assert sol.converged and not record
    assert sol.kl <= 0.4 * KL_TOL
    assert sol.cross_entropy <= kappa + 1e-6 * max(kappa, 1.0)
    resid = sol.sample_weights @ phi - phi.mean(0)
    assert float(resid.abs().max()) <= 1e-6 * float(phi.std(0).max())


# ---- constant features ------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["all-contexts-equal", "all-zero", "one-constant-column"])
def test_episodic_constant_features_are_dropped(kind):
    gen = torch.Generator().manual_seed(2)
    N = 50
    R, lr, phi = randn(gen, N), soft(gen, N), randn(gen, N, 2)
    kw = dict(epsilon=0.5, log_responsibilities=lr, kappa=0.7 * float(entropy(lr)))
    if kind == "one-constant-column":
        bad = torch.cat([phi, torch.full((N, 1), 3.7, dtype=F64)], 1)
        ref = solve_episodic_dual(R, context_features=phi, **kw)
    else:
        bad = torch.full((N, 2), 2.5 if kind == "all-contexts-equal" else 0.0, dtype=F64)
        ref = solve_episodic_dual(R, **kw)
    sol, record = solve_quietly(solve_episodic_dual, R, context_features=bad, **kw)
    assert sol.converged and not record
    assert torch.allclose(sol.weights, ref.weights, rtol=1e-6, atol=1e-12)


def test_infinite_horizon_constant_features():
    gen = torch.Generator().manual_seed(3)
    r, _ = infinite_horizon(gen)
    N = r.shape[0]
    ones = torch.ones(N, 1, dtype=F64)
    plain = solve_infinite_horizon_dual(
        r, torch.zeros(N, 0), torch.zeros(N, 0), torch.zeros(0), gamma=0.9, epsilon=0.5
    )
    # all states alike (phi = phi' = phi_0): nothing to keep, the feature-free solution
    for c in (0.0, 1.0, -2.5):
        sol, record = solve_quietly(
            solve_infinite_horizon_dual,
            r,
            c * ones,
            c * ones,
            c * ones[0],
            gamma=0.9,
            epsilon=0.5,
        )
        assert sol.converged and not record
        assert torch.allclose(sol.weights, plain.weights, rtol=1e-6, atol=1e-12)
    # a constant column next to informative ones, with the start distribution agreeing
    phi, phi_next, phi0 = _chain_features(N)
    base = solve_infinite_horizon_dual(r, phi, phi_next, phi0, gamma=0.9, epsilon=0.5)
    with_const, record = solve_quietly(
        solve_infinite_horizon_dual,
        r,
        torch.cat([phi, ones], 1),
        torch.cat([phi_next, ones], 1),
        torch.cat([phi0, torch.ones(1, dtype=F64)]),
        gamma=0.9,
        epsilon=0.5,
    )
    assert with_const.converged and not record
    assert torch.allclose(with_const.weights, base.weights, rtol=1e-6, atol=1e-12)
    # ... and disagreeing: no reweighting can meet that constraint; said so, KL kept
    sol, record = solve_quietly(
        solve_infinite_horizon_dual,
        r,
        torch.cat([phi, ones], 1),
        torch.cat([phi_next, ones], 1),
        torch.cat([phi0, torch.full((1,), 2.0, dtype=F64)]),
        gamma=0.9,
        epsilon=0.5,
    )
    assert_kept_promises(sol, 0.5, record)
    assert not sol.converged
    assert any(
        issubclass(w.category, InfeasibleConstraintsWarning) and "without spread" in str(w.message)
        for w in record
    )


def _chain_features(N, F=3, seed=3):
    """(phi, phi', phi_0) of a random 1-D chain of N transitions, Fourier features."""
    gen = torch.Generator().manual_seed(seed)
    s = torch.cumsum(0.3 * randn(gen, N + 1), 0)
    phi_all = torch.cos(0.5 * torch.arange(1, F + 1, dtype=F64) * s[:, None])
    return phi_all[:-1], phi_all[1:], phi_all[0]


def test_time_indexed_constant_features():
    gen = torch.Generator().manual_seed(4)
    N, K = 40, 3
    R, s = randn(gen, N, K), randn(gen, N, K, 2)
    none = solve_time_indexed_dual(R, torch.zeros(N, K, 0), epsilon=0.5)
    for c in (0.0, 1.0, 3.7):  # every state alike, per step
        sol, record = solve_quietly(
            solve_time_indexed_dual, R, torch.full((N, K, 2), c, dtype=F64), epsilon=0.5
        )
        assert sol.converged and not record
        assert torch.allclose(sol.weights, none.weights, rtol=1e-6, atol=1e-12)
    base = solve_time_indexed_dual(R, s, epsilon=0.5)
    with_one = torch.cat([s, torch.full((N, K, 1), 0.1, dtype=F64)], -1)
    sol, record = solve_quietly(solve_time_indexed_dual, R, with_one, epsilon=0.5)
    assert sol.converged and not record
    assert torch.allclose(sol.weights, base.weights, rtol=1e-6, atol=1e-12)
    # a start distribution whose constant feature is not 0.1: no reweighting keeps it
    phi1 = torch.cat([s[:, 0].mean(0), torch.full((1,), 2.0, dtype=F64)])
    sol, record = solve_quietly(
        solve_time_indexed_dual, R, with_one, epsilon=0.5, initial_features=phi1
    )
    assert_kept_promises(sol, 0.5, record)
    assert not sol.converged
    assert any(issubclass(w.category, InfeasibleConstraintsWarning) for w in record)


def test_generic_solver_with_all_zero_features():
    gen = torch.Generator().manual_seed(5)
    R, lr = randn(gen, 2, 30), soft(gen, 2, 30)
    eps = torch.tensor([0.5, 0.5], dtype=F64)
    plain = solve_reps_dual(R, lr, eps)
    sol, record = solve_quietly(
        solve_reps_dual, R, lr, eps, D=torch.zeros(2, 30, 4), c=torch.zeros(4)
    )
    assert sol.converged and not record
    assert torch.allclose(sol.weights, plain.weights, rtol=1e-9, atol=0)


# ---- scale and shift invariance ---------------------------------------------------------
@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("factor", [1e-12, 1e12, 1e-300, 1e300])
def test_weights_invariant_to_the_return_scale(variant, factor):
    R, solve = VARIANTS[variant](torch.Generator().manual_seed(6))
    base = solve(R)
    sol, record = solve_quietly(solve, R * factor)
    assert sol.converged and not record
    assert torch.allclose(sol.weights, base.weights, rtol=1e-6, atol=0)
    eta = torch.as_tensor(sol.eta)
    assert torch.allclose(eta, factor * torch.as_tensor(base.eta), rtol=1e-6, atol=0)
    assert sol.dual_value == pytest.approx(float(factor * base.dual_value), rel=1e-6)


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_weights_invariant_to_a_huge_return_shift(variant):
    # float64 stores R + 1e12 to 2^-13 ~ 1.2e-4: the shifted problem is the problem of the
    # rounded returns fl(R + 1e12) - 1e12 (exact), and it is solved to the same precision as
    # any other; against the unrounded R the weights can only agree to ~1e-4 / eta.
    R, solve = VARIANTS[variant](torch.Generator().manual_seed(7))
    shifted, record = solve_quietly(solve, R + 1e12)
    assert shifted.converged and not record
    rounded = solve((R + 1e12) - 1e12)
    assert torch.allclose(shifted.weights, rounded.weights, rtol=1e-6, atol=0)
    assert torch.allclose(shifted.weights, solve(R).weights, rtol=1e-3, atol=0)
    small = solve(R + 1e6)  # resolution 1e-10: the weights agree to the solver's tolerance
    assert torch.allclose(small.weights, solve(R).weights, rtol=1e-6, atol=0)


# ---- constant returns -------------------------------------------------------------------
def stationary_chain(gen, N=40, O=3):
    """An infinite-horizon problem whose samples are stationary under uniform weights (s'
    cycles through the sampled states, phi_hat_0 = their mean)."""
    phi = randn(gen, N, 3)
    lr = soft(gen, N, O=O) if O > 1 else None

    def solve(rewards, **kw):
        args = dict(gamma=0.9, epsilon=0.5, log_responsibilities=lr)
        return solve_infinite_horizon_dual(
            rewards, phi, phi.roll(1, 0), phi.mean(0), **{**args, **kw}
        )

    return randn(gen, N), solve


CONSTANT = {
    **VARIANTS,
    "infinite-horizon": lambda gen: stationary_chain(gen, O=1),
    "infinite-horizon-options": lambda gen: stationary_chain(gen),
}


@pytest.mark.parametrize("variant", list(CONSTANT))
def test_constant_returns_keep_the_old_distribution(variant):
    R, solve = CONSTANT[variant](torch.Generator().manual_seed(8))
    const = torch.full_like(R, 2.5)
    if const.dim() == 2:
        const = const * torch.arange(1, const.shape[1] + 1, dtype=F64)  # per step 2.5 k
    sol, record = solve_quietly(solve, const, kappa=None)
    assert sol.converged and not record
    w = sol.weights.sum(-1)
    N = w.shape[-1]
    assert torch.allclose(w, torch.full_like(w, 1.0 / N), rtol=0, atol=1e-12)
    assert bool((torch.as_tensor(sol.kl).abs() <= 1e-12).all())
    assert bool(torch.isinf(torch.as_tensor(sol.eta)).all())
    assert sol.dual_value == pytest.approx(float(const[0].sum()), rel=1e-12)


@pytest.mark.parametrize("options", [False, True])
def test_constant_rewards_keep_the_closest_stationary_distribution(options):
    # uniform weights are not stationary on these samples: with no reward information the
    # weights are the distribution closest to the old one (in KL) that is, whatever the reward
    gen = torch.Generator().manual_seed(26)
    _, solve = infinite_horizon(gen, O=3 if options else 1, kappa_rel=None)
    r = torch.zeros(40, dtype=F64)
    a, record = solve_quietly(solve, r + 2.5)
    assert a.converged and not record
    assert_kept_promises(a, 0.5, record)
    assert a.feature_error < 1e-6 and 0.0 < a.kl < 0.5
    assert math.isinf(a.eta) and a.dual_value == pytest.approx(2.5, rel=1e-12)
    b = solve(r - 7.0)
    assert torch.allclose(a.weights, b.weights, rtol=1e-9, atol=0)


@pytest.mark.parametrize("steps", [None, 3])
def test_constant_returns_with_a_binding_entropy_bound_tilt_just_enough(steps):
    # no return information, and the old distribution breaks the entropy bound: the weights
    # are the closest distribution to it (in KL) that meets the bound, which then binds
    gen = torch.Generator().manual_seed(9)
    N = 40
    if steps is None:
        lr, phi = soft(gen, N), randn(gen, N, 2)
        kappa = 0.7 * entropy(lr)
        sol, record = solve_quietly(
            solve_episodic_dual,
            torch.full((N,), -1.0, dtype=F64),
            epsilon=0.5,
            log_responsibilities=lr,
            context_features=phi,
            kappa=float(kappa),
        )
    else:
        lr, s = soft(gen, N, steps), randn(gen, N, steps, 2)
        kappa = 0.7 * entropy(lr)
        sol, record = solve_quietly(
            solve_time_indexed_dual,
            torch.full((N, steps), -1.0, dtype=F64),
            s,
            epsilon=0.5,
            log_responsibilities=lr,
            kappa=kappa,
        )
    assert sol.converged and not record
    assert_kept_promises(sol, 0.5, record)
    ce = torch.as_tensor(sol.cross_entropy, dtype=F64)
    assert torch.allclose(ce, torch.as_tensor(kappa, dtype=F64), rtol=1e-6, atol=0)
    assert bool((torch.as_tensor(sol.kl) < 0.5).all())
    assert sol.feature_error < 1e-6


# ---- an entropy bound that cannot be met ------------------------------------------------
@pytest.mark.parametrize(
    "variant", ["episodic-options-context", "infinite-horizon-options", "time-indexed-options"]
)
@pytest.mark.parametrize("case", ["kappa-0", "tiny-epsilon"])
def test_an_entropy_bound_out_of_reach_is_reported(variant, case):
    R, solve = VARIANTS[variant](torch.Generator().manual_seed(10))
    kw = dict(kappa=0.0) if case == "kappa-0" else dict(epsilon=1e-4)
    sol, record = solve_quietly(solve, R, **kw)
    eps = kw.get("epsilon", 0.5)
    assert_kept_promises(sol, eps, record)
    assert not sol.converged
    assert any(
        issubclass(w.category, InfeasibleConstraintsWarning)
        and "entropy bound cannot be met within the KL bound" in str(w.message)
        for w in record
    )


def test_an_entropy_bound_out_of_reach_names_the_step():
    gen = torch.Generator().manual_seed(11)
    R, s, lr = randn(gen, 40, 3), randn(gen, 40, 3, 2), soft(gen, 40, 3)
    kappa = torch.tensor([0.0, math.inf, 0.8 * float(entropy(lr)[2])], dtype=F64)
    with pytest.warns(InfeasibleConstraintsWarning, match=r"block\(s\) 0:"):
        sol = solve_time_indexed_dual(R, s, epsilon=0.5, log_responsibilities=lr, kappa=kappa)
    assert float(sol.xi[1]) == 0.0
    assert float(sol.cross_entropy[2]) <= float(kappa[2]) + 1e-6


# ---- solver options that make no sense --------------------------------------------------
BAD_MAX_ITER = [
    (0, ValueError),
    (-3, ValueError),
    (1.5, TypeError),
    (True, TypeError),
    ("10", TypeError),
    (None, TypeError),
    (torch.tensor([5]), TypeError),  # a count is a 0-d tensor at most
    (torch.tensor(5, device="meta"), TypeError),
]


@pytest.mark.parametrize("value,error", BAD_MAX_ITER)
def test_bad_max_iter_is_rejected_naming_the_value(value, error):
    gen = torch.Generator().manual_seed(12)
    R = randn(gen, 10)
    phi = randn(gen, 10, 2)
    match = "max_iter must be an integer >= 1, got"
    with pytest.raises(error, match=match):
        solve_episodic_dual(R, epsilon=0.5, max_iter=value)
    with pytest.raises(error, match=match):
        solve_infinite_horizon_dual(R, phi, phi, phi[0], gamma=0.9, epsilon=0.5, max_iter=value)
    with pytest.raises(error, match=match):
        solve_time_indexed_dual(R[:, None], phi[:, None], epsilon=0.5, max_iter=value)
    with pytest.raises(error, match=match):
        solve_reps_dual(R[None], torch.zeros(1, 10, 1), 0.5, max_iter=value)


@pytest.mark.parametrize("name", ["tolerance_grad", "converged_grad"])
@pytest.mark.parametrize("value", [0.0, -1e-6, math.nan, math.inf, True, "1e-6"])
def test_bad_tolerances_are_rejected_naming_the_value(name, value):
    R = torch.randn(10, generator=torch.Generator().manual_seed(13), dtype=F64)
    with pytest.raises((ValueError, TypeError), match=f"{name} must be a finite number > 0"):
        solve_reps_dual(R[None], torch.zeros(1, 10, 1), 0.5, **{name: value})


def test_generic_solver_checks_its_inputs():
    R = torch.randn(1, 10, generator=torch.Generator().manual_seed(14), dtype=F64)
    one = torch.zeros(1, 10, 1)
    with pytest.raises(ValueError, match=r"R must have shape \(K, N\)"):
        solve_reps_dual(R[0], one, 0.5)
    with pytest.raises(ValueError, match="R contains 1 non-finite"):
        solve_reps_dual(torch.where(torch.arange(10) == 3, math.nan, R), one, 0.5)
    with pytest.raises(ValueError, match="log_resp must be normalised"):
        solve_reps_dual(R, torch.zeros(1, 10, 2), 0.5)
    with pytest.raises(ValueError, match="epsilon"):
        solve_reps_dual(R, one, -0.5)
    with pytest.raises(ValueError, match=r"D must have shape \(K, N, P\)"):
        solve_reps_dual(R, one, 0.5, D=torch.zeros(1, 9, 2))
    with pytest.raises(ValueError, match="needs D"):
        solve_reps_dual(R, one, 0.5, c=torch.zeros(2))
    with pytest.raises(ValueError, match="kappa"):
        solve_reps_dual(R, one, 0.5, kappa=-1.0)


# ---- as_f64 -----------------------------------------------------------------------------
def test_python_floats_go_straight_to_float64():
    assert as_f64("epsilon", 0.2).item() == 0.2  # was 0.20000000298 through float32
    assert as_f64("x", [0.1, 0.3]).tolist() == [0.1, 0.3]
    assert as_f64("x", torch.tensor(0.2)).item() == float(torch.tensor(0.2))  # float32 kept
    with pytest.raises(TypeError, match="x must hold real numbers"):
        as_f64("x", torch.tensor([1 + 2j]))
    with pytest.raises(TypeError, match="x must be a tensor"):
        as_f64("x", "0.2")


# ---- hostile input ----------------------------------------------------------------------
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_two_samples(variant):
    gen = torch.Generator().manual_seed(15)
    R, solve = VARIANTS[variant](gen)
    R2 = R[:2]
    N = 2
    if variant.startswith("episodic"):
        lr = soft(gen, N) if "options" in variant else None
        phi = randn(gen, N, 2) if "context" in variant else None
        sol, record = solve_quietly(
            solve_episodic_dual,
            R2,
            epsilon=0.3,
            log_responsibilities=lr,
            context_features=phi,
            kappa=None if lr is None else 0.5,
        )
    elif variant.startswith("infinite"):
        lr = soft(gen, N) if "options" in variant else None
        phi = randn(gen, N, 2)
        sol, record = solve_quietly(
            solve_infinite_horizon_dual,
            R2,
            phi,
            phi.roll(1, 0),
            phi.mean(0),
            gamma=0.9,
            epsilon=0.3,
            log_responsibilities=lr,
            kappa=None if lr is None else 0.5,
        )
    else:
        lr = soft(gen, N, 3) if "options" in variant else None
        sol, record = solve_quietly(
            solve_time_indexed_dual,
            R2,
            randn(gen, N, 3, 2),
            epsilon=0.3,
            log_responsibilities=lr,
            kappa=None if lr is None else 0.5,
        )
    assert_kept_promises(sol, 0.3, record)


def test_option_columns_that_change_nothing():
    gen = torch.Generator().manual_seed(16)
    N = 40
    R, phi = randn(gen, N), randn(gen, N, 2)
    ref = solve_episodic_dual(R, epsilon=0.5, context_features=phi)
    one = solve_episodic_dual(
        R, epsilon=0.5, context_features=phi, log_responsibilities=torch.zeros(N, 1), kappa=0.3
    )
    assert torch.allclose(one.weights, ref.weights, rtol=1e-9, atol=0)
    # one option holds all the responsibility (the others pruned: -inf): CE = 0 <= kappa = 0
    hard = torch.full((N, 3), -math.inf, dtype=F64)
    hard[:, 1] = 0.0
    sol, record = solve_quietly(
        solve_episodic_dual,
        R,
        epsilon=0.5,
        context_features=phi,
        log_responsibilities=hard,
        kappa=0.0,
    )
    assert sol.converged and not record
    assert torch.allclose(sol.weights[:, 1], ref.weights[:, 0], rtol=1e-6, atol=0)
    assert float(sol.weights[:, [0, 2]].abs().max()) == 0.0


def test_pruned_options_with_an_entropy_bound():
    gen = torch.Generator().manual_seed(17)
    N = 40
    lr = soft(gen, N, O=4)
    lr[:, 3] = -math.inf
    lr = torch.log_softmax(lr, -1)
    R = randn(gen, N)
    sol, record = solve_quietly(
        solve_episodic_dual,
        R,
        epsilon=0.5,
        log_responsibilities=lr,
        kappa=0.6 * float(entropy(lr.clamp_min(-1e4))),
    )
    assert sol.converged and not record
    assert float(sol.weights[:, 3].abs().max()) == 0.0
    sol, record = solve_quietly(  # kappa = 0: the 3 live options are soft, out of reach
        solve_episodic_dual, R, epsilon=0.5, log_responsibilities=lr, kappa=0.0
    )
    assert_kept_promises(sol, 0.5, record)
    assert not sol.converged


def test_many_options():
    gen = torch.Generator().manual_seed(18)
    N, O = 60, 400
    lr = soft(gen, N, O=O, sharp=3.0)
    R = randn(gen, N)
    sol, record = solve_quietly(
        solve_episodic_dual,
        R,
        epsilon=0.5,
        log_responsibilities=lr,
        kappa=0.9 * float(entropy(lr)),
    )
    assert_kept_promises(sol, 0.5, record)
    assert sol.weights.shape == (N, O)


@pytest.mark.parametrize("scale", [1e15, 1e-15, 1e200])
def test_feature_magnitudes_do_not_matter(scale):
    gen = torch.Generator().manual_seed(19)
    N = 50
    R, lr, phi = randn(gen, N), soft(gen, N), randn(gen, N, 2)
    kw = dict(epsilon=0.5, log_responsibilities=lr, kappa=0.7 * float(entropy(lr)))
    base = solve_episodic_dual(R, context_features=phi, **kw)
    sol, record = solve_quietly(solve_episodic_dual, R, context_features=scale * phi, **kw)
    assert sol.converged and not record
    assert torch.allclose(sol.weights, base.weights, rtol=1e-6, atol=0)
    phi, phi_next, phi0 = _chain_features(40)
    base = solve_infinite_horizon_dual(R[:40], phi, phi_next, phi0, gamma=0.9, epsilon=0.5)
    sol, record = solve_quietly(
        solve_infinite_horizon_dual,
        R[:40],
        scale * phi,
        scale * phi_next,
        scale * phi0,
        gamma=0.9,
        epsilon=0.5,
    )
    assert sol.converged and not record
    assert torch.allclose(sol.weights, base.weights, rtol=1e-6, atol=0)


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_float32_input_is_the_float64_problem_of_its_values(variant):
    R, solve = VARIANTS[variant](torch.Generator().manual_seed(20))
    R32 = R.float()
    a = solve(R32)
    b = solve(R32.double())
    assert a.weights.dtype == F64
    assert torch.equal(a.weights, b.weights)


def test_float32_responsibilities_are_renormalised_in_float64():
    gen = torch.Generator().manual_seed(21)
    R, lr = randn(gen, 50), soft(gen, 50).float()
    norm = torch.logsumexp(lr.double(), -1, keepdim=True)
    assert float(norm.abs().max()) > 1e-9  # float32 rows are off by ~1e-7
    sol = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr, kappa=0.5)
    ref = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr.double() - norm, kappa=0.5)
    assert sol.converged and sol.kl <= 0.5 * KL_TOL and sol.kl >= 0.0
    assert torch.allclose(sol.weights, ref.weights, rtol=1e-9, atol=0)
    # the old distribution q p~ sums to 1 in float64: its KL to itself is 0 (constant returns)
    flat = solve_episodic_dual(torch.zeros(50), epsilon=0.5, log_responsibilities=lr)
    assert float(flat.weights.sum()) == pytest.approx(1.0, abs=1e-15)
    assert abs(flat.kl) <= 1e-15
    assert torch.allclose(flat.weights, (lr.double() - norm).exp() / 50, rtol=1e-12, atol=0)


def test_epsilon_and_kappa_shapes():
    gen = torch.Generator().manual_seed(22)
    R, s, lr = randn(gen, 40, 3), randn(gen, 40, 3, 2), soft(gen, 40, 3)
    ref = solve_time_indexed_dual(R, s, epsilon=0.5)
    for eps in (torch.tensor(0.5), torch.full((3,), 0.5), [0.5, 0.5, 0.5], 0.5):
        assert torch.equal(solve_time_indexed_dual(R, s, epsilon=eps).weights, ref.weights)
    with pytest.raises(ValueError, match=r"epsilon must be a float or have shape \(3,\)"):
        solve_time_indexed_dual(R, s, epsilon=torch.full((2,), 0.5))
    e1 = solve_episodic_dual(R[:, 0], epsilon=torch.tensor([0.5]))
    assert torch.equal(e1.weights, solve_episodic_dual(R[:, 0], epsilon=0.5).weights)
    # kappa = inf is no bound, per step too
    free = solve_time_indexed_dual(R, s, epsilon=0.5, log_responsibilities=lr)
    inf = solve_time_indexed_dual(
        R, s, epsilon=0.5, log_responsibilities=lr, kappa=torch.full((3,), math.inf)
    )
    assert torch.equal(free.weights, inf.weights)
    e_inf = solve_episodic_dual(R[:, 0], epsilon=0.5, log_responsibilities=lr[:, 0], kappa=math.inf)
    e_none = solve_episodic_dual(R[:, 0], epsilon=0.5, log_responsibilities=lr[:, 0])
    assert torch.equal(e_inf.weights, e_none.weights)


def test_inputs_that_require_grad_are_detached():
    gen = torch.Generator().manual_seed(23)
    R, lr = randn(gen, 30).requires_grad_(), soft(gen, 30).requires_grad_()
    sol = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr, kappa=0.5)
    assert not sol.weights.requires_grad


def test_zero_width_features_are_no_features():
    gen = torch.Generator().manual_seed(24)
    R = randn(gen, 30)
    ref = solve_episodic_dual(R, epsilon=0.5)
    assert torch.equal(
        solve_episodic_dual(R, epsilon=0.5, context_features=torch.zeros(30, 0)).weights,
        ref.weights,
    )
    zero = torch.zeros(30, 0)
    ih = solve_infinite_horizon_dual(R, zero, zero, torch.zeros(0), gamma=0.9, epsilon=0.5)
    assert torch.equal(ih.weights[:, 0], ref.weights[:, 0])


@pytest.mark.parametrize("eps", [1e-12, 1e-300])
def test_tiny_epsilon_keeps_the_bound(eps):
    R = torch.randn(30, generator=torch.Generator().manual_seed(25), dtype=F64)
    sol, record = solve_quietly(solve_episodic_dual, R, epsilon=eps)
    assert_kept_promises(sol, eps, record)
    assert sol.converged


# ---- random problems of every variant ---------------------------------------------------
def random_case(gen, variant):
    """One random problem: (solver, positional args, keyword args, epsilon)."""
    N = [2, 3, 5, 12, 40][int(torch.randint(5, (1,), generator=gen))]
    O = [1, 1, 2, 4][int(torch.randint(4, (1,), generator=gen))]
    F = [0, 1, 3, 8][int(torch.randint(4, (1,), generator=gen))]
    K = 1 + int(torch.randint(3, (1,), generator=gen))
    lead = (N,) if variant != "time_indexed" else (N, K)
    eps = math.exp(float(torch.empty(1).uniform_(math.log(1e-3), math.log(2.0), generator=gen)))
    scale = 10.0 ** float(torch.empty(1).uniform_(-6, 6, generator=gen))
    R = scale * (randn(gen, *lead) + 5.0 * float(randn(gen, 1)))
    kw: dict = dict(epsilon=eps)
    if O > 1:
        lr = soft(gen, *lead, O=O, sharp=float(torch.empty(1).uniform_(0.5, 6, generator=gen)))
        kw["log_responsibilities"] = lr
        choice = int(torch.randint(4, (1,), generator=gen))  # none, binding, loose, 0
        H = entropy(lr)
        kw["kappa"] = [None, 0.8 * H, H + 1.0, 0.0 * H][choice]
    if variant == "episodic":
        if F:
            kw["context_features"] = randn(gen, N, F)
        return solve_episodic_dual, (R,), kw, eps
    if variant == "infinite_horizon":  # a noisy chain (s' follows s) or unrelated states
        phi = randn(gen, N, max(F, 1))
        chain = bool(torch.rand(1, generator=gen) < 0.5)
        noise = randn(gen, *phi.shape)
        phi_next = phi.roll(1, 0) + 0.1 * noise if chain else noise
        return (
            solve_infinite_horizon_dual,
            (R, phi, phi_next, phi.mean(0)),
            {**kw, "gamma": 0.9},
            eps,
        )
    return solve_time_indexed_dual, (R, randn(gen, N, K, F)), kw, eps


@pytest.mark.parametrize("variant", ["episodic", "infinite_horizon", "time_indexed"])
def test_random_problems_keep_every_promise(variant):
    gen = torch.Generator().manual_seed({"episodic": 0, "infinite_horizon": 1}.get(variant, 2))
    for case in range(200):
        fn, args, kw, eps = random_case(gen, variant)
        sol, record = solve_quietly(fn, *args, **kw)
        try:
            assert_kept_promises(sol, eps, record)
            kappa = kw.get("kappa")
            if sol.converged and kappa is not None:
                kap = torch.as_tensor(kappa, dtype=F64)
                ce = torch.as_tensor(sol.cross_entropy)
                assert bool((ce <= kap + 1e-6 * kap.clamp_min(1.0)).all())
        except AssertionError as exc:
            raise AssertionError(f"{variant} case {case}: {exc}") from exc


def test_a_numerically_failed_solve_keeps_the_old_distribution(monkeypatch):
    # never seen in practice: the guard behind every other one
    import hireps_torch.dual.block_solver as block_solver

    def broken(self):
        self.x = torch.full_like(self.x, math.nan)
        nan = torch.full_like(self.prob.lr, math.nan)
        end = block_solver._End(torch.tensor([False]), torch.tensor([math.nan], dtype=F64), nan)
        return end, None

    monkeypatch.setattr(block_solver.BlockSolver, "run", broken)
    gen = torch.Generator().manual_seed(27)
    R, lr = randn(gen, 30), soft(gen, 30)
    with pytest.warns(DualConvergenceWarning, match="failed numerically"):
        sol = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=lr, kappa=10.0)
    assert torch.allclose(sol.weights, lr.exp() / 30, rtol=1e-12, atol=0)
    assert not sol.converged and math.isfinite(sol.dual_value) and sol.kl <= 1e-12
