"""Populations of duals (``population=True``): S independent problems solved together equal S
separate solves, share nothing, and keep every promise per problem."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from hireps_torch.dual import (
    DualSolution,
    InfeasibleConstraintsWarning,
    solve_episodic_dual,
    solve_infinite_horizon_dual,
    solve_time_indexed_dual,
)

F64 = torch.float64
S = 5


def randn(gen, *shape):
    return torch.randn(*shape, generator=gen, dtype=F64)


def soft(gen, *shape):
    return torch.log_softmax(2.0 * randn(gen, *shape), -1)


def entropy(lr):
    return float(-(lr.exp() * lr).sum(-1).mean())


def episodic_case(gen, options, context):
    R = randn(gen, S, 30)
    kw = {"epsilon": 0.5}
    if options:
        lr = soft(gen, S, 30, 3)
        kw |= {"log_responsibilities": lr, "kappa": 0.8 * entropy(lr)}
    if context:
        kw["context_features"] = randn(gen, S, 30, 3)
    return solve_episodic_dual, (R,), kw


def infinite_horizon_case(gen, options, context):
    phi, phi_next = randn(gen, S, 40, 4), randn(gen, S, 40, 4)
    kw = {"epsilon": 0.5, "gamma": 0.9}
    if options:
        lr = soft(gen, S, 40, 3)
        kw |= {"log_responsibilities": lr, "kappa": 0.8 * entropy(lr)}
    phi0 = phi.mean(1) if context else phi.mean((0, 1))  # per problem, or one shared (F,)
    return solve_infinite_horizon_dual, (randn(gen, S, 40), phi, phi_next, phi0), kw


def time_indexed_case(gen, options, context):
    R = randn(gen, S, 30, 3)
    kw = {"epsilon": torch.tensor([0.5, 0.7, 0.9], dtype=F64)}
    if options:
        lr = soft(gen, S, 30, 3, 2)
        kw |= {"log_responsibilities": lr, "kappa": 0.8 * entropy(lr)}
    return solve_time_indexed_dual, (R, randn(gen, S, 30, 3, 2 if context else 1)), kw


CASES = {
    "episodic": episodic_case,
    "infinite_horizon": infinite_horizon_case,
    "time_indexed": time_indexed_case,
}


def one(x, s, shared_vector=False):
    """Problem s of a population input (a tensor with a leading S, or anything else)."""
    if isinstance(x, torch.Tensor) and x.dim() >= 2 and x.shape[0] == S:
        return x[s]
    return x


def separate(fn, args, kw, s):
    return fn(*(one(a, s) for a in args), **{k: one(v, s) for k, v in kw.items()})


@pytest.mark.parametrize("options", [False, True])
@pytest.mark.parametrize("context", [False, True])
@pytest.mark.parametrize("variant", list(CASES))
def test_a_population_equals_separate_solves(variant, options, context):
    gen = torch.Generator().manual_seed(3)
    fn, args, kw = CASES[variant](gen, options, context)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every problem here converges: no warning at all
        pop = fn(*args, **kw, population=True)
        singles = [separate(fn, args, kw, s) for s in range(S)]
    assert isinstance(pop, DualSolution) and all(isinstance(sol, DualSolution) for sol in singles)
    assert pop.converged.shape == pop.iterations.shape == (S,) and bool(pop.converged.all())
    assert pop.kl.shape == pop.eta.shape == pop.xi.shape == pop.effective_sample_size.shape
    for s, sol in enumerate(singles):
        # member s of the population is shaped as the separate solve, every field
        member = pop.problem(s)
        for name in ("eta", "xi", "v", "weights", "kl", "dual_value", "iterations"):
            assert getattr(member, name).shape == getattr(sol, name).shape, name
        assert torch.allclose(member.weights, sol.weights, rtol=0, atol=1e-10), s
        assert torch.allclose(member.eta, sol.eta, rtol=1e-8, atol=0), (s, member.eta, sol.eta)
        assert torch.allclose(member.kl, sol.kl, rtol=0, atol=1e-9), s
        assert torch.allclose(member.xi, sol.xi, rtol=1e-6, atol=1e-10), (s, member.xi, sol.xi)
        assert torch.allclose(member.v, sol.v, rtol=1e-7, atol=1e-9), s
        assert float(member.kl.max()) <= 0.9 * (1 + 1e-6)


@pytest.mark.parametrize("variant", list(CASES))
def test_copies_of_one_problem_get_the_same_solution(variant):
    gen = torch.Generator().manual_seed(4)
    fn, args, kw = CASES[variant](gen, True, True)

    def copies(x):
        return x[:1].expand(S, *x.shape[1:]).clone() if isinstance(x, torch.Tensor) else x

    args = tuple(copies(a) if a.dim() >= 2 else a for a in args)
    kw = {
        k: copies(v) if isinstance(v, torch.Tensor) and v.dim() >= 2 else v for k, v in kw.items()
    }
    pop = fn(*args, **kw, population=True)
    for field in ("weights", "eta", "xi", "v", "kl", "dual_value"):
        value = getattr(pop, field)
        assert torch.equal(value, value[:1].expand_as(value)), field


def test_a_fallback_in_one_problem_leaves_the_others_alone():
    # problem 1's start features lie far outside what its transitions can reach: its feature
    # constraints cannot be met within the KL bound and it is re-solved with a ridge; the
    # others are not touched
    gen = torch.Generator().manual_seed(5)
    phi, phi_next = randn(gen, 3, 40, 2), randn(gen, 3, 40, 2)
    phi0 = (phi - 0.9 * phi_next).mean(1) / 0.1  # met by the uniform weights
    phi0[1] = 50.0
    lr = soft(gen, 3, 40, 2)
    R = randn(gen, 3, 40)
    kw = {"gamma": 0.9, "epsilon": 0.3, "log_responsibilities": lr}
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        pop = solve_infinite_horizon_dual(R, phi, phi_next, phi0, population=True, **kw)
    texts = [str(r.message) for r in record if issubclass(r.category, RuntimeWarning)]
    assert texts and all(t.startswith("member 1: ") for t in texts), texts
    assert "cannot be met within the KL bound" in texts[0]
    assert pop.converged.tolist() == [True, False, True]
    assert bool((pop.kl <= 0.3 * (1 + 1e-6)).all())
    for s in (0, 2):
        alone = solve_infinite_horizon_dual(
            R[s], phi[s], phi_next[s], phi0[s], **{**kw, "log_responsibilities": lr[s]}
        )
        assert torch.allclose(pop.weights[s], alone.weights, rtol=0, atol=1e-10)
        assert float(pop.eta[s]) == pytest.approx(float(alone.eta), rel=1e-8)


def test_a_population_of_one_is_the_single_solve():
    gen = torch.Generator().manual_seed(6)
    R, lr, phi = randn(gen, 1, 20), soft(gen, 1, 20, 3), randn(gen, 1, 20, 2)
    kw = {"epsilon": 0.4, "kappa": 0.8 * entropy(lr)}
    pop = solve_episodic_dual(
        R, log_responsibilities=lr, context_features=phi, population=True, **kw
    )
    alone = solve_episodic_dual(R[0], log_responsibilities=lr[0], context_features=phi[0], **kw)
    assert torch.equal(pop.weights[0], alone.weights)
    assert float(pop.eta[0]) == alone.eta and bool(pop.converged[0]) == alone.converged


@pytest.mark.parametrize(
    "call, message",
    [
        (
            lambda: solve_episodic_dual(torch.zeros(10), epsilon=0.5, population=True),
            r"returns must have shape \(S, N\), got \(10,\)",
        ),
        (
            lambda: solve_episodic_dual(torch.zeros(3, 10), epsilon=0.5),
            r"returns must have shape \(N,\), got \(3, 10\)",
        ),
        (
            lambda: solve_episodic_dual(
                torch.zeros(3, 10),
                epsilon=0.5,
                population=True,
                log_responsibilities=torch.zeros(2, 10, 1),
            ),
            r"log_responsibilities must have shape \(S, N, O\) = \(3, 10, O\), got \(2, 10, 1\)",
        ),
        (
            lambda: solve_episodic_dual(
                torch.zeros(3, 10),
                epsilon=0.5,
                population=True,
                context_features=torch.zeros(10, 2),
            ),
            r"context_features must have shape \(S, N, F\) = \(3, 10, F\), got \(10, 2\)",
        ),
        (
            lambda: solve_infinite_horizon_dual(
                torch.zeros(3, 10),
                torch.zeros(3, 10, 2),
                torch.zeros(3, 10, 2),
                torch.zeros(2, 2),
                gamma=0.9,
                epsilon=0.5,
                population=True,
            ),
            r"initial_features must have shape \(2,\) or \(3, 2\), got \(2, 2\)",
        ),
        (
            lambda: solve_time_indexed_dual(
                torch.zeros(3, 10, 2), torch.zeros(3, 10, 3, 1), epsilon=0.5, population=True
            ),
            r"features must have shape \(S, N, K, F\) = \(3, 10, 2, F\), got \(3, 10, 3, 1\)",
        ),
        (
            lambda: solve_episodic_dual(
                torch.tensor([[0.0, 1.0], [0.0, math.nan]]), epsilon=0.5, population=True
            ),
            r"returns",
        ),
    ],
)
def test_bad_population_inputs_name_the_value(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_an_entropy_bound_out_of_reach_is_relaxed_in_its_own_problem_only():
    gen = torch.Generator().manual_seed(7)
    R, lr = randn(gen, 3, 30), soft(gen, 3, 30, 3)
    lr[2] = torch.log_softmax(0.01 * randn(gen, 30, 3), -1)  # nearly uniform: CE ~ log 3
    with pytest.warns(InfeasibleConstraintsWarning, match=r"^member 2: .*entropy bound"):
        pop = solve_episodic_dual(
            R, epsilon=0.05, log_responsibilities=lr, kappa=0.3, population=True
        )
    assert not bool(pop.converged[2])
    for s in (0, 1):
        alone = solve_episodic_dual(R[s], epsilon=0.05, log_responsibilities=lr[s], kappa=0.3)
        assert torch.allclose(pop.weights[s], alone.weights, rtol=0, atol=1e-10)


def test_population_must_be_a_bool():
    with pytest.raises(TypeError, match="population must be True or False, got 'yes'"):
        solve_episodic_dual(torch.zeros(3, 10), epsilon=0.5, population="yes")


def test_a_run_off_is_detected_per_problem():
    # problem 0 sits at its eta floor with a small residual (no conflict); problem 1's v ran
    # past V_MAX: only problem 1 is flagged, whatever problem 0 does
    from hireps_torch.dual.problem import V_MAX, DualProblem

    gen = torch.Generator().manual_seed(8)
    R, D = randn(gen, 2, 1, 20), randn(gen, 2, 1, 20, 2)
    D[0] = 0.0  # problem 0's feature constraint holds for any weights: residual 0
    prob = DualProblem(
        R,
        D,
        None,
        torch.zeros(2, 1, 20, 1, dtype=F64),
        torch.full((2, 1), 0.5, dtype=F64),
        torch.zeros(2, 1, dtype=F64),
    )
    x = torch.zeros(2, 4, dtype=F64)
    x[0, 0] = prob.log_eta_min[0, 0] - 1.0
    x[1, 2] = 2 * V_MAX
    g = prob.evaluate(x)[0]
    assert prob.shows_conflict(x, g).tolist() == [False, True]


def test_unconverged_problems_are_solved_again_alone():
    # one LBFGS iteration per phase: no problem converges within it; each is solved again
    # alone and ends where its own solve ends (up to round-off of the shared conditioning)
    gen = torch.Generator().manual_seed(9)
    R, lr, phi = randn(gen, 3, 40), soft(gen, 3, 40, 3), randn(gen, 3, 40, 2)
    kw = {"epsilon": 0.5, "kappa": 0.8 * entropy(lr), "max_iter": 1}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pop = solve_episodic_dual(
            R, log_responsibilities=lr, context_features=phi, population=True, **kw
        )
        for s in range(3):
            alone = solve_episodic_dual(
                R[s], log_responsibilities=lr[s], context_features=phi[s], **kw
            )
            assert bool(pop.converged[s]) == alone.converged
            assert torch.allclose(pop.weights[s], alone.weights, rtol=0, atol=1e-8), s


def test_problems_solved_side_by_side_equal_one_after_the_other(monkeypatch):
    # the pool of idle cores changes nothing: the same answers, bit for bit, and each
    # problem's warning in the problems' order, attributed to the caller
    import hireps_torch._parallel as parallel

    gen = torch.Generator().manual_seed(5)
    phi, phi_next = randn(gen, 4, 40, 2), randn(gen, 4, 40, 2)
    phi0 = (phi - 0.9 * phi_next).mean(1) / 0.1
    phi0[1] = phi0[3] = 50.0  # problems 1 and 3 fall back (a warning each)
    args = (randn(gen, 4, 40), phi, phi_next, phi0)
    kw = {"gamma": 0.9, "epsilon": 0.3, "log_responsibilities": soft(gen, 4, 40, 2)}
    results = {}
    for workers in (1, 3):
        monkeypatch.setattr(parallel, "idle_workers", lambda device, n=workers: n)
        monkeypatch.setattr(parallel, "MIN_SIZE", 0)  # these small problems too
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always")
            results[workers] = solve_infinite_horizon_dual(*args, population=True, **kw)
        texts = [str(r.message)[:9] for r in record if issubclass(r.category, RuntimeWarning)]
        assert texts == ["member 1:", "member 3:"], (workers, texts)
        assert all(r.filename == __file__ for r in record), [r.filename for r in record]
    for field in ("weights", "eta", "xi", "v", "kl", "dual_value", "converged"):
        assert torch.equal(getattr(results[1], field), getattr(results[3], field)), field


def test_idle_workers_are_the_cores_torch_leaves_idle(monkeypatch):
    import hireps_torch._parallel as parallel
    from hireps_torch._parallel import idle_workers, member_chunks

    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1}, raising=False)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert idle_workers(torch.device("cpu")) == 2
        big, small = parallel.MIN_SIZE, parallel.MIN_SIZE - 1
        assert member_chunks(5, torch.device("cpu"), big) == [slice(0, 2), slice(2, 5)]
        assert member_chunks(5, torch.device("cpu"), small) == [slice(0, 5)]
        assert member_chunks(1, torch.device("cpu"), big) == [slice(0, 1)]
        torch.set_num_threads(2)
        assert idle_workers(torch.device("cpu")) == 1
        assert member_chunks(5, torch.device("cpu"), big) == [slice(0, 5)]
        assert idle_workers(torch.device("meta")) == 1
    finally:
        torch.set_num_threads(threads)


def test_one_solution_type_indexes_its_problems_and_blocks_or_says_why_not():
    gen = torch.Generator().manual_seed(10)
    one = solve_episodic_dual(randn(gen, 20), epsilon=0.5)
    assert one.eta.shape == () and one.weights.shape == (20, 1) and one.iterations.shape == ()
    with pytest.raises(ValueError, match="this one holds one"):
        one.problem(0)
    with pytest.raises(ValueError, match="this one has one"):
        one.step(0)
    ti = solve_time_indexed_dual(
        randn(gen, 3, 20, 2), randn(gen, 3, 20, 2, 1), epsilon=0.5, population=True
    )
    assert ti.eta.shape == (3, 2) and ti.v.shape == (3, 2, 1) and ti.weights.shape == (3, 2, 20, 1)
    member_step = ti.problem(2).step(1)
    assert torch.equal(member_step.weights, ti.weights[2, 1])
    assert torch.equal(member_step.v, ti.v[2, 1]) and member_step.eta.shape == ()
    with pytest.raises(ValueError, match=r"problem must be in \[0, 3\), got 3"):
        ti.problem(3)
