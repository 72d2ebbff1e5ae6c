"""The shared interface: one loop drives every variant through sample / learn / mean_action /
state_dict only; learn's shape errors; InfiniteHorizonHiREPS.create."""

import copy
from collections.abc import Callable

import pytest
import torch
from torch import Tensor

from hireps_torch import Algorithm, Experience
from hireps_torch.algorithms import (
    REPS,
    EpisodicHiREPS,
    InfiniteHorizonHiREPS,
    TimeIndexedHiREPS,
)
from hireps_torch.algorithms.base import stream_seed
from hireps_torch.features import QuadraticFeatures
from hireps_torch.policies import HierarchicalPolicy

f64 = torch.float64
Act = Callable[[Tensor, int], Tensor]  # states (N, S), step -> actions (N, D)


def generic_loop(
    make: Callable[[], Algorithm],
    rollout: Callable[[Act, torch.Generator], Experience],
    iterations: int,
) -> list[float]:
    """Train a fresh algorithm; returns the noise-free mean return before and after each update.

    Uses nothing but the interface. After training, a fresh algorithm restored from the
    state_dict must give the same mean actions and draw the same samples, at every step.
    """
    algo = make()
    assert isinstance(algo, Algorithm)
    gen = torch.Generator().manual_seed(0)

    def score() -> float:  # the same start states every time: a fair comparison
        return float(
            rollout(algo.mean_action, torch.Generator().manual_seed(99)).rewards.sum(1).mean()
        )

    curve = [score()]
    for i in range(iterations):
        diagnostics = algo.learn(rollout(algo.sample, gen))
        assert algo.iteration == diagnostics["iteration"] == i + 1
        curve.append(score())

    restored = make()
    restored.load_state_dict(copy.deepcopy(algo.state_dict()))
    assert restored.iteration == algo.iteration
    probe = rollout(algo.mean_action, torch.Generator().manual_seed(5)).states
    for k in range(len(algo.policies)):
        assert torch.equal(restored.mean_action(probe[:, k], k), algo.mean_action(probe[:, k], k))
        assert torch.equal(restored.sample(probe[:, k], k), algo.sample(probe[:, k], k))
    return curve


# ---- three toy problems -----------------------------------------------------------------------
def contextual_quadratic(act: Act, gen: torch.Generator, n: int = 40) -> Experience:
    """Episodic: context s ~ U[-1, 1], reward -||theta - (s, -s)||^2 (K = 1, S = 1, D = 2)."""
    s = torch.rand(n, 1, generator=gen, dtype=f64) * 2 - 1
    theta = act(s, 0)
    reward = -((theta - torch.cat([s, -s], 1)) ** 2).sum(1)
    return Experience(s[:, None], theta[:, None], reward[:, None])


def quadratic(act: Act, gen: torch.Generator, n: int = 30) -> Experience:
    """Episodic without context (S = 0): reward -||theta - (1, -2)||^2."""
    s = torch.zeros(n, 0, dtype=f64)
    theta = act(s, 0)
    reward = -((theta - torch.tensor([1.0, -2.0], dtype=f64)) ** 2).sum(1)
    return Experience(s[:, None], theta[:, None], reward[:, None])


def two_step_sequence(act: Act, gen: torch.Generator, n: int = 40) -> Experience:
    """Time-indexed, K = 2: s_2 = s_1 + a_1, reward r_k = -(s_k + a_k - 1)^2 - 0.1 a_k^2."""
    s1 = torch.rand(n, 1, generator=gen, dtype=f64) * 2 - 1
    a1 = act(s1, 0)
    s2 = s1 + a1
    a2 = act(s2, 1)
    rewards = torch.stack(
        [-(((s + a)[:, 0] - 1) ** 2) - 0.1 * a[:, 0] ** 2 for s, a in ((s1, a1), (s2, a2))], 1
    )
    return Experience(torch.stack([s1, s2], 1), torch.stack([a1, a2], 1), rewards)


def linear_system(act: Act, gen: torch.Generator, n: int = 8, T: int = 15) -> Experience:
    """Infinite horizon: s' = s + 0.5 a, reward -s^2 - 0.1 a^2, n runs of T decisions from
    s ~ U[-2, 2] (decisions, K = 1; rewards are per decision, so the score is their mean)."""
    s = torch.rand(n, 1, generator=gen, dtype=f64) * 4 - 2
    states, actions, rewards, nexts = [], [], [], []
    for _ in range(T):
        a = act(s, 0)
        nxt = s + 0.5 * a
        states.append(s), actions.append(a), nexts.append(nxt)
        rewards.append(-(s[:, 0] ** 2) - 0.1 * a[:, 0] ** 2)
        s = nxt
    cat = torch.cat
    return Experience(
        cat(states)[:, None], cat(actions)[:, None], cat(rewards)[:, None], cat(nexts)[:, None]
    )


def make_linear_system_algo(seed: int = 0) -> InfiniteHorizonHiREPS:
    start = torch.linspace(-2, 2, 41, dtype=f64)[:, None]
    return InfiniteHorizonHiREPS.create(
        1, 1, value_features=QuadraticFeatures(1), initial_states=start, gamma=0.9,
        n_options=3, init_std=1.0, epsilon=0.5, seed=seed,
    )  # fmt: skip


CASES = {
    "episodic": (
        lambda: EpisodicHiREPS.create(2, context_dim=1, n_options=3, epsilon=0.5, seed=1),
        contextual_quadratic,
    ),
    "reps": (lambda: REPS.create(2, init_std=2.0, epsilon=0.5, seed=2), quadratic),
    "time_indexed": (
        lambda: TimeIndexedHiREPS.create(2, 1, 1, n_options=3, init_std=1.0, epsilon=0.5, seed=3),
        two_step_sequence,
    ),
    "infinite_horizon": (make_linear_system_algo, linear_system),
}


@pytest.mark.parametrize("name", list(CASES))
def test_one_loop_improves_every_variant_and_checkpoints_round_trip(name):
    make, rollout = CASES[name]
    curve = generic_loop(make, rollout, iterations=6)
    assert curve[0] < 0 and curve[-1] > 0.2 * curve[0], curve  # the cost falls by > 80 %


def assert_same_state(a, b):
    """Two state dicts are equal entry by entry (policies, value weights, generator, ...)."""
    if isinstance(a, torch.Tensor):
        assert torch.equal(a, b)
    elif isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_same_state(a[key], b[key])
    elif isinstance(a, list | tuple):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same_state(x, y)
    else:
        assert a == b


@pytest.mark.parametrize("name", list(CASES))
def test_a_state_dict_is_a_snapshot_that_later_updates_leave_alone(name):
    """state_dict() taken before two updates still holds the state of that moment (no tensor
    shared with the policy): loaded back, the algorithm acts and draws as a fresh one does."""
    make, rollout = CASES[name]
    algo, fresh = make(), make()
    start = algo.state_dict()
    gen = torch.Generator().manual_seed(0)
    for _ in range(2):
        algo.learn(rollout(algo.sample, gen))
    assert_same_state(start, fresh.state_dict())
    algo.load_state_dict(start)
    probe = rollout(fresh.mean_action, torch.Generator().manual_seed(5)).states
    for k in range(len(algo.policies)):
        assert torch.equal(algo.mean_action(probe[:, k], k), fresh.mean_action(probe[:, k], k))
        assert torch.equal(algo.sample(probe[:, k], k), fresh.sample(probe[:, k], k))


def test_learn_is_tell_and_update():
    """learn delegates: the same samples give the same state (policies, value weights) and the
    same diagnostics as the variant's own update."""
    gen = torch.Generator().manual_seed(4)
    a, b = make_linear_system_algo(), make_linear_system_algo()
    exp = linear_system(a.sample, gen)
    b.generator.set_state(a.generator.get_state())  # as if b had drawn the samples
    da = a.learn(exp)
    e = exp
    db = b.update(e.states[:, 0], e.actions[:, 0], e.rewards[:, 0], e.next_states[:, 0])
    assert da == db
    assert_same_state(a.state_dict(), b.state_dict())

    ti = [TimeIndexedHiREPS.create(2, 1, 1, n_options=2, seed=0) for _ in range(2)]
    exp = two_step_sequence(ti[0].sample, torch.Generator().manual_seed(1))
    ti[1].generator.set_state(ti[0].generator.get_state())
    d0 = ti[0].learn(exp)
    d1 = ti[1].tell(exp.states, exp.actions, exp.rewards)
    assert d0 == d1
    assert_same_state(ti[0].state_dict(), ti[1].state_dict())


def test_sample_draws_from_the_algorithms_generator():
    algo = make_linear_system_algo(seed=7)
    s = torch.linspace(-1, 1, 5, dtype=f64)[:, None]
    state = algo.generator.get_state()
    x = algo.sample(s)
    assert not torch.equal(x, algo.sample(s))  # the generator advanced
    algo.generator.set_state(state)
    assert torch.equal(x, algo.sample(s))
    assert torch.equal(algo.mean_action(s), algo.policy.mean_action(s)[0])


def _exp(N=6, K=1, S=1, D=2, **extra):
    return Experience(torch.zeros(N, K, S), torch.zeros(N, K, D), torch.zeros(N, K), **extra)


def test_learn_names_expected_and_actual_shapes():
    ep = EpisodicHiREPS.create(2, context_dim=1, n_options=2)
    with pytest.raises(
        ValueError, match=r"experience.rewards must have shape \(N, 1\), got \(6,\)"
    ):
        ep.learn(Experience(torch.zeros(6, 1, 1), torch.zeros(6, 1, 2), torch.zeros(6)))
    with pytest.raises(ValueError, match=r"states must have shape \(6, 1, 1\), got \(6, 1, 3\)"):
        ep.learn(_exp(S=3))
    with pytest.raises(ValueError, match=r"actions must have shape \(6, 1, 2\), got \(6, 1, 3\)"):
        ep.learn(_exp(D=3))
    with pytest.raises(ValueError, match="next_states is read by InfiniteHorizonHiREPS only"):
        ep.learn(_exp(next_states=torch.zeros(6, 1, 1)))
    with pytest.raises(TypeError, match="experience.actions must be a tensor, got list"):
        ep.learn(Experience(torch.zeros(6, 1, 1), [[0.0, 0.0]] * 6, torch.zeros(6, 1)))
    with pytest.raises(TypeError, match="learn takes an Experience"):
        ep.learn((torch.zeros(6, 1, 1), torch.zeros(6, 1, 2), torch.zeros(6, 1)))

    ti = TimeIndexedHiREPS.create(3, 2, 1, n_options=2)
    with pytest.raises(ValueError, match=r"rewards must have shape \(N, 3\), got \(6, 1\)"):
        ti.learn(_exp())
    with pytest.raises(ValueError, match=r"states must have shape \(6, 3, 1\), got \(6, 3, 2\)"):
        ti.learn(_exp(K=3, S=2))
    with pytest.raises(ValueError, match=r"step must be in \[0, 3\)"):
        ti.sample(torch.zeros(4, 1), 3)

    ih = make_linear_system_algo()
    with pytest.raises(ValueError, match=r"needs experience.next_states \(6, 1, 1\)"):
        ih.learn(_exp(D=1))
    with pytest.raises(ValueError, match=r"next_states must have shape \(6, 1, 1\), got \(6, 1\)"):
        ih.learn(_exp(D=1, next_states=torch.zeros(6, 1)))
    with pytest.raises(ValueError, match="terminated must be a bool tensor"):
        ih.learn(_exp(D=1, next_states=torch.zeros(6, 1, 1), terminated=torch.zeros(6, 1)))
    with pytest.raises(ValueError, match=r"rewards must have shape \(N, 1\), got \(6, 2\)"):
        ih.learn(_exp(K=2, D=1, next_states=torch.zeros(6, 2, 1)))
    with pytest.raises(ValueError, match=r"step must be in \[0, 1\)"):
        ih.sample(torch.zeros(4, 1), 1)
    with pytest.raises(ValueError, match=r"states must have shape \(N, 1\), got \(4, 2\)"):
        ih.mean_action(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="states contains non-finite"):
        ih.sample(torch.full((4, 1), float("nan")))


def test_infinite_horizon_create_is_the_manual_construction():
    start = torch.rand(20, 2, generator=torch.Generator().manual_seed(0), dtype=f64)
    kw = dict(value_features=QuadraticFeatures(2), initial_states=start, gamma=0.95)
    algo = InfiniteHorizonHiREPS.create(
        2, 3, n_options=4, init_std=0.5, spread=2.0, kappa_rel=0.8, prune_threshold=0.0, seed=5,
        **kw,
    )  # fmt: skip
    policy = HierarchicalPolicy.create(
        4, 2, 3, init_std=0.5, spread=2.0, gating_features=QuadraticFeatures(2),
        generator=torch.Generator().manual_seed(5),
    )  # fmt: skip
    sampling = stream_seed(5, "sampling")
    manual = InfiniteHorizonHiREPS(policy, kappa_rel=0.8, prune_threshold=0.0, seed=sampling, **kw)
    a, b = algo.state_dict(), manual.state_dict()
    assert a.keys() == b.keys()
    for k, v in a["policy"].items():
        assert torch.equal(v, b["policy"][k]), k
    assert torch.equal(a["generator"], b["generator"])
    assert (algo.gamma, algo.epsilon, algo.kappa_rel, algo.prune_threshold) == (0.95, 0.5, 0.8, 0.0)
    assert algo.policy.n_options == 4 and algo.policy.action_dim == 3
    assert isinstance(algo.policy.gating_features, QuadraticFeatures)

    with pytest.raises(ValueError, match="value_features take states of dimension 2"):
        InfiniteHorizonHiREPS.create(3, 1, **kw)
    with pytest.raises(ValueError, match="state_dim must be >= 1"):
        InfiniteHorizonHiREPS.create(0, 1, **kw)
    with pytest.raises(ValueError, match="gamma"):
        InfiniteHorizonHiREPS.create(2, 1, **{**kw, "gamma": 1.0})
