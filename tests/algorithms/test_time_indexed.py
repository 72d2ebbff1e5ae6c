"""Time-indexed HiREPS: the per-step dual's constraints, its reduction to the episodic dual,
a two-step sequencing task, determinism and checkpoints, bad input."""

import math
import warnings

import pytest
import torch

from hireps_torch import TimeIndexedHiREPS, solve_episodic_dual, solve_time_indexed_dual
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


def two_step_chain(seed, N, noise, sharpness):
    """Episodes of the two-step task below with actions optimal up to ``noise``: value
    features [s, s^2] per step, random responsibilities of the given sharpness."""
    gen = torch.Generator().manual_seed(seed)
    f64 = dict(generator=gen, dtype=torch.float64)
    s1 = 0.3 * torch.randn(N, **f64)
    t1 = (2 - s1) / 1.2 + noise * torch.randn(N, **f64)
    s2 = s1 + t1
    t2 = (2 - s2) / 2 + noise * torch.randn(N, **f64)
    R = torch.stack([-0.1 * t1**2, -((s2 + t2 - 2) ** 2) - t2**2], 1)
    phi = QuadraticFeatures(1)(torch.stack([s1, s2], 1)[..., None])
    lr = torch.log_softmax(sharpness * torch.randn(N, 2, 3, **f64), -1)
    return R, phi, lr


@pytest.mark.parametrize("seed", range(4))
def test_dual_solves_a_converged_chain(seed):
    # Two steps of a converged policy (actions optimal up to 0.003 noise): the value features
    # explain the rewards almost exactly, step 2's features [s, s^2] are nearly collinear and
    # the two steps' temperatures differ ~100-fold. Before the solver scaled by the Bellman
    # residual (with a block-weighted start) and whitened the features, every one of 20 such
    # problems failed (no convergence, KL off, bound violated).
    R, phi, lr = two_step_chain(seed, 60, noise=0.003, sharpness=4.0)
    kappa = 0.9 * mean_entropy(lr)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = solve_time_indexed_dual(R, phi, epsilon=0.5, log_responsibilities=lr, kappa=kappa)
    assert sol.converged
    assert torch.allclose(sol.kl, torch.full((2,), 0.5, dtype=torch.float64), atol=1e-3)
    assert bool((sol.cross_entropy <= kappa + 1e-6).all())
    assert chained_violation(sol.sample_weights, phi, phi[:, 0].mean(0)) < 1e-5


@pytest.mark.parametrize("seed", [33, 34])
def test_entropy_bound_holds_with_nearly_separated_options(seed):
    # Sharp responsibilities (mean entropy ~0.1): the xi that meets the bound is small and the
    # dual nearly flat in log xi below it; LBFGS used to jump there and stop with xi ~1e-100,
    # the bound violated by ~1e-3 (these seeds) and the solve reported as converged.
    R, phi, lr = two_step_chain(seed, 50, noise=0.3, sharpness=12.0)
    kappa = 0.9 * mean_entropy(lr)
    sol = solve_time_indexed_dual(R, phi, epsilon=0.5, log_responsibilities=lr, kappa=kappa)
    assert sol.converged
    assert bool((sol.cross_entropy <= kappa + 1e-6).all())
    assert torch.allclose(sol.kl, torch.full((2,), 0.5, dtype=torch.float64), atol=1e-3)


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
        assert float(ti.eta[0]) == pytest.approx(float(ep.eta), rel=1e-5)
        assert ti.dual_value == pytest.approx(float(ep.dual_value), rel=1e-6)
        step = ti.step(0)
        assert torch.allclose(step.v, ep.v, atol=1e-4) and step.kl == pytest.approx(float(ep.kl))


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


# ---- the algorithm --------------------------------------------------------------------------
GOAL = 2.0


def two_step_episodes(algo, N, gen, greedy=False):
    """Two decisions on a line: theta_1 moves the state, s_2 = s_1 + theta_1 (cost 0.1
    theta_1^2); theta_2 then aims at the goal: R_2 = -(s_2 + theta_2 - goal)^2 - theta_2^2.
    Step 2's best action, (goal - s_2) / 2, depends on the state step 1 reached, and step 1
    only pays off through step 2: the best theta_1 is (goal - s_1) / 1.2."""
    s = torch.zeros(N, 2, 1, dtype=torch.float64)
    theta = torch.zeros(N, 2, 1, dtype=torch.float64)
    r = torch.zeros(N, 2, dtype=torch.float64)
    s[:, 0, 0] = 0.3 * torch.randn(N, generator=gen, dtype=torch.float64)
    policy = algo.act if greedy else algo.ask
    theta[:, 0] = policy(0, s[:, 0])
    r[:, 0] = -0.1 * theta[:, 0, 0] ** 2
    s[:, 1] = s[:, 0] + theta[:, 0]
    theta[:, 1] = policy(1, s[:, 1])
    r[:, 1] = -((s[:, 1, 0] + theta[:, 1, 0] - GOAL) ** 2) - theta[:, 1, 0] ** 2
    return s, theta, r


def make_two_step(seed):
    return TimeIndexedHiREPS.create(
        2, 1, 1, n_options=3, init_std=1.0, epsilon=0.5, min_variance=1e-3, seed=seed
    )


def run_two_step(seed, iterations, algo=None):
    algo = algo or make_two_step(seed)
    gen = torch.Generator().manual_seed(seed + 1000 * algo.iteration)
    history = []
    for _ in range(iterations):
        history.append(algo.tell(*two_step_episodes(algo, 50, gen)))
    return algo, history


def test_tell_reports_per_step_diagnostics_and_meets_the_bounds(gen):
    algo = TimeIndexedHiREPS.create(3, 2, 2, n_options=3, epsilon=[0.3, 0.5, 0.8], seed=0)
    N = 60
    s = torch.zeros(N, 3, 2, dtype=torch.float64)
    theta = torch.zeros(N, 3, 2, dtype=torch.float64)
    s[:, 0] = torch.randn(N, 2, generator=gen, dtype=torch.float64)
    for k in range(3):
        theta[:, k] = algo.ask(k, s[:, k])
        if k < 2:
            s[:, k + 1] = s[:, k] + 0.5 * theta[:, k]
    r = -(s + theta - 1.0).pow(2).sum(-1)
    assert theta.dtype == torch.float64
    entropy = [float(p.option_entropy(s[:, k], theta[:, k])) for k, p in enumerate(algo.policies)]
    d = algo.tell(s, theta, r)
    for key in ("eta", "xi", "kappa", "kl", "cross_entropy", "effective_sample_size"):
        assert len(d[key]) == 3 and all(math.isfinite(x) for x in d[key]), key
    for key in ("option_entropy", "policy_entropy", "n_active_options", "pruned"):
        assert len(d[key]) == 3, key
    assert d["kl"] == pytest.approx([0.3, 0.5, 0.8], abs=1e-3)
    assert d["option_entropy"] == pytest.approx(entropy)
    assert d["kappa"] == pytest.approx([0.9 * h for h in entropy])
    assert all(ce <= kap + 1e-3 for ce, kap in zip(d["cross_entropy"], d["kappa"], strict=True))
    assert d["feature_error"] < 1e-5 and d["dual_converged"]
    assert d["mean_return"] == pytest.approx(float(r.sum(1).mean()))
    assert d["iteration"] == 1 and algo.value_weights.shape == (3, 5)
    assert algo.value(2, s[:4, 2]).shape == (4,)


def test_two_step_sequencing_learns_to_set_up_the_second_step():
    """Seeds 0-2 (a seed falls short now and then: 10 and 11 of seeds 0-11 reached the greedy
    return below with two draw layouts): at least two of three learn to set up the second step."""
    learned = 0
    for seed in range(3):
        algo, history = run_two_step(seed, 12)
        first, last = history[0]["mean_return"], history[-1]["mean_return"]
        assert first < -3.0  # from far (seeds 0-11: -4.6 to -14.5); the optimum is about -0.34
        # the duals stay solved as the policies converge and the rewards become predictable
        assert all(d["dual_converged"] and d["feature_error"] < 1e-5 for d in history)
        assert all(max(abs(kl - 0.5) for kl in d["kl"]) < 1e-3 for d in history)
        _, _, r = two_step_episodes(algo, 500, torch.Generator().manual_seed(7), greedy=True)
        # step 1 moves towards the goal although its own reward only penalises moving: the
        # chained value of the state it reaches pays for it (a myopic learner keeps theta_1 = 0)
        zero = torch.zeros(1, 1, dtype=torch.float64)
        learned += (
            last > -0.45
            and float(r.sum(1).mean()) > -0.36
            and abs(float(algo.act(0, zero)) - GOAL / 1.2) < 0.1
            and abs(float(algo.act(1, zero + 1.5)) - (GOAL - 1.5) / 2) < 0.05
        )
    assert learned >= 2


def test_same_seed_same_run_and_state_dict_resume():
    a, ha = run_two_step(1, 4)
    _, hb = run_two_step(1, 4)
    _, hc = run_two_step(2, 4)
    assert ha == hb and ha != hc
    # a checkpoint continues bit-for-bit in a fresh instance
    fresh = make_two_step(99)
    fresh.load_state_dict(a.state_dict())
    _, cont_a = run_two_step(1, 2, a)
    _, cont_f = run_two_step(1, 2, fresh)
    assert cont_a == cont_f
    for pa, pf in zip(a.policies, fresh.policies, strict=True):
        for key, value in pa.state_dict().items():
            assert torch.equal(value, pf.state_dict()[key])
    assert torch.equal(a.value_weights, fresh.value_weights)
    assert torch.equal(a.generator.get_state(), fresh.generator.get_state())
    assert a.iteration == fresh.iteration == 6


def test_steps_with_different_option_counts_are_stacked():
    # prune step 1 to a single option: its log p~ is padded and it gets no entropy bound
    algo = make_two_step(0)
    algo.policies[1].gating.active[1:] = False
    gen = torch.Generator().manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = algo.tell(*two_step_episodes(algo, 50, gen))
    assert d["n_active_options"] == [3, 1]
    assert math.isnan(d["kappa"][1]) and d["xi"][1] == 0.0 and d["cross_entropy"][1] == 0.0
    assert d["kl"] == pytest.approx([0.5, 0.5], abs=1e-3)


def test_algorithm_bad_input_names_the_value():
    algo = make_two_step(0)
    s, theta, r = two_step_episodes(algo, 10, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"step must be in \[0, 2\).*got 2"):
        algo.ask(2, s[:, 0])
    with pytest.raises(ValueError, match=r"step must be in \[0, 2\).*got -1"):
        algo.act(-1, s[:, 0])
    with pytest.raises(ValueError, match="step must be an integer"):
        algo.ask(0.5, s[:, 0])
    with pytest.raises(ValueError, match=r"contexts must have shape \(N, 1\)"):
        algo.ask(0, torch.zeros(5, 2))
    with pytest.raises(ValueError, match="contexts contains non-finite"):
        algo.ask(0, torch.full((5, 1), math.nan))
    with pytest.raises(ValueError, match=r"rewards must have shape \(N, K\) = \(N, 2\)"):
        algo.tell(s, theta, r[:, :1])
    with pytest.raises(ValueError, match=r"states must have shape \(10, 2, 1\)"):
        algo.tell(s[:, :1], theta, r)
    with pytest.raises(ValueError, match=r"params must have shape \(10, 2, 1\)"):
        algo.tell(s, theta[:9], r)
    bad = r.clone()
    bad[3, 1] = math.nan
    before = algo.state_dict()["policies"][0]["options.0.bias"].clone()
    with pytest.raises(ValueError, match="rewards contains 1 non-finite"):
        algo.tell(s, theta, bad)
    assert torch.equal(algo.policies[0].options[0].bias, before) and algo.iteration == 0
    with pytest.raises(ValueError, match="epsilon"):
        TimeIndexedHiREPS.create(2, 1, 1, epsilon=[0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match=r"init_mean must have shape \(D,\) = \(1,\)"):
        TimeIndexedHiREPS.create(2, 1, 1, init_mean=torch.zeros(3, 1))
    with pytest.raises(ValueError, match="K"):
        TimeIndexedHiREPS.create(0, 1, 1)


def test_too_few_episodes_for_the_chained_features_keep_the_kl_bound():
    # 10 episodes against 3 x 5 chained value features: the feature constraints often cannot be
    # met; the solver must then relax them (warning) rather than let the weights collapse
    # onto one episode (KL = log 10 = 2.3 against epsilon = 1 before the fix). The KL bound
    # holds by construction, and a solve that is not converged says so with a warning.
    # Before the final eta search, seeds 1, 4, 5, 6, 8 and 16 broke the bound (1.03, 1.0008,
    # 1.007, 1.07 on one CPU, 1.004, 1.004) and 4, 7 and 16 stopped short without a warning;
    # those seeds and seed 0 (each solve takes ~1 s: the ridge fallback re-solves).
    q = QuadraticFeatures(2)
    for seed in (0, 1, 4, 5, 6, 7, 8, 16):
        gen = torch.Generator().manual_seed(seed)
        s = torch.randn(10, 3, 2, generator=gen, dtype=torch.float64)
        s = s + torch.tensor([1.5, 0.0], dtype=torch.float64)
        R = 0.5 * torch.randn(10, 3, generator=gen, dtype=torch.float64)
        R[:, -1] += torch.randint(0, 4, (10,), generator=gen)
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always")
            sol = solve_time_indexed_dual(R, q(s), epsilon=1.0)
        assert torch.isfinite(sol.weights).all()
        assert bool((sol.weights >= 0).all())
        assert torch.allclose(sol.weights.sum(dim=(1, 2)), torch.ones(3, dtype=torch.float64))
        assert float(sol.kl.max()) <= 1.0 * (1 + 1e-6), (seed, sol.kl.tolist())
        assert sol.converged or any(issubclass(r.category, RuntimeWarning) for r in record)
