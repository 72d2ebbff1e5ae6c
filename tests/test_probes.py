"""Red-team probes: a user who misuses the library gets a ValueError / TypeError naming the
argument and the bad value or shape (or a documented fallback), never a silent NaN, a silently
reshaped input, a half-changed object or an overwritten run directory.

Most rows failed before their fix (a deep torch error, an AttributeError, a silent result);
a few pin the neighbouring cases. Cheap in-process calls, one short bimodal run, and two
``train.py`` subprocesses at the end.
"""

import copy
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from hireps_torch import EpisodicHiREPS, Experience, InfiniteHorizonHiREPS, TimeIndexedHiREPS, envs
from hireps_torch.dual import (
    solve_episodic_dual,
    solve_infinite_horizon_dual,
    solve_reps_dual,
    solve_time_indexed_dual,
)
from hireps_torch.envs import (
    BallOnBeamBatchEnv,
    BallOnBeamEnv,
    ContextualTwoGaussians,
    PendulumSwingUpBatchEnv,
    PendulumSwingUpEnv,
    TwoGaussians,
)
from hireps_torch.envs.ball_on_beam import BeamParams, beam_step, evaluate_beam
from hireps_torch.envs.ball_on_beam import sample_start as beam_start
from hireps_torch.envs.pendulum import (
    PendulumParams,
    evaluate_swing_up,
    pendulum_step,
    sample_start,
)
from hireps_torch.experiments.checkpoint import FORMAT
from hireps_torch.features import (
    ConcatFeatures,
    FourierFeatures,
    IdentityFeatures,
    QuadraticFeatures,
)
from hireps_torch.policies import ConstantGating, HierarchicalPolicy, LinearGaussian, SoftmaxGating
from hireps_torch.rollout import make_collector, policy_module, time_indexed_module

ROOT = Path(__file__).resolve().parents[1]
f64 = torch.float64
NAN, INF = math.nan, math.inf
BAD = (ValueError, TypeError)


def expect(call, match, error=BAD):
    with pytest.raises(error, match=match):
        call()


def state_of(obj):
    """Everything a failed call must leave as it was: state_dict, generator, iteration."""
    out = {"state": copy.deepcopy(obj.state_dict())}
    if hasattr(obj, "generator"):
        out["generator"] = obj.generator.get_state().clone()
    return out


def same(a, b):
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.shape == b.shape and torch.equal(a, b)
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def expect_unchanged(obj, call, match, error=BAD):
    before = state_of(obj)
    expect(call, match, error)
    assert same(state_of(obj), before)


# ---- the duals ------------------------------------------------------------------------------
_g = torch.Generator().manual_seed(0)
N = 12
R = torch.randn(N, generator=_g, dtype=f64)
LR = torch.log_softmax(torch.randn(N, 3, generator=_g, dtype=f64), -1)
PHI = torch.randn(N, 2, generator=_g, dtype=f64)
P0 = PHI.mean(0)
RK = torch.randn(N, 2, generator=_g, dtype=f64)
PHK = torch.randn(N, 2, 2, generator=_g, dtype=f64)


def ih(**kw):
    args = dict(gamma=0.9, epsilon=0.5) | kw
    return solve_infinite_horizon_dual(R, PHI, PHI.roll(1, 0), args.pop("p0", P0), **args)


DUAL_PROBES = {
    "meta returns": (lambda: solve_episodic_dual(R.to("meta"), epsilon=0.5), "returns is a meta"),
    "meta log_resp": (
        lambda: solve_episodic_dual(R, epsilon=0.5, log_responsibilities=LR.to("meta")),
        "log_responsibilities is on device meta but the other inputs are on cpu",
    ),
    "meta R generic": (
        lambda: solve_reps_dual(R[None].to("meta"), LR[None], 0.5),
        "R is a meta",
    ),
    "string returns name the value": (
        lambda: solve_episodic_dual("abc", epsilon=0.5),
        "returns must be a tensor of numbers, got str 'abc'",
    ),
    "string epsilon names the value": (
        lambda: solve_episodic_dual(R, epsilon="0.5"),
        "epsilon must be a tensor of numbers, got str '0.5'",
    ),
    "O = 0 option columns": (
        lambda: solve_episodic_dual(R, epsilon=0.5, log_responsibilities=LR[:, :0]),
        r"at least one option column, got \(12, 0\)",
    ),
    "O = 0 time-indexed": (
        lambda: solve_time_indexed_dual(
            RK, PHK, epsilon=0.5, log_responsibilities=torch.zeros(N, 2, 0)
        ),
        "at least one option column",
    ),
    "a row with every option impossible": (
        lambda: solve_episodic_dual(
            R, epsilon=0.5, log_responsibilities=LR.index_fill(0, torch.tensor([3]), -INF)
        ),
        r"row \[3\] is off by inf \(every option has probability 0\)",
    ),
    "NaN log_resp names the index": (
        lambda: solve_episodic_dual(
            R, epsilon=0.5, log_responsibilities=LR.index_fill(0, torch.tensor([2]), NAN)
        ),
        r"NaN or \+inf \(first at index \(2, 0\): nan\)",
    ),
    "gamma string": (lambda: ih(gamma="0.9"), "gamma must be a number, got str '0.9'"),
    "gamma (2,)": (lambda: ih(gamma=torch.tensor([0.9, 0.9])), r"gamma must be one number"),
    "gamma complex": (lambda: ih(gamma=0.9 + 0j), "gamma must be a number"),
    "gamma None": (lambda: ih(gamma=None), "gamma must be a number"),
    "gamma -0.0": (lambda: ih(gamma=-0.0), r"gamma must be in \(0, 1\)"),
    "initial_features (1, F)": (
        lambda: ih(p0=P0[None]),
        r"initial_features must have shape \(2,\), got \(1, 2\)",
    ),
    "initial_features (F, 1)": (
        lambda: ih(p0=P0[:, None]),
        r"initial_features must have shape \(2,\), got \(2, 1\)",
    ),
    "initial_features (N, F)": (
        lambda: ih(p0=PHI),
        r"initial_features must have shape \(2,\), got \(12, 2\)",
    ),
    "initial_features 0-d for F = 1": (
        lambda: solve_infinite_horizon_dual(
            R, PHI[:, :1], PHI[:, :1], P0[0], gamma=0.9, epsilon=0.5
        ),
        r"initial_features must have shape \(1,\), got \(\)",
    ),
    "time-indexed initial_features (1, F)": (
        lambda: solve_time_indexed_dual(RK, PHK, epsilon=0.5, initial_features=P0[None]),
        r"initial_features must have shape \(2,\), got \(1, 2\)",
    ),
    "generic c (1, P)": (
        lambda: solve_reps_dual(R[None], LR[None], 0.5, D=PHI[None], c=P0[None]),
        r"c must have shape \(2,\), got \(1, 2\)",
    ),
    "tolerance (2,)": (
        lambda: solve_reps_dual(R[None], LR[None], 0.5, tolerance_grad=torch.ones(2)),
        "tolerance_grad must be a finite number > 0",
    ),
    "converged_grad string": (
        lambda: solve_reps_dual(R[None], LR[None], 0.5, converged_grad="x"),
        "converged_grad must be a finite number > 0, got 'x'",
    ),
    "epsilon per step of another K": (
        lambda: solve_time_indexed_dual(RK, PHK, epsilon=torch.tensor([0.5, 0.5, 0.5])),
        r"epsilon must be a float or have shape \(2,\)",
    ),
    "kappa per step of another K": (
        lambda: solve_time_indexed_dual(
            RK, PHK, epsilon=0.5, log_responsibilities=LR[:, None].expand(N, 2, 3), kappa=[1.0]
        ),
        r"kappa must be a float or have shape \(2,\)",
    ),
    "epsilon -0.0": (lambda: solve_episodic_dual(R, epsilon=-0.0), "epsilon must be finite"),
    "complex returns": (
        lambda: solve_episodic_dual(R.to(torch.complex128), epsilon=0.5),
        "returns must hold real numbers",
    ),
    "3-d returns": (
        lambda: solve_episodic_dual(R[:, None, None], epsilon=0.5),
        r"returns must have shape \(N,\), got \(12, 1, 1\)",
    ),
    "N = 1": (lambda: solve_episodic_dual(R[:1], epsilon=0.5), "at least 2 samples, got N = 1"),
}


@pytest.mark.parametrize("name", list(DUAL_PROBES))
def test_dual_probes(name):
    call, match = DUAL_PROBES[name]
    expect(call, match)


def test_duals_take_numbers_and_arrays_of_any_kind():
    base = solve_episodic_dual(R, epsilon=0.5, log_responsibilities=LR, kappa=0.5)
    for returns in (R.numpy(), R.tolist()):
        sol = solve_episodic_dual(returns, epsilon=0.5, log_responsibilities=LR, kappa=0.5)
        assert torch.equal(sol.weights, base.weights)
    assert torch.isfinite(solve_episodic_dual(R > 0, epsilon=0.5).weights).all()
    np_eps = solve_episodic_dual(R, epsilon=np.float32(0.5), log_responsibilities=LR)
    assert torch.isfinite(np_eps.weights).all()


# ---- feature maps ---------------------------------------------------------------------------
FEATURE_PROBES = {
    "Fourier (1, S) low": (
        lambda: FourierFeatures([[0.0, 0.0]], [[1.0, 1.0]]),
        r"low and high must both have shape \(C,\) \(C: the state dimension\), got \(1, 2\)",
    ),
    "Fourier periodic string": (
        lambda: FourierFeatures([0.0, 0.0], [1.0, 1.0], periodic="ab"),
        "periodic must be 2 bools",
    ),
    "Fourier periodic ints": (
        lambda: FourierFeatures([0.0, 0.0], [1.0, 1.0], periodic=[1, 0]),
        r"periodic\[0\] must be a bool, got int 1",
    ),
    "Fourier too many terms": (
        lambda: FourierFeatures([0.0] * 12, [1.0] * 12, 10),
        r"n_bases \*\* state dimension = 10\^12 = 1e\+12 frequency vectors exceed",
    ),
    "Fourier NaN state": (
        lambda: FourierFeatures([0.0], [1.0])(torch.tensor([[NAN]])),
        "states given to FourierFeatures contains 1 non-finite",
    ),
    "Quadratic inf state": (
        lambda: QuadraticFeatures(2)(torch.tensor([[1.0, INF]])),
        "states given to QuadraticFeatures contains",
    ),
    "Concat of a non-map": (lambda: ConcatFeatures("x"), r"maps\[0\] must be a feature map"),
    "Concat with a non-map second": (
        lambda: ConcatFeatures(QuadraticFeatures(1), IdentityFeatures),
        r"maps\[1\] must be a feature map",
    ),
}


@pytest.mark.parametrize("name", list(FEATURE_PROBES))
def test_feature_probes(name):
    call, match = FEATURE_PROBES[name]
    expect(call, match)


def test_valid_feature_arguments_still_work():
    four = FourierFeatures(torch.tensor([-1.0, 0.0]), [1.0, 2.0], 3, periodic=np.array([1, 0]) > 0)
    assert four(torch.zeros(4, 2)).shape == (4, 2 * (3**2 - 1))
    assert FourierFeatures([0.0], [1.0], periodic=torch.tensor([True])).out_features == 8


# ---- policies -------------------------------------------------------------------------------
def fitted_policy():
    gen = torch.Generator().manual_seed(0)
    pol = HierarchicalPolicy.create(
        3, 1, 2, init_std=1.0, spread=2.0, gating_features=QuadraticFeatures(1), generator=gen
    )
    s = torch.randn(30, 1, generator=gen, dtype=f64)
    theta, _ = pol.sample(s, gen)
    w = torch.rand(30, 3, generator=gen, dtype=f64)
    pol.weighted_fit(s, theta, w)
    return pol, s, theta, w


POL, S, TH, W = fitted_policy()
C = HierarchicalPolicy.create

CONSTRUCT_PROBES = {
    "init_std bool": (lambda: C(3, 1, 2, init_std=True), "init_std must be a number.*bool"),
    "min_variance bool": (lambda: C(3, 1, 2, min_variance=True), "min_variance must be a number"),
    "gating_features string": (
        lambda: C(3, 1, 2, gating_features="quad"),
        "gating_features must be a feature map",
    ),
    "policy_features function": (
        lambda: C(3, 1, 2, policy_features=lambda x: x),
        "policy_features must be a feature map",
    ),
    "gating string": (lambda: C(3, 1, 2, gating="softmax"), "gating must be a Gating"),
    "generator int": (lambda: C(3, 1, 2, generator=0), "generator must be a torch.Generator"),
    "options not LinearGaussian": (
        lambda: HierarchicalPolicy(SoftmaxGating(1, 1), ["a"]),
        r"options\[0\] must be a LinearGaussian, got str",
    ),
    "gating not Gating": (
        lambda: HierarchicalPolicy("g", [LinearGaussian(1, 1)]),
        "gating must be a Gating",
    ),
    "LinearGaussian dtype string": (
        lambda: LinearGaussian(1, 1, dtype="float64"),
        "dtype must be a floating torch.dtype, got 'float64'",
    ),
    "SoftmaxGating dtype string": (
        lambda: SoftmaxGating(2, 3, dtype="float32"),
        "dtype must be a floating torch.dtype",
    ),
    "LinearGaussian sample generator int": (
        lambda: LinearGaussian(1, 1).sample(torch.zeros(2, 1), generator=5),
        "generator must be a torch.Generator or None, got int 5",
    ),
}


@pytest.mark.parametrize("name", list(CONSTRUCT_PROBES))
def test_policy_construction_probes(name):
    call, match = CONSTRUCT_PROBES[name]
    expect(call, match)


@pytest.mark.parametrize(
    "gating, match",
    [
        (SoftmaxGating(1, 4), "gating has 4 options but 3 sub-policies"),
        (SoftmaxGating(5, 3), "gating_features give 1 features but the gating takes 5"),
        ("x", "gating must be a Gating"),
    ],
)
def test_create_with_a_gating_that_does_not_fit_draws_nothing(gating, match):
    gen = torch.Generator().manual_seed(0)
    expect(lambda: C(3, 1, 2, gating=gating, generator=gen), match)
    assert torch.equal(gen.get_state(), torch.Generator().manual_seed(0).get_state())


FIT_PROBES = {
    "weights NaN names the index": (
        lambda: POL.weighted_fit(S, TH, W.index_fill(0, torch.tensor([4]), NAN)),
        r"weights contains 3 non-finite value\(s\) \(first at index \(4, 0\): nan\)",
    ),
    "weights negative names the index": (
        lambda: POL.weighted_fit(S, TH, W - W[2, 1] - 1e-3),
        "weights must be non-negative, got .* negative value",
    ),
    "weights all zero": (lambda: POL.weighted_fit(S, TH, W * 0), "not all zero"),
    "weights meta": (lambda: POL.weighted_fit(S, TH, W.to("meta")), "weights is a meta"),
    "theta meta": (lambda: POL.weighted_fit(S, TH.to("meta"), W), "theta is a meta"),
    "generator int": (lambda: POL.sample(S, 3), "generator must be a torch.Generator"),
    "weights inf": (
        lambda: POL.weighted_fit(S, TH, W.index_fill(0, torch.tensor([1]), INF)),
        r"weights contains 3 non-finite value\(s\) \(first at index \(1, 0\): inf\)",
    ),
    "load a meta entry": (
        lambda: POL.load_state_dict(
            {**POL.state_dict(), "options.0.chol": torch.eye(2, device="meta")}
        ),
        "'options.0.chol' is a meta tensor",
    ),
}


@pytest.mark.parametrize("name", list(FIT_PROBES))
def test_hierarchical_probes_change_nothing(name):
    call, match = FIT_PROBES[name]
    expect_unchanged(POL, call, match)


def test_weights_on_a_pruned_option_are_refused():
    pol, s, th, w = fitted_policy()
    pol.gating.active[1] = False
    expect_unchanged(
        pol, lambda: pol.weighted_fit(s, th, w), r"weights put mass on pruned option\(s\) \[1\]"
    )
    w[:, 1] = 0.0
    pol.weighted_fit(s, th, w)  # zero on the pruned column: fine


def test_weights_of_any_scale_give_the_same_fit():
    ref, s, th, w = fitted_policy()
    ref.weighted_fit(s, th, w)
    for scale in (1e-300, 1e300):
        pol, *_ = fitted_policy()
        pol.weighted_fit(s, th, w * scale)
        for key, value in ref.state_dict().items():
            assert torch.allclose(pol.state_dict()[key], value, rtol=1e-9, atol=1e-12), key
    pol, *_ = fitted_policy()
    pol.weighted_fit(s, th, w * 1e-320)  # denormal weights raised "the weighted fit overflows"
    for opt, ref_opt in zip(pol.sub_policies, ref.sub_policies, strict=True):
        assert torch.allclose(opt.bias, ref_opt.bias, rtol=1e-2, atol=1e-2)


GATING = SoftmaxGating(2, 3)
_x = torch.randn(20, 2, generator=_g, dtype=f64)
_t = torch.softmax(torch.randn(20, 3, generator=_g, dtype=f64), -1)
_w = torch.rand(20, generator=_g, dtype=f64)
GATING.weighted_fit(_x, _t, _w)
LG = LinearGaussian(2, 2, init_std=0.5)
_y = torch.randn(20, 2, generator=_g, dtype=f64)
LG.weighted_fit(_x, _y, _w)

MODULE_PROBES = {
    "gating targets all zero (silently shrank the gating)": (
        GATING,
        lambda: GATING.weighted_fit(_x, _t * 0, _w),
        "targets must be distributions over the active options.*row 0 sums to 0",
    ),
    "gating targets summing to 5": (
        GATING,
        lambda: GATING.weighted_fit(_x, _t * 5, _w),
        "row 0 sums to 5",
    ),
    "gating NaN sample weights name the index": (
        GATING,
        lambda: GATING.weighted_fit(_x, _t, _w.index_fill(0, torch.tensor([7]), NAN)),
        r"sample_weights contains 1 non-finite value\(s\) \(first at index \(7,\): nan\)",
    ),
    "gating negative target names it": (
        GATING,
        lambda: GATING.weighted_fit(_x, _t.index_fill(0, torch.tensor([2]), -1.0), _w),
        r"targets must be finite and non-negative, got -1.0 at \[2, 0\]",
    ),
    "constant gating targets summing to 2": (
        ConstantGating(torch.tensor([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])),
        None,
        "row 0 sums to 2",
    ),
    "linear-Gaussian meta targets": (
        LG,
        lambda: LG.weighted_fit(_x, _y.to("meta"), _w),
        "targets is a meta",
    ),
    "linear-Gaussian meta weights": (
        LG,
        lambda: LG.weighted_fit(_x, _y, _w.to("meta")),
        "weights is a meta",
    ),
    "linear-Gaussian meta checkpoint": (
        LG,
        lambda: LG.load_state_dict({**LG.state_dict(), "weight": torch.zeros(2, 2, device="meta")}),
        "'weight' is a meta tensor",
    ),
}


@pytest.mark.parametrize("name", list(MODULE_PROBES))
def test_module_probes_change_nothing(name):
    module, call, match = MODULE_PROBES[name]
    if call is None:
        call = lambda: module.weighted_fit(_x, _t * 2, _w)  # noqa: E731
    expect_unchanged(module, call, match)


# ---- algorithms -----------------------------------------------------------------------------
START = torch.linspace(-2, 2, 21, dtype=f64)[:, None]


def make_ih(**kw):
    args = dict(value_features=QuadraticFeatures(1), initial_states=START, gamma=0.9, seed=0)
    return InfiniteHorizonHiREPS.create(1, 1, **(args | kw))


@pytest.mark.parametrize(
    "value, error, match",
    [
        (10**400, ValueError, "epsilon is beyond float64's range, got 1000"),
        (-(10**400), ValueError, "epsilon is beyond float64's range, got -1000"),
        (np.bool_(True), TypeError, "epsilon must be a number, got the bool"),
        (np.complex128(1), TypeError, "epsilon must be a real number, got a complex"),
        (np.array(1 + 0j), TypeError, "epsilon must be a real number, got a complex ndarray"),
        (torch.tensor(0.5, device="meta"), ValueError, "epsilon is a meta tensor"),
    ],
    ids=[
        "int past float64",
        "-int past float64",
        "numpy bool",
        "numpy complex",
        "complex array",
        "meta tensor",
    ],
)
def test_odd_scalars_are_named_where_a_number_enters(value, error, match):
    """They were: an OverflowError without the option's name, numpy's bool and complex taken as
    1.0 (with a ComplexWarning), and an error from torch for the meta tensor."""
    with pytest.raises(error, match=match):
        EpisodicHiREPS.create(2, epsilon=value)
    with pytest.raises(error, match=match.replace("epsilon", "gamma")):
        make_ih(gamma=value)


ALGO_CREATE_PROBES = {
    "seed beyond torch's range": (
        lambda: EpisodicHiREPS.create(2, seed=2**70),
        r"seed must be an integer in \[-2\*\*63, ",
    ),
    "seeds that are one seed to torch": (
        lambda: EpisodicHiREPS.create(2, seed=[-3, 2**64 - 3]),
        r"seeds -3 and 18446744073709551613 .* are one seed to torch \(equal modulo 2\*\*64\)",
    ),
    "context_features string": (
        lambda: EpisodicHiREPS(
            HierarchicalPolicy.create(2, 1, 2), context_dim=1, context_features="quad"
        ),
        "context_features must be a feature map",
    ),
    "time-indexed value_features string": (
        lambda: TimeIndexedHiREPS.create(2, 1, 1, value_features="quad"),
        "value_features must be a feature map",
    ),
    "time-indexed policies not a sequence": (
        lambda: TimeIndexedHiREPS(HierarchicalPolicy.create(2, 1, 1), QuadraticFeatures(1)),
        "policies must be a sequence of K HierarchicalPolicy",
    ),
    "time-indexed epsilon string": (
        lambda: TimeIndexedHiREPS.create(3, 1, 1, epsilon="0.5"),
        "epsilon must be a float or 3 floats, got str '0.5'",
    ),
    "time-indexed epsilon dict": (
        lambda: TimeIndexedHiREPS.create(2, 1, 1, epsilon={0: 0.5, 1: 0.5}),
        "epsilon must be a float or 2 floats, got dict",
    ),
    "infinite-horizon value_features string": (
        lambda: make_ih(value_features="quad"),
        "value_features must be a feature map",
    ),
    "infinite-horizon value_features None": (
        lambda: InfiniteHorizonHiREPS(HierarchicalPolicy.create(2, 1, 1), None, START, gamma=0.9),
        "value_features must be a feature map",
    ),
}


@pytest.mark.parametrize("name", list(ALGO_CREATE_PROBES))
def test_algorithm_construction_probes(name):
    call, match = ALGO_CREATE_PROBES[name]
    expect(call, match)


IH = make_ih(n_options=3)
_s = torch.randn(20, 1, generator=_g, dtype=f64)
_a = IH.sample(_s)
_r = -(_s[:, 0] ** 2)

IH_PROBES = {
    "terminated string": (
        lambda: IH.update(_s, _a, _r, _s + 0.1, "no"),
        r"terminated must be a bool tensor of shape \(20,\), got str 'no'",
    ),
    "terminated meta": (
        lambda: IH.update(_s, _a, _r, _s + 0.1, torch.zeros(20, dtype=torch.bool, device="meta")),
        "terminated is on device meta but the other inputs are on cpu",
    ),
    "terminated ints": (
        lambda: IH.update(_s, _a, _r, _s + 0.1, torch.zeros(20, dtype=torch.int64)),
        r"terminated must be a bool tensor of shape \(20,\), got torch.int64",
    ),
    "learn with float terminated": (
        lambda: IH.learn(
            Experience(_s[:, None], _a[:, None], _r[:, None], _s[:, None], torch.zeros(20, 1))
        ),
        r"terminated must be a bool tensor of shape \(20,\), got torch.float32",
    ),
    "value of meta states": (
        lambda: IH.value(torch.zeros(3, 1, device="meta")),
        "states is on device meta",
    ),
    "update with complex actions": (
        lambda: IH.update(_s, _a.to(torch.complex128), _r, _s + 0.1),
        "actions must hold real numbers",
    ),
    "load a gamma string": (
        lambda: IH.load_state_dict({**IH.state_dict(), "gamma": "0.9"}),
        "gamma must be a number, got str",
    ),
}


@pytest.mark.parametrize("name", list(IH_PROBES))
def test_infinite_horizon_probes_change_nothing(name):
    call, match = IH_PROBES[name]
    expect_unchanged(IH, call, match)


def test_episodic_tell_with_bad_input_changes_nothing():
    algo = EpisodicHiREPS.create(2, n_options=3, seed=0)
    th = algo.ask(10)
    R10 = -(th**2).sum(1)
    for call, match in [
        (lambda: algo.tell(None, th.to("meta"), R10), "params is on device meta"),
        (lambda: algo.tell(None, th, "x"), "returns must be a tensor of numbers, got str 'x'"),
        (lambda: algo.ask(torch.tensor(2.5)), "the number of samples must be an integer"),
        (lambda: algo.sample(torch.zeros(3, 0), step=0.0), "step must be an integer"),
    ]:
        expect_unchanged(algo, call, match)


# ---- environments ---------------------------------------------------------------------------
STATE = torch.zeros(3, 2, dtype=f64)
BSTATE = torch.zeros(3, 3, dtype=f64)

ENV_FUNCTION_PROBES = {
    "PendulumParams gravity NaN": (lambda: PendulumParams(gravity=NAN), "gravity must be finite"),
    "PendulumParams gravity inf": (lambda: PendulumParams(gravity=INF), "gravity must be finite"),
    "PendulumParams gravity string": (
        lambda: PendulumParams(gravity="9.8"),
        "gravity must be a number",
    ),
    "PendulumParams restart string": (
        lambda: PendulumParams(restart_probability="0.1"),
        "restart_probability must be a number",
    ),
    "BeamParams start_position string": (
        lambda: BeamParams(start_position="0.1"),
        "start_position must be a number",
    ),
    "BeamParams goal off the beam": (
        lambda: BeamParams(goal=1.0),
        r"goal must be in \[0, half_length = 0.5\), got 1.0",
    ),
    "BeamParams endless episode": (
        lambda: BeamParams(episode_seconds=1e300),
        "episode_seconds / decision_seconds = .* steps is more than",
    ),
    "BeamParams endless decision": (
        lambda: BeamParams(dt=1e-300, decision_seconds=0.5),
        "decision_seconds / dt = .* steps is more than",
    ),
    "pendulum_step complex action": (
        lambda: pendulum_step(STATE, torch.zeros(3, dtype=torch.complex64), PendulumParams()),
        "action must hold real numbers",
    ),
    "pendulum_step string action": (
        lambda: pendulum_step(STATE, "a", PendulumParams()),
        "action must be a tensor of numbers, got str 'a'",
    ),
    "pendulum_step params None": (
        lambda: pendulum_step(STATE, torch.zeros(3), None),
        "params must be a PendulumParams, got NoneType",
    ),
    "pendulum_step complex state": (
        lambda: pendulum_step(STATE.to(torch.complex128), torch.zeros(3), PendulumParams()),
        "state must hold real numbers",
    ),
    "beam_step params of the pendulum": (
        lambda: beam_step(BSTATE, torch.zeros(3), PendulumParams()),
        "params must be a BeamParams, got PendulumParams",
    ),
    "pendulum sample_start generator int": (
        lambda: sample_start(3, PendulumParams(), 5),
        "generator must be a torch.Generator or None, got int 5",
    ),
    "beam sample_start generator int": (
        lambda: beam_start(torch.ones(2), BeamParams(), 5),
        "generator must be a torch.Generator",
    ),
    "evaluate_swing_up hold longer than the rollout": (
        lambda: evaluate_swing_up(lambda s: s[:, 0], seconds=1.0, hold_seconds=2.0),
        r"hold_seconds must be <= seconds = 1.0, got 2.0",
    ),
    "evaluate_beam hold longer than the episode": (
        lambda: evaluate_beam(lambda s: s[:, 0], hold_seconds=30.0),
        r"hold_seconds must be <= episode_seconds = 20.0, got 30.0",
    ),
    "TwoGaussians modes of width 3": (
        lambda: TwoGaussians(modes=torch.zeros(2, 3)),
        r"modes must have shape \(M, 2\) with M >= 1, got \(2, 3\)",
    ),
    "TwoGaussians heights of another M": (
        lambda: TwoGaussians(heights=torch.zeros(3)),
        r"heights must have shape \(2,\), got \(3,\)",
    ),
    "TwoGaussians NaN modes": (
        lambda: TwoGaussians(modes=torch.full((2, 2), NAN)),
        "modes contains non-finite",
    ),
    "ContextualTwoGaussians slope": (
        lambda: ContextualTwoGaussians(slope=torch.zeros(3)),
        r"slope must have shape \(2,\), got \(3,\)",
    ),
    "ContextualTwoGaussians context_low string": (
        lambda: ContextualTwoGaussians(context_low="a"),
        "context_low must be a number",
    ),
    "ContextualTwoGaussians complex context": (
        lambda: ContextualTwoGaussians()(
            torch.zeros(4, 1, dtype=torch.complex64), torch.zeros(4, 2)
        ),
        "context must hold real numbers",
    ),
    "ContextualTwoGaussians string context": (
        lambda: ContextualTwoGaussians()("a", torch.zeros(4, 2)),
        "context must be a tensor of numbers",
    ),
    "pendulum batch env seed 2**64": (
        lambda: PendulumSwingUpBatchEnv(2, seed=2**64),
        r"seed must be an integer in \[-2\*\*63, 18446744073709551615\]",
    ),
    "beam batch env seed below -2**63": (
        lambda: BallOnBeamBatchEnv(2, seed=-(2**63) - 1),
        "seed must be >= -9223372036854775808",
    ),
    "evaluate_swing_up seed 2**64": (
        lambda: evaluate_swing_up(lambda s: s[:, 0], seed=2**64),
        "seed must be an integer in",
    ),
    "sample_contexts generator int": (
        lambda: ContextualTwoGaussians().sample_contexts(3, generator=1),
        "generator must be a torch.Generator",
    ),
}


@pytest.mark.parametrize("name", list(ENV_FUNCTION_PROBES))
def test_environment_function_probes(name):
    call, match = ENV_FUNCTION_PROBES[name]
    expect(call, match)


def test_physics_take_numpy_and_integer_states():
    a = torch.zeros(3)
    ref = pendulum_step(STATE, a, PendulumParams())[0]
    assert torch.equal(pendulum_step(STATE.numpy(), a, PendulumParams())[0], ref)
    assert torch.equal(pendulum_step(STATE.long(), a.numpy(), PendulumParams())[0], ref)


@pytest.mark.parametrize("big", [2**63, [2**70, 1], np.uint64(2**63 + 5)])
def test_integers_past_int64_are_numbers(big):
    from hireps_torch.checks import as_finite_f64, as_float_tensor

    want = torch.as_tensor(big, dtype=torch.float64)
    assert torch.equal(as_float_tensor("x", big), want)
    assert torch.equal(as_finite_f64("x", big), want)


GYM_ENVS = {"pendulum": PendulumSwingUpEnv, "beam": BallOnBeamEnv}


@pytest.mark.parametrize("kind", list(GYM_ENVS))
@pytest.mark.parametrize(
    "call, match, error",
    [
        (lambda e: e.step("0.1"), "action must be a tensor of numbers, got str '0.1'", BAD),
        (lambda e: e.step(np.array([0.1j])), "action must hold real numbers", BAD),
        (lambda e: e.step(None), "action must be a tensor of numbers, got NoneType", BAD),
        (lambda e: e.reset(seed="1"), "seed must be an integer, got str '1'", BAD),
        (lambda e: e.reset(seed=1.5), "seed must be an integer, got float 1.5", BAD),
        (lambda e: e.reset(seed=-1), "seed must be >= 0, got -1", BAD),
    ],
)
def test_gym_env_probes(kind, call, match, error):
    env = GYM_ENVS[kind]()
    env.reset(seed=0)
    before = env.task.state.clone()
    expect(lambda: call(env), match, error)
    assert torch.equal(env.task.state, before)


@pytest.mark.parametrize("kind", list(GYM_ENVS))
def test_gym_env_step_before_reset_is_refused(kind):
    env = GYM_ENVS[kind]()
    with pytest.raises(gym.error.ResetNeeded, match="call reset"):
        env.step(np.zeros(1, np.float32))
    with pytest.raises(RuntimeError, match="call reset"):  # also a RuntimeError
        env.step(np.zeros(1, np.float32))
    env.reset(seed=np.int64(3))  # numpy seeds are fine
    env.step(np.zeros(1, np.float32))


@pytest.mark.parametrize("env_id", [envs.PENDULUM_ID, envs.BALL_ON_BEAM_ID])
def test_gym_make_with_params_of_the_wrong_type(env_id):
    expect(lambda: gym.make(env_id, params="x"), "params must be a")


BATCH_ENVS = {"pendulum": PendulumSwingUpBatchEnv, "beam": BallOnBeamBatchEnv}


@pytest.mark.parametrize("kind", list(BATCH_ENVS))
@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(params="x"), "params must be a"),
        (dict(device="nonsense"), "device must be a torch device or its name, got 'nonsense'"),
        (dict(batch_size="3"), "batch_size must be an integer, got str '3'"),
    ],
)
def test_batch_env_construction_probes(kind, kwargs, match):
    expect(lambda: BATCH_ENVS[kind](**kwargs), match)


@pytest.mark.parametrize("kind", list(BATCH_ENVS))
def test_batch_env_step_before_reset_and_without_action(kind):
    env = BATCH_ENVS[kind](3)
    td = TensorDict({"action": torch.zeros(3, 1)}, batch_size=[3])
    with pytest.raises(gym.error.ResetNeeded, match="call reset"):
        env.step(td)
    out = env.reset()
    expect(lambda: env.step(out.clone()), "the tensordict holds no 'action' entry")
    assert env.step(out.set("action", torch.zeros(3, 1)))["next", "state"].shape == (
        3,
        3 if kind == "beam" else 2,
    )


def test_hockey_probes():
    pytest.importorskip("pybullet")
    from hireps_torch.envs.hockey import HockeyParams, RobotHockeyEnv, RobotHockeyEpisodicEnv
    from hireps_torch.envs.hockey.kinematics import ArmGeometry

    for call, match in [
        (lambda: HockeyParams(puck_radius="1"), "HockeyParams.puck_radius must be a number"),
        (lambda: HockeyParams(target_mean="ab"), "HockeyParams.target_mean must be a sequence"),
        (lambda: HockeyParams(zones=("a",) * 4), r"HockeyParams.zones\[0\] must be a number"),
        (lambda: HockeyParams(geometry="x"), "HockeyParams.geometry must be an ArmGeometry"),
        (lambda: ArmGeometry(stick_length=-1.0), "ArmGeometry.stick_length must be finite"),
        (lambda: ArmGeometry(blade_size=(0.1, 0.1)), "ArmGeometry.blade_size must be 3"),
        (lambda: ArmGeometry(blade_size=(0.1, NAN, 0.1)), "ArmGeometry.blade_size must be fin"),
        (lambda: ArmGeometry(demo_points=1), "ArmGeometry.demo_points must be >= 2"),
        (lambda: RobotHockeyEnv(params="x"), "params must be a HockeyParams"),
    ]:
        expect(call, match)
    env = RobotHockeyEnv()
    try:
        with pytest.raises(gym.error.ResetNeeded):
            env.step(env.demo_action())
        expect(lambda: env.reset(seed="1"), "seed must be an integer")
        env.reset(seed=0)
        expect(lambda: env.step("abc"), "action must be a tensor of numbers, got str 'abc'")
        expect(lambda: env.step(env.demo_action() * 1j), "action must hold real numbers")
        assert env.shot_index == 0  # nothing was played
    finally:
        env.close()
    episodic = RobotHockeyEpisodicEnv()
    try:
        with pytest.raises(gym.error.ResetNeeded):
            episodic.step(np.zeros(42))
    finally:
        episodic.close()


# ---- TorchRL glue ---------------------------------------------------------------------------
ROLLOUT_PROBES = {
    "policy_module of a non-policy": (
        lambda: policy_module(LinearGaussian(1, 1)),
        "policy 0 must be a HierarchicalPolicy, got LinearGaussian",
    ),
    "time_indexed_module of strings": (
        lambda: time_indexed_module(["a"]),
        "policy 0 must be a HierarchicalPolicy, got str",
    ),
    "collector seed float": (
        lambda: make_collector(
            lambda: PendulumSwingUpBatchEnv(2),
            policy_module(HierarchicalPolicy.create(1, 2, 1)),
            frames_per_batch=4,
            seed=1.5,
        ),
        "seed must be an integer, got float 1.5",
    ),
    "collector total_frames 0": (
        lambda: make_collector(
            lambda: PendulumSwingUpBatchEnv(2),
            policy_module(HierarchicalPolicy.create(1, 2, 1)),
            frames_per_batch=4,
            total_frames=0,
        ),
        "total_frames must be -1",
    ),
    "collector env not callable": (
        lambda: make_collector(
            "hireps/PendulumSwingUp-v0",
            policy_module(HierarchicalPolicy.create(1, 2, 1)),
            frames_per_batch=4,
        ),
        "create_env_fn must be a callable",
    ),
}


@pytest.mark.parametrize("name", list(ROLLOUT_PROBES))
def test_rollout_probes(name):
    call, match = ROLLOUT_PROBES[name]
    expect(call, match)


# ---- experiments in process -----------------------------------------------------------------
from hireps_torch.experiments.ball_on_beam import BallOnBeamConfig  # noqa: E402
from hireps_torch.experiments.ball_on_beam import run as beam_run  # noqa: E402
from hireps_torch.experiments.bimodal import BimodalConfig  # noqa: E402
from hireps_torch.experiments.bimodal import run as bimodal_run  # noqa: E402
from hireps_torch.experiments.checkpoint import RunFinished  # noqa: E402
from hireps_torch.experiments.hockey import HockeyEpisodicConfig  # noqa: E402
from hireps_torch.experiments.hockey import run as hockey_run  # noqa: E402
from hireps_torch.experiments.pendulum import PendulumConfig  # noqa: E402
from hireps_torch.experiments.pendulum import run as pendulum_run  # noqa: E402

SMALL = {
    "bimodal": (BimodalConfig, bimodal_run, dict(episodes=400)),
    "pendulum": (PendulumConfig, pendulum_run, dict(episodes=20, episodes_per_iteration=10)),
    "beam": (BallOnBeamConfig, beam_run, dict(episodes=6, episodes_per_iteration=3)),
    "hockey": (HockeyEpisodicConfig, hockey_run, dict(episodes=4, episodes_per_iteration=2)),
}
OPTION_PROBES = [
    (
        "bimodal",
        dict(algorithm="foo"),
        r"algorithm \(--algorithm\) must be one of 'hireps', 'hireps-unbounded', "
        r"'hireps-versatile', 'reps', 'cmaes'",
    ),
    ("bimodal", dict(algorithm=1), "algorithm .* must be one of"),
    ("bimodal", dict(contextual="yes"), r"contextual \(--contextual\) must be True or False"),
    ("bimodal", dict(checkpoint_every=1.5), "checkpoint_every .* must be an integer, got 1.5"),
    ("bimodal", dict(checkpoint_every=True), "checkpoint_every .* must be an integer, got True"),
    ("bimodal", dict(checkpoint_every=NAN), "checkpoint_every .* must be an integer, got nan"),
    ("bimodal", dict(checkpoint_every="2"), "checkpoint_every .* must be an integer, got '2'"),
    ("bimodal", dict(seed="1"), "seed .* must be an integer, got '1'"),
    ("bimodal", dict(samples_per_iteration=2.5), "samples_per_iteration .* must be an integer"),
    ("bimodal", dict(samples_per_iteration="200"), "samples_per_iteration .* must be an integer"),
    ("bimodal", dict(episodes=NAN), r"episodes \(--episodes\) must be an integer, got nan"),
    ("bimodal", dict(episodes=INF), "episodes .* must be an integer, got inf"),
    ("bimodal", dict(episodes=400.5), "episodes .* must be an integer, got 400.5"),
    ("bimodal", dict(init_std="2"), r"init_std \(--init-std\) must be a number, got '2'"),
    ("bimodal", dict(epsilon=True), "epsilon .* must be a number, got True"),
    ("bimodal", dict(logger=3), "logger .* must be one of 'csv', 'tensorboard', 'wandb'"),
    ("bimodal", dict(progress="no"), "progress .* must be True or False"),
    ("bimodal", dict(run_dir=3), r"run_dir \(--run-dir\) must be a path, got 3"),
    ("pendulum", dict(gating="foo"), "gating .* must be one of 'learned', 'constant', 'flat'"),
    ("pendulum", dict(init_means="foo"), "init_means .* must be one of"),
    ("pendulum", dict(value_features="foo"), "value_features .* must be one of"),
    ("pendulum", dict(mirror_samples="x"), "mirror_samples .* must be True or False"),
    ("pendulum", dict(reset_each_iteration=1), "reset_each_iteration .* must be True or False"),
    ("pendulum", dict(episodes_per_iteration=3.5), "episodes_per_iteration .* must be an integer"),
    ("pendulum", dict(workers=1.5), "workers .* must be an integer, got 1.5"),
    (
        "pendulum",
        dict(fourier_bases=1),
        r"fourier_bases \(--fourier-bases\) must be an integer in 2",
    ),
    ("pendulum", dict(fourier_bases=10**6), "fourier_bases .* in 2..1000 .*got 1000000"),
    (
        "pendulum",
        dict(episode_seconds=1e300),
        "episode_seconds .* must be at most 1e\\+06 decisions",
    ),
    ("beam", dict(fourier_bases=1001), r"fourier_bases .* in 2..1000 \(2-D states\).*got 1001"),
    (
        "beam",
        dict(fourier_bases=1000, value_beam_angle=True),
        r"fourier_bases .* in 2..100 \(3-D states\).*got 1000",
    ),
    ("beam", dict(fourier_coupling=4), r"fourier_coupling \(--fourier-coupling\) must be in 1..3"),
    ("beam", dict(eval_episodes=1.5), "eval_episodes .* must be an integer, got 1.5"),
    ("hockey", dict(exploration_floor="x"), "exploration_floor .* must be a number, got 'x'"),
    ("hockey", dict(exploration_floor_end=1.0), r"exploration_floor_end must be in \[0, 1\)"),
    ("hockey", dict(exploration_floor_end=-0.1), r"exploration_floor_end .*got -0.1"),
    ("hockey", dict(exploration_floor_end="x"), "exploration_floor_end .*'x'"),
    ("hockey", dict(kappa_rel="0.9"), "kappa_rel .* must be a number"),
    ("hockey", dict(workers=1.5), "workers .* must be an integer, got 1.5"),
    ("hockey", dict(covariance_prior=True), "covariance_prior .* must be a number, got True"),
    ("hockey", dict(n_options=2.0), "n_options .* must be an integer, got 2.0"),
    ("pendulum", dict(kp="60"), r"kp \(--kp\) must be a number, got '60'"),
    ("pendulum", dict(steps_per_decision=NAN), "steps_per_decision .* must be an integer"),
    ("pendulum", dict(epsilon_end=0.0), r"epsilon_end \(--epsilon-end\) must be finite and > 0"),
    ("pendulum", dict(epsilon_end=math.inf), r"epsilon_end .* must be finite and > 0, got inf"),
    ("pendulum", dict(epsilon=-0.5), r"epsilon \(--epsilon\) must be finite and > 0, got -0.5"),
    ("beam", dict(kappa_rel="x"), "kappa_rel .* must be a number, got 'x'"),
    ("beam", dict(fourier_coupling=1.5), "fourier_coupling .* must be an integer"),
    ("bimodal", dict(min_variance="0"), "min_variance .* must be a number"),
    ("bimodal", dict(n_options=NAN), "n_options .* must be an integer, got nan"),
]


@pytest.mark.parametrize(
    "name, kwargs, match",
    OPTION_PROBES,
    ids=[f"{n}-{list(k)[0]}={k[list(k)[0]]!r}" for n, k, _ in OPTION_PROBES],
)
def test_bad_options_are_named_and_nothing_is_written(tmp_path, monkeypatch, name, kwargs, match):
    monkeypatch.chdir(tmp_path)
    cls, run, small = SMALL[name]
    run_dir = tmp_path / "run"
    args = dict(run_dir=run_dir, progress=False) | small | kwargs
    expect(lambda: run(cls(**args)), match)
    assert not run_dir.exists() and not (tmp_path / "runs").exists()


def test_run_dirs_in_the_way_are_named_before_anything_is_built(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("mine")
    for run_dir, error, match in [
        (afile, FileExistsError, "run directory .*afile already exists and is a file"),
        (afile / "sub", ValueError, r"--run-dir .*sub: .*afile is a file, not a directory"),
    ]:
        expect(
            lambda d=run_dir: bimodal_run(BimodalConfig(run_dir=d, progress=False)), match, error
        )
    assert afile.read_text() == "mine" and sorted(os.listdir(tmp_path)) == ["afile"]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("finished") / "good"
    bimodal_run(BimodalConfig(run_dir=run_dir, progress=False, episodes=400))
    return run_dir


def files_of(path):
    return {p.name: p.read_bytes() for p in sorted(path.iterdir()) if p.is_file()}


def unfinished_copy(finished_run, tmp_path, name="run"):
    import shutil

    d = tmp_path / name
    shutil.copytree(finished_run, d)
    (d / "summary.json").unlink()
    return d


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d: (d / "config.json").write_text("{nope"), r"config.json cannot be read as JSON"),
        (lambda d: (d / "config.json").write_text("[1, 2]"), "holds a JSON list, not the options"),
        (lambda d: torch.save([1, 2], d / "checkpoint.pt"), "holds a list, not a checkpoint"),
        (
            lambda d: torch.save({"format": FORMAT}, d / "checkpoint.pt"),
            "not a complete checkpoint",
        ),
        (lambda d: torch.save({"format": 1}, d / "checkpoint.pt"), "another version of this code"),
        (
            lambda d: torch.save(
                {
                    **torch.load(d / "checkpoint.pt"),
                    "rng": {"torch": torch.zeros(3, dtype=torch.uint8)},
                },
                d / "checkpoint.pt",
            ),
            "no state for the generators|'torch' generator state",
        ),
    ],
)
def test_resume_of_a_damaged_run_is_named_and_changes_no_file(
    finished_run, tmp_path, change, match
):
    d = unfinished_copy(finished_run, tmp_path)
    change(d)
    before = files_of(d)
    expect(lambda: bimodal_run(BimodalConfig(resume=d, progress=False, episodes=400)), match)
    assert files_of(d) == before


def test_resume_of_another_experiment_names_it(finished_run, tmp_path):
    d = unfinished_copy(finished_run, tmp_path)
    before = files_of(d)
    cfg = PendulumConfig(resume=d, progress=False, episodes=20, episodes_per_iteration=10)
    expect(lambda: pendulum_run(cfg), "it is a 'bimodal' run, not 'pendulum'")
    assert files_of(d) == before
    with pytest.raises(RunFinished):  # a finished run says so
        bimodal_run(BimodalConfig(resume=finished_run, progress=False, episodes=400))


# ---- train.py as a subprocess (few: ~3 s each) ----------------------------------------------
def train(*args, cwd):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args, "--no-progress"],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_train_run_dir_under_a_file_exits_2_without_a_traceback(tmp_path):
    (tmp_path / "afile").write_text("mine")
    out = train("bimodal", "--run-dir", "afile/run", cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    assert "afile is a file, not a directory" in out.stderr and "Traceback" not in out.stderr
    assert sorted(os.listdir(tmp_path)) == ["afile"]


@pytest.mark.slow
def test_train_resumes_a_moved_run_directory_in_place(finished_run, tmp_path):
    """config.json names the directory the run started in; a copy is resumed where it is
    (it was refused: '--resume and --run-dir name different directories')."""
    d = unfinished_copy(finished_run, tmp_path, "moved")
    changed = train("bimodal", "--resume", "moved", "--epsilon", "0.3", cwd=tmp_path)
    assert changed.returncode == 2 and "epsilon (run: 1.0, now: 0.3)" in changed.stderr
    out = train("bimodal", "--resume", "moved", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    summary = json.loads((d / "summary.json").read_text())
    expected = json.loads((finished_run / "summary.json").read_text())
    assert {k: v for k, v in summary.items() if k != "wall_seconds"} == {
        k: v for k, v in expected.items() if k != "wall_seconds"
    }


def test_a_sixth_probes_errors_name_the_value_as_the_user_gave_it(tmp_path):
    """Errors at the entry points speak of what the user passed: the argument's own name, a
    broadcast number as one number, the user's indices, the actor's observation."""
    from hireps_torch import HierarchicalPolicy, load_run, solve_episodic_dual
    from hireps_torch.checks import check_positive
    from hireps_torch.rollout import policy_module

    with pytest.raises(ValueError, match="param_dim must be >= 1, got 0"):
        EpisodicHiREPS.create(param_dim=0)
    with pytest.raises(ValueError, match=r"init_std must be finite and > 0, got -1.0$"):
        EpisodicHiREPS.create(param_dim=2, init_std=-1)
    with pytest.raises(ValueError, match=r"epsilon must be finite and > 0, got 0.0$"):
        solve_episodic_dual(torch.randn(10, dtype=torch.float64), epsilon=0)
    with pytest.raises(ValueError, match=r"x must be finite and > 0, got \[0.5, -1.0\]"):
        check_positive("x", torch.tensor([0.5, -1.0]))  # numbers that differ: all of them
    with pytest.raises(ValueError, match="without context, pass the number of samples N >= 1"):
        EpisodicHiREPS.create(param_dim=2, seed=[0, 1]).ask(None)
    bimodal_run(
        BimodalConfig(run_dir=tmp_path / "r", contextual=True, episodes=400, progress=False)
    )
    run = load_run(tmp_path / "r")  # a population of one inside: the user's (N, C) indices
    with pytest.raises(ValueError, match=r"first at index \[1, 0\]: nan"):
        run.mean_action(torch.tensor([[0.0], [math.nan]]))
    ti = TimeIndexedHiREPS.create(3, 2, 2)
    for swapped in (lambda: ti.ask(torch.zeros(4, 2), 0), lambda: ti.sample(0, torch.zeros(4, 2))):
        with pytest.raises(ValueError, match=r"got a Tensor of shape \(4, 2\) \(sample and mean"):
            swapped()
    pop = HierarchicalPolicy.stack([HierarchicalPolicy.create(3, 2, 1) for _ in range(2)])
    td = TensorDict({"observation": torch.zeros(4, 3)}, [4])
    with pytest.raises(
        ValueError, match=r"observation must have shape \(\.\.\., 2\) .* got \(4, 3\)"
    ):
        policy_module(pop)(td)
