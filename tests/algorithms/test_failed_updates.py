"""A failed update or load changes nothing: policies, value weights, generator and iteration are
compared in full before and after every call with a bad input, including failures that come
late (the dual raises, the last step's refit fails after the others were computed)."""

import copy
import math

import pytest
import torch

from hireps_torch.algorithms import (
    REPS,
    EpisodicHiREPS,
    Experience,
    InfiniteHorizonHiREPS,
    TimeIndexedHiREPS,
)
from hireps_torch.features import QuadraticFeatures

f64 = torch.float64
NAN = math.nan


def snapshot(algo):
    return copy.deepcopy(algo.state_dict())


def assert_same(a, b, where="state"):
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


def expect_unchanged(algo, call, match, error=ValueError):
    before = snapshot(algo)
    with pytest.raises(error, match=match):
        call()
    assert_same(before, snapshot(algo))


# ---- one small problem per variant, after one informative update --------------------------------
def episodic_data(algo, n=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    s = torch.rand(n, 1, generator=g, dtype=f64) * 2 - 1
    theta = algo.ask(s)
    return s, theta, -((theta - torch.cat([s, -s], 1)) ** 2).sum(1)


def make_episodic():
    algo = EpisodicHiREPS.create(2, context_dim=1, n_options=3, epsilon=0.5, seed=1)
    algo.tell(*episodic_data(algo))
    return algo


def ti_data(algo, n=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    s1 = torch.rand(n, 1, generator=g, dtype=f64) * 2 - 1
    a1 = algo.ask(0, s1)
    a2 = algo.ask(1, s1 + a1)
    s, a = torch.stack([s1, s1 + a1], 1), torch.stack([a1, a2], 1)
    return s, a, -((s + a - 1) ** 2).sum(-1)


def make_ti():
    algo = TimeIndexedHiREPS.create(2, 1, 1, n_options=3, init_std=1.0, epsilon=0.5, seed=3)
    algo.tell(*ti_data(algo))
    return algo


def ih_data(algo, n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    s = torch.rand(n, 1, generator=g, dtype=f64) * 4 - 2
    a = algo.sample(s)
    return s, a, -(s[:, 0] ** 2) - 0.1 * a[:, 0] ** 2, s + 0.5 * a


def make_ih(seed=0, update=True):
    start = torch.linspace(-2, 2, 41, dtype=f64)[:, None]
    algo = InfiniteHorizonHiREPS.create(
        1, 1, value_features=QuadraticFeatures(1), initial_states=start, gamma=0.9,
        n_options=3, init_std=1.0, epsilon=0.5, seed=seed,
    )  # fmt: skip
    if update:
        algo.update(*ih_data(algo))
    return algo


# ---- bad inputs ---------------------------------------------------------------------------------
def test_episodic_tell_with_bad_input_changes_nothing():
    algo = make_episodic()
    s, th, R = episodic_data(algo, seed=1)
    R_nan = R.clone()
    R_nan[3] = NAN
    for args, match in [
        ((s, th, R[:, None]), r"returns must have shape \(30,\) .*got \(30, 1\)"),
        ((s, th, R[None]), r"returns must have shape \(30,\) .*got \(1, 30\)"),
        ((s, th, R_nan), "returns contains 1 non-finite"),
        ((s, th[:, :1], R), r"params must have shape \(30, 2\)"),
        ((s[:5], th, R), "got 5 contexts for 30"),
        ((s * NAN, th, R), "contexts contains non-finite"),
        ((s, th * NAN, R), "params contains"),
        ((s[:1], th[:1], R[:1]), "at least 2 samples"),
        ((None, th, R), "contextual"),
        ((s, th.to("meta"), R), "device meta"),
        ((s, th, R.to(torch.complex128)), "real numbers"),
    ]:
        expect_unchanged(algo, lambda a=args: algo.tell(*a), match, (ValueError, TypeError))
    bad = Experience(s[:, None], th[:, None], R[:, None], next_states=s[:, None])
    expect_unchanged(algo, lambda: algo.learn(bad), "next_states")


def test_time_indexed_tell_with_bad_input_changes_nothing():
    algo = make_ti()
    s, a, r = ti_data(algo, seed=1)
    for args, match in [
        ((s, a, r[..., None]), r"rewards must have shape \(N, K\) = \(N, 2\), got \(30, 2, 1\)"),
        ((s, a, r.reshape(-1)), r"rewards must have shape \(N, K\) = \(N, 2\), got \(60,\)"),
        ((s, a, r.masked_fill(r < -1, NAN)), "rewards contains"),
        ((s[:, :1], a, r), r"states must have shape \(30, 2, 1\)"),
        ((s, a[:20], r), r"params must have shape \(30, 2, 1\)"),
        ((s, a * NAN, r), "params contains"),
    ]:
        expect_unchanged(algo, lambda x=args: algo.tell(*x), match)
    expect_unchanged(algo, lambda: algo.learn(Experience(s, a, r[:, :1])), r"\(N, 2\)")


def test_infinite_horizon_update_with_bad_input_changes_nothing():
    algo = make_ih()
    s, a, r, s2 = ih_data(algo, seed=1)
    term = torch.zeros(40, dtype=torch.bool)
    for args, match in [
        ((s, a, r[:, None], s2), r"rewards must have shape \(40,\) .*got \(40, 1\)"),
        ((s, a, r[None], s2), r"rewards must have shape \(40,\)"),
        ((s, a, r, s2[:-1]), r"next_states must have shape \(40, 1\)"),
        ((s, a, r, s2 * NAN), "next_states contains"),
        ((s, a[:, [0, 0]], r, s2), r"actions must have shape \(40, 1\)"),
        ((s, a, r, s2, term[:-1]), "terminated"),
        ((s, a, r, s2, term[:, None]), r"terminated must be a bool tensor of shape \(40,\)"),
        ((s, a, r, s2, term.long()), "terminated must be a bool"),
        ((s[:1], a[:1], r[:1], s2[:1]), "at least 2 decisions"),
        ((s[:, [0, 0]], a, r, s2), r"states must have shape \(N, 1\), got \(40, 2\)"),
    ]:
        expect_unchanged(algo, lambda x=args: algo.update(*x), match)


# ---- late failures: the dual, or the last refit --------------------------------------------------
@pytest.mark.parametrize(
    "make, data, call, dual",
    [
        (make_episodic, episodic_data, "tell", "episodic.episodic_solution"),
        (make_ti, ti_data, "tell", "time_indexed.time_indexed_solution"),
        (make_ih, ih_data, "update", "infinite_horizon.infinite_horizon_solution"),
    ],
)
def test_a_late_failure_changes_nothing(make, data, call, dual, monkeypatch):
    algo = make()
    args = data(algo, seed=2)

    def broken(*a, **k):
        raise RuntimeError("the dual failed (injected)")

    with monkeypatch.context() as m:
        m.setattr(f"hireps_torch.algorithms.{dual}", broken)
        expect_unchanged(algo, lambda: getattr(algo, call)(*args), "injected", RuntimeError)
    # the last policy's last option fails after everything before it was computed
    last = algo.policies[-1].sub_policies[-1]

    def fail(*a, **k):
        raise ValueError("the covariance overflows (injected)")

    monkeypatch.setattr(last, "fit_checked", fail)
    expect_unchanged(algo, lambda: getattr(algo, call)(*args), "option 2: .*injected")
    monkeypatch.undo()
    getattr(algo, call)(*args)  # and the same call then works
    assert algo.iteration == 2


@pytest.mark.parametrize(
    "make, data, call, dual",
    [
        (make_episodic, episodic_data, "tell", "episodic.episodic_solution"),
        (make_ti, ti_data, "tell", "time_indexed.time_indexed_solution"),
        (make_ih, ih_data, "update", "infinite_horizon.infinite_horizon_solution"),
    ],
)
def test_non_finite_weights_from_the_dual_are_refused_and_change_nothing(
    make, data, call, dual, monkeypatch
):
    import dataclasses
    import importlib

    algo = make()
    args = data(algo, seed=3)
    module, name = dual.split(".")
    solve = getattr(importlib.import_module(f"hireps_torch.algorithms.{module}"), name)

    def nan_weights(*a, **k):  # a dual that regressed: one weight NaN
        sol = solve(*a, **k)
        w = sol.weights.clone()
        w[0, -1, 0, 0] = math.nan
        return dataclasses.replace(sol, weights=w)

    monkeypatch.setattr(f"hireps_torch.algorithms.{dual}", nan_weights)
    expect_unchanged(
        algo, lambda: getattr(algo, call)(*args), "the dual returned non-finite weights"
    )


def test_parameters_that_overflow_the_refit_are_refused_and_change_nothing():
    algo = REPS.create(2, init_std=1.0, seed=0)
    th = algo.ask(20)
    R = -(th**2).sum(1)
    th[4] = 1e200
    expect_unchanged(algo, lambda: algo.tell(None, th, R), "option 0: the weighted fit overflows")
    hi = EpisodicHiREPS.create(2, n_options=3, seed=0)
    expect_unchanged(hi, lambda: hi.tell(None, th, R), r"theta\[4\] has zero density")


# ---- load_state_dict ----------------------------------------------------------------------------
def test_load_state_dict_refuses_what_does_not_fit_and_changes_nothing():
    algo = make_episodic()
    other_o = EpisodicHiREPS.create(2, context_dim=1, n_options=5).state_dict()
    other_d = EpisodicHiREPS.create(3, context_dim=1, n_options=3).state_dict()
    missing = snapshot(algo)
    del missing["kappa_rel"]
    no_key = snapshot(algo)
    del no_key["policy"]["options.2.chol"]
    cases = [
        (other_o, r"gating.weight: saved \(5, 2\), expected \(3, 2\)"),
        (other_d, r"options.0.weight: saved \(3, 1\), expected \(2, 1\)"),
        (make_ti().state_dict(), r"missing keys \['policy'\].*TimeIndexedHiREPS"),
        (make_ih().state_dict(), r"unexpected keys \['gamma', 'value_weights'\]"),
        (missing, r"missing keys \['kappa_rel'\]"),
        (no_key, r"missing keys \['options.2.chol'\]"),
        (snapshot(algo) | {"epsilon": -1.0}, "epsilon must be finite and > 0"),
        (snapshot(algo) | {"epsilon": torch.ones(2)}, "epsilon must be one number"),
        (snapshot(algo) | {"kappa_rel": NAN}, "kappa_rel"),
        (snapshot(algo) | {"iteration": -1}, "iteration must be >= 0"),
        (snapshot(algo) | {"generator": torch.zeros(3, dtype=torch.uint8)}, "generator"),
    ]
    for state, match in cases:
        expect_unchanged(algo, lambda st=state: algo.load_state_dict(st), match)
    expect_unchanged(algo, lambda: algo.load_state_dict(None), "mapping", TypeError)


def test_load_state_dict_of_the_other_variants_changes_nothing():
    ti, ih = make_ti(), make_ih()
    other_k = TimeIndexedHiREPS.create(3, 1, 1, n_options=3).state_dict()
    other_o = TimeIndexedHiREPS.create(2, 1, 1, n_options=2).state_dict()
    bad_v = snapshot(ti) | {"value_weights": torch.zeros(2, 7)}
    nan_v = snapshot(ih) | {"value_weights": torch.full((2,), NAN)}
    for algo, state, match in [
        (ti, other_k, "the state holds 3 policies, this algorithm has K = 2"),
        (ti, other_o, r"step 0: .*gating.weight: saved \(2, 2\), expected \(3, 2\)"),
        (ti, bad_v, r"value_weights: saved \(2, 7\), expected \(2, 2\)"),
        (ti, snapshot(ti) | {"epsilon": [0.5]}, "one float or 2"),
        (ti, make_episodic().state_dict(), r"missing keys \['policies', 'value_weights'\]"),
        (ih, nan_v, "value_weights contains"),
        (ih, snapshot(ih) | {"gamma": 1.0}, r"gamma must be in \(0, 1\)"),
        (ih, make_ti().state_dict(), "TimeIndexedHiREPS"),
    ]:
        expect_unchanged(algo, lambda a=algo, st=state: a.load_state_dict(st), match)
    # a checkpoint written before the infinite-horizon variant had a generator still loads
    # (into an algorithm that differs in every entry) and keeps the current generator
    old = snapshot(ih)
    del old["generator"]
    fresh = make_ih(seed=3, update=False)
    generator = fresh.generator.get_state()
    assert not torch.equal(fresh.value_weights, old["value_weights"])
    fresh.load_state_dict(old)
    assert_same(fresh.state_dict(), old | {"generator": generator})


def test_bad_sampling_calls_do_not_advance_the_generator():
    algo, ti = make_episodic(), make_ti()
    for call, match in [
        (lambda: algo.ask(torch.zeros(4, 2)), r"contexts must have shape \(N, 1\)"),
        (lambda: algo.ask(torch.zeros(0, 1)), "at least one context"),
        (lambda: algo.ask(5), "contextual"),
        (lambda: algo.sample(torch.zeros(4, 1), 1), r"step must be in \[0, 1\)"),
        (lambda: ti.ask(2, torch.zeros(4, 1)), r"step must be in \[0, 2\)"),
        (lambda: ti.ask(True, torch.zeros(4, 1)), "step must be an integer"),
        (lambda: ti.ask(0, torch.full((4, 1), NAN)), "contexts contains non-finite"),
    ]:
        before = snapshot(algo), snapshot(ti)
        with pytest.raises(ValueError, match=match):
            call()
        assert_same(before, (snapshot(algo), snapshot(ti)))


@pytest.mark.parametrize("seed", [0, [0, 1]], ids=["one seed", "population"])
@pytest.mark.parametrize("failure", ["memory", "other"])
def test_a_sample_that_fails_after_drawing_leaves_the_generators_and_names_memory(
    monkeypatch, seed, failure
):
    algo = EpisodicHiREPS.create(param_dim=2, n_options=3, seed=seed)
    fresh = EpisodicHiREPS.create(param_dim=2, n_options=3, seed=seed)
    einsum = torch.einsum
    calls = []

    def failing_einsum(*args):  # the second einsum runs after the option and noise draws
        calls.append(args[0])
        if len(calls) == 2:
            if failure == "memory":
                raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried ...")
            raise ValueError("something else")
        return einsum(*args)

    monkeypatch.setattr(torch, "einsum", failing_einsum)
    before = snapshot(algo)
    if failure == "memory":
        with pytest.raises(MemoryError, match=r"sampling N = 40 needs .*N x 3 options x 2"):
            algo.ask(40)
    else:
        with pytest.raises(ValueError, match="something else"):
            algo.ask(40)
    assert len(calls) == 2
    assert_same(before, snapshot(algo))
    monkeypatch.setattr(torch, "einsum", einsum)
    assert torch.equal(algo.ask(5), fresh.ask(5))


def test_a_mean_action_past_memory_and_counts_past_int64_are_named(monkeypatch):
    """They were torch's allocator error and 'Overflow when unpacking long long'."""
    algo = EpisodicHiREPS.create(param_dim=2, n_options=3, seed=0)
    for call in (algo.ask, algo.act, algo.mean_action):
        with pytest.raises(
            ValueError, match=r"number of samples must be below 2\*\*63, got 9223372036854775808"
        ):
            call(2**63)

    def no_memory(*args):
        raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried ...")

    monkeypatch.setattr(algo.policy, "mean_action", no_memory)
    with pytest.raises(MemoryError, match=r"the mean action of N = 40 needs N x 3 options x 2"):
        algo.act(40)


def test_sampling_from_the_global_rng_or_a_tuple_of_generators_still_works():
    algo = EpisodicHiREPS.create(param_dim=2, n_options=3, seed=[0, 1])
    algo.generator = tuple(algo.generator)
    assert algo.ask(4).shape == (2, 4, 2)
    algo.generator = None  # the global RNG
    assert algo.ask(4).shape == (2, 4, 2)
