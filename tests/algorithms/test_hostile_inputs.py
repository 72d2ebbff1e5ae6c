"""A user who misuses the algorithms gets a ValueError / TypeError naming the argument and the
bad value or shape, at construction or at the call, never an error from deep inside torch or a
silent NaN; and what is harmless (0-d tensors, integer tensors, telling twice) just works."""

import copy
import math

import numpy as np
import pytest
import torch

from hireps_torch.algorithms import (
    REPS,
    EpisodicHiREPS,
    InfiniteHorizonHiREPS,
    TimeIndexedHiREPS,
)
from hireps_torch.features import QuadraticFeatures

f64 = torch.float64
NAN, INF = math.nan, math.inf
START = torch.linspace(-2, 2, 41, dtype=f64)[:, None]


def make_ih(**kwargs):
    args = dict(value_features=QuadraticFeatures(1), initial_states=START, gamma=0.9, seed=0)
    return InfiniteHorizonHiREPS.create(1, 1, **(args | kwargs))


BASE = dict(n_options=3, seed=0)
CREATE = {
    "episodic": lambda **k: EpisodicHiREPS.create(2, **(BASE | k)),
    "time_indexed": lambda **k: TimeIndexedHiREPS.create(2, 1, 1, **(BASE | k)),
    "infinite_horizon": lambda **k: make_ih(**(BASE | k)),
}


@pytest.mark.parametrize("variant", list(CREATE))
@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(epsilon=torch.tensor([0.5, 0.5, 0.5])), ValueError, "epsilon"),
        (dict(epsilon=NAN), ValueError, "epsilon"),
        (dict(epsilon=True), TypeError, "epsilon must be a number, got the bool"),
        (dict(kappa_rel=torch.tensor([0.5, 0.5])), ValueError, "kappa_rel must be one number"),
        (dict(kappa_rel=-0.1), ValueError, "kappa_rel must be finite and >= 0"),
        (dict(seed=1.5), TypeError, "seed must be an integer, got float"),
        (dict(seed=np.arange(3)), TypeError, r"or a list of .* ndarray of shape \(3,\): pass"),
        (dict(seed=torch.tensor([3])), TypeError, r"list of integers .* Tensor of shape \(1,\)"),
        (dict(seed=[torch.tensor([3])]), TypeError, r"seed\[0\] must be an integer \(a 0-d"),
        (dict(n_options=torch.tensor([3])), TypeError, r"n_options .* tensor of shape \(1,\)"),
        (dict(seed=torch.tensor(3, device="meta")), TypeError, "got a meta tensor"),
        (dict(init_mean=torch.tensor([NAN])), ValueError, "init_mean contains"),
        (dict(init_std=INF), ValueError, "init_std must be finite and > 0"),
        (dict(spread=NAN), ValueError, "spread must be finite"),
        (dict(min_variance=-1.0), ValueError, "min_variance must be in"),
        (dict(covariance_prior=INF), ValueError, "covariance_prior must be finite"),
        (dict(n_options=0), ValueError, "n_options must be >= 1"),
    ],
)
def test_create_names_the_bad_argument(variant, kwargs, error, match):
    if variant == "episodic" and "init_mean" in kwargs:
        kwargs = dict(init_mean=torch.tensor([NAN, 0.0]))
    with pytest.raises(error, match=match):
        CREATE[variant](**kwargs)


def test_zero_d_tensors_are_numbers():
    algo = EpisodicHiREPS.create(
        2, epsilon=torch.tensor(0.5, dtype=f64), kappa_rel=torch.tensor(0.8)
    )
    assert algo.epsilon == 0.5 and algo.kappa_rel == pytest.approx(0.8)
    ti = TimeIndexedHiREPS.create(2, 1, 1, epsilon=torch.tensor([0.3, 0.4], dtype=f64))
    assert ti.epsilon == [0.3, 0.4]
    assert (
        TimeIndexedHiREPS.create(2, 1, 1, epsilon=torch.tensor(0.3, dtype=f64)).epsilon == [0.3] * 2
    )
    assert make_ih(gamma=torch.tensor(0.5, dtype=f64)).gamma == 0.5
    assert EpisodicHiREPS.create(2, n_options=torch.tensor(2)).policy.n_options == 2


def test_counts_and_thresholds_are_checked():
    pol = REPS.create(2).policy
    for kwargs, error, match in [
        (dict(prune_threshold=NAN), ValueError, r"prune_threshold must be in \[0, 1\)"),
        (dict(prune_threshold=1.0), ValueError, "prune_threshold"),
        (dict(context_dim=-1), ValueError, "context_dim must be >= 0"),
        (dict(context_dim=1), ValueError, "the policy takes contexts of dimension 0"),
    ]:
        with pytest.raises(error, match=match):
            EpisodicHiREPS(pol, **kwargs)
    for fixed in ("n_options", "kappa_rel"):  # REPS: one option, no entropy bound
        with pytest.raises(TypeError, match=f"unexpected keyword argument '{fixed}'"):
            REPS.create(2, **{fixed: 1})
    with pytest.raises(TypeError, match="policy must be a HierarchicalPolicy"):
        EpisodicHiREPS(pol.options[0])
    with pytest.raises(ValueError, match=r"K \(the number of decision steps\) must be >= 1"):
        TimeIndexedHiREPS.create(0, 1, 1)
    with pytest.raises(TypeError, match="param_dim must be an integer"):
        TimeIndexedHiREPS.create(2, 1.0 * 2, 1)
    with pytest.raises(ValueError, match="initial_states contains non-finite"):
        make_ih(initial_states=START.masked_fill(START > 1, NAN))
    with pytest.raises(ValueError, match=r"initial_states must have shape \(N, 1\), got \(41,\)"):
        make_ih(initial_states=START[:, 0])
    with pytest.raises(ValueError, match="state_dim must be >= 1"):
        InfiniteHorizonHiREPS.create(
            0, 1, value_features=QuadraticFeatures(0), initial_states=START, gamma=0.9
        )


def test_sample_counts_contexts_and_widths_are_named():
    free, ctx = EpisodicHiREPS.create(2, n_options=2), EpisodicHiREPS.create(2, context_dim=1)
    for call, error, match in [
        (lambda: free.ask(0), ValueError, "the number of samples must be >= 1, got 0"),
        (lambda: free.ask(-3), ValueError, "the number of samples must be >= 1, got -3"),
        (lambda: free.ask(2.0), TypeError, "the number of samples must be an integer"),
        (lambda: free.ask(True), TypeError, "the number of samples must be an integer"),
        (lambda: free.ask(torch.zeros(5, 2)), ValueError, "this algorithm has no context"),
        (lambda: free.act(torch.zeros(0, 0)), ValueError, "at least one context"),
        (lambda: ctx.act(torch.zeros(4, 2)), ValueError, r"contexts must have shape \(N, 1\)"),
        (lambda: ctx.ask(None), ValueError, r"contextual \(context_dim = 1\)"),
        (lambda: make_ih().value(torch.zeros(3, 2)), ValueError, r"\(N, 1\), got \(3, 2\)"),
        (lambda: make_ih().value(torch.zeros(0, 1)), ValueError, "at least one"),
        (
            lambda: TimeIndexedHiREPS.create(2, 1, 2).value(1, torch.zeros(3, 1)),
            ValueError,
            r"contexts must have shape \(N, 2\), got \(3, 1\)",
        ),
        (lambda: ctx.ask(torch.zeros(4, 1, device="meta")), ValueError, "device meta"),
    ]:
        with pytest.raises(error, match=match):
            call()
    assert free.ask(torch.tensor(3)).shape == (3, 2)  # a 0-d integer tensor is a count
    assert free.ask(torch.zeros(4, 0)).shape == (4, 2)
    assert ctx.ask(torch.zeros(4)).shape == (4, 2)  # S = 1: a flat batch of contexts


def test_integer_and_bool_tensors_are_used_as_floats():
    # the same update as with the float64 values: same diagnostics, same policy
    gen = torch.Generator().manual_seed(0)
    algo, twin = (EpisodicHiREPS.create(2, context_dim=1, n_options=2, seed=0) for _ in "ab")
    s = torch.randint(-2, 3, (30, 1), generator=gen)
    th = algo.ask(s).round().to(torch.int64)
    assert torch.equal(twin.ask(s.double()).round(), th.double())  # the same draws
    d = algo.tell(s, th, -(th**2).sum(1))  # int contexts, params and returns
    assert d["kl"] == pytest.approx(algo.epsilon, abs=1e-3) and d["refitted"]
    assert d == twin.tell(s.double(), th.double(), -(th.double() ** 2).sum(1))
    for key, value in algo.policy.state_dict().items():
        assert torch.equal(value, twin.policy.state_dict()[key]), key
    ti, ti_twin = (
        TimeIndexedHiREPS.create(1, 1, 1, n_options=1, kappa_rel=None, seed=0) for _ in "ab"
    )
    states = torch.randint(0, 2, (20, 1, 1), generator=gen).bool()
    theta = ti.ask(0, states[:, 0]).round().int()[:, None]
    d = ti.tell(states, theta, torch.arange(20)[:, None])
    d_twin = ti_twin.tell(states.double(), theta.double(), torch.arange(20.0)[:, None])
    assert ti.iteration == 1 and d["kl"] == d_twin["kl"]
    assert torch.equal(ti.value_weights, ti_twin.value_weights)
    for key, value in ti.policies[0].state_dict().items():
        assert torch.equal(value, ti_twin.policies[0].state_dict()[key]), key


def test_single_option_tell_twice_and_tell_before_ask():
    algo = EpisodicHiREPS.create(2, n_options=1, seed=0)  # one option, with the entropy bound
    th = torch.randn(20, 2, generator=torch.Generator().manual_seed(1), dtype=f64)
    R = -(th**2).sum(1)
    first = algo.tell(None, th, R)  # samples that ask never drew: any samples are data
    second = algo.tell(None, th, R)  # the same samples again: a second, valid update
    assert math.isnan(first["kappa"]) and first["n_active_options"] == 1
    assert second["iteration"] == 2 and math.isfinite(second["kl"])
    assert bool(torch.isfinite(algo.policy.options[0].chol).all())


def test_update_needs_at_least_two_samples_and_exact_shapes():
    algo = EpisodicHiREPS.create(2, n_options=2, seed=0)
    th = algo.ask(6)
    with pytest.raises(ValueError, match="at least 2 samples"):
        algo.tell(None, th[:1], torch.zeros(1))
    with pytest.raises(ValueError, match="the number of samples must be >= 1, got 0"):
        algo.tell(None, th[:0], torch.zeros(0))
    with pytest.raises(ValueError, match=r"returns must have shape \(6,\).*got \(6, 1\)"):
        algo.tell(None, th, torch.zeros(6, 1))
    ih = make_ih()
    s = torch.zeros(6, 1, dtype=f64)
    with pytest.raises(ValueError, match=r"rewards must have shape \(6,\).*got \(1, 6\)"):
        ih.update(s, s, torch.zeros(1, 6), s)


def test_a_population_names_its_own_shape_for_a_bad_terminated():
    algo = make_ih(seed=[0, 1])
    s = torch.zeros(2, 30, 1, dtype=f64)
    a, r = torch.zeros(2, 30, 1, dtype=f64), torch.zeros(2, 30, dtype=f64)
    for bad, error in [("yes", TypeError), (torch.zeros(2, 30), ValueError)]:
        with pytest.raises(error, match=r"terminated must be a bool tensor of shape \(2, 30\)"):
            algo.update(s, a, r, s, bad)


def test_sparse_inputs_are_named_and_change_nothing():
    algo = EpisodicHiREPS.create(2, context_dim=1, n_options=2, seed=0)
    c = torch.randn(20, 1, generator=torch.Generator().manual_seed(0), dtype=f64)
    theta, R = algo.ask(c), torch.linspace(0, 1, 20, dtype=f64)
    before = copy.deepcopy(algo.state_dict())
    for args, name in [
        ((c.to_sparse(), theta, R), "contexts"),
        ((c, theta, R.to_sparse()), "returns"),
    ]:
        with pytest.raises(TypeError, match=f"{name} must be a dense tensor, got a sparse_coo one"):
            algo.tell(*args)
    with pytest.raises(TypeError, match="contexts must be a dense tensor"):
        algo.ask(c.to_sparse_csr())
    assert same_tree(algo.state_dict(), before)


def same_tree(a, b):
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and torch.equal(a, b)
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same_tree(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(map(same_tree, a, b))
    return a == b
