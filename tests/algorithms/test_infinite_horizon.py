"""Infinite-horizon HiREPS on pendulum transitions: the update's constraints and bad input."""

import math

import pytest
import torch

from hireps_torch.algorithms import InfiniteHorizonHiREPS
from hireps_torch.dual import solve_infinite_horizon_dual
from hireps_torch.envs.pendulum import PendulumParams, pendulum_step, sample_start
from hireps_torch.features import FeatureMap, FourierFeatures, QuadraticFeatures
from hireps_torch.policies import HierarchicalPolicy


def make_algo(gen, n_options=3, kappa_rel=0.9):
    p = PendulumParams()
    pol = HierarchicalPolicy.create(
        n_options,
        2,
        1,
        init_std=torch.tensor([1.5], dtype=torch.float64),
        gating_features=QuadraticFeatures(2, scale=torch.tensor([math.pi, 20.0])),
        generator=gen,
    )
    feats = FourierFeatures([-math.pi, -20.0], [math.pi, 20.0], 4, periodic=[True, False])
    algo = InfiniteHorizonHiREPS(
        pol, feats, sample_start(500, p, gen), gamma=p.gamma, epsilon=0.5, kappa_rel=kappa_rel
    )
    return algo, p


def rollout(algo, p, gen, B=20, T=40):
    s = sample_start(B, p, gen)
    S, A, R, S2 = [], [], [], []
    for _ in range(T):
        a, _ = algo.policy.sample(s, gen)
        s2, r, _ = pendulum_step(s, a, p)
        S.append(s), A.append(a), R.append(r), S2.append(s2)
        s = s2
    return torch.cat(S), torch.cat(A), torch.cat(R), torch.cat(S2)


def test_update_meets_kl_entropy_and_stationarity(gen):
    algo, p = make_algo(gen)
    s, a, r, s2 = rollout(algo, p, gen)
    before = algo.policy.log_responsibilities(s, a)
    kappa = 0.9 * float(-(before.exp() * before).sum(-1).mean())
    phi, phi_next, phi0 = algo.value_features(s), algo.value_features(s2), algo.initial_features
    d = algo.update(s, a, r, s2)
    assert d["dual_converged"]
    assert d["kl"] == pytest.approx(0.5, abs=1e-3)
    assert d["cross_entropy"] <= kappa + 1e-3
    assert d["kappa"] == pytest.approx(kappa)
    assert d["feature_error"] < 1e-5
    assert 1 <= d["effective_sample_size"] <= s.shape[0]
    for key in ("eta", "xi", "option_entropy", "policy_entropy", "mean_reward"):
        assert math.isfinite(d[key]), key
    # the value estimate is the dual's v on the value features
    sol = solve_infinite_horizon_dual(
        r, phi, phi_next, phi0, gamma=p.gamma, epsilon=0.5, log_responsibilities=before,
        kappa=kappa,
    )  # fmt: skip
    assert torch.equal(algo.value_weights, sol.v)
    assert torch.allclose(algo.value(s[:3]), phi[:3] @ sol.v, rtol=1e-12, atol=0)


def test_terminated_transitions_lead_to_the_start_distribution(gen):
    # After a terminal transition the process restarts for sure: the next state's features are
    # phi_hat_0. Passing next states whose features are exactly phi_hat_0 must give the same
    # update as flagging them terminated.
    algo, p = make_algo(gen, n_options=1, kappa_rel=None)
    s, a, r, s2 = rollout(algo, p, gen, B=10, T=20)
    term = torch.zeros(s.shape[0], dtype=torch.bool)
    term[::7] = True
    state = algo.state_dict()
    d_flag = algo.update(s, a, r, s2, term)
    v_flag = algo.value_weights.clone()
    algo.load_state_dict(state)
    sentinel = torch.tensor([0.123, -4.56], dtype=torch.float64)

    class SentinelIsStart(FeatureMap):  # phi(sentinel) = phi_hat_0, else the Fourier features
        def __init__(self, inner, phi0):
            super().__init__()
            self.inner, self.phi0 = inner, phi0
            self.in_features, self.out_features = inner.in_features, inner.out_features

        def forward(self, x):
            return torch.where((x == sentinel).all(-1, keepdim=True), self.phi0, self.inner(x))

    algo.value_features = SentinelIsStart(algo.value_features, algo.initial_features)
    s2_alt = torch.where(term[:, None], sentinel, s2)
    d_alt = algo.update(s, a, r, s2_alt)
    assert torch.allclose(algo.value_weights, v_flag, atol=1e-8)
    assert d_flag["kl"] == pytest.approx(d_alt["kl"], abs=1e-9)
    assert d_flag["feature_error"] == pytest.approx(d_alt["feature_error"], abs=1e-9)
    with pytest.raises(ValueError, match="terminated"):
        algo.update(s, a, r, s2, term[:-1])


def assert_same_state(a, b):
    """Two state dicts are equal entry by entry (policy tensors, value weights, generator)."""
    assert a.keys() == b.keys()
    for key, value in a.items():
        if isinstance(value, dict):
            assert_same_state(value, b[key])
        elif isinstance(value, torch.Tensor):
            assert torch.equal(value, b[key]), key
        else:
            assert value == b[key], key


def test_update_is_deterministic_and_state_dict_round_trips():
    outs = []
    for _ in range(2):
        g = torch.Generator().manual_seed(5)
        algo, p = make_algo(g)
        algo.update(*rollout(algo, p, g))
        outs.append(algo.state_dict())
    a, b = outs
    assert_same_state(a, b)
    g = torch.Generator().manual_seed(6)
    fresh, _ = make_algo(g)
    assert not torch.equal(fresh.value_weights, a["value_weights"])  # the load has work to do
    fresh.load_state_dict(a)
    assert_same_state(fresh.state_dict(), a)


def test_bad_input_is_named(gen):
    algo, p = make_algo(gen)
    s, a, r, s2 = rollout(algo, p, gen, B=4, T=5)
    r_bad = r.clone()
    r_bad[2] = math.inf
    with pytest.raises(ValueError, match="rewards"):
        algo.update(s, a, r_bad, s2)
    with pytest.raises(ValueError, match="next_states"):
        algo.update(s, a, r, s2[:-1])
    with pytest.raises(ValueError, match="actions"):
        algo.update(s, a.repeat(1, 2), r, s2)
    with pytest.raises(ValueError, match="gamma"):
        make_algo(gen)[0].__class__(algo.policy, algo.value_features, s[:3], gamma=1.0)
