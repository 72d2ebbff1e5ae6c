"""TorchRL glue: the policy as a TensorDict module, a Collector over the batched pendulum."""

import pytest
import torch
from tensordict import TensorDict

from hireps_torch.envs.pendulum import PendulumParams, PendulumSwingUpBatchEnv, pendulum_step
from hireps_torch.policies import HierarchicalPolicy
from hireps_torch.rollout import (
    episodes,
    make_collector,
    policy_module,
    shutdown_collector,
    time_indexed_module,
    transitions,
)


def test_collector_gathers_decisions_with_their_options():
    torch.manual_seed(0)
    params = PendulumParams(restart_probability=0.0)
    pol = HierarchicalPolicy.create(3, 2, 1, init_std=torch.tensor([1.0], dtype=torch.float64))
    actor = policy_module(pol)
    collector = make_collector(
        lambda: PendulumSwingUpBatchEnv(4, params, seed=3),
        actor,
        frames_per_batch=40,
        total_frames=80,
    )
    try:
        batches = list(collector)
    finally:
        shutdown_collector(collector)
    assert len(batches) == 2
    b = batches[0]
    assert b.batch_size == torch.Size([4, 10])
    assert "collector" not in b.keys()  # no trajectory ids: episodes end where done is set
    assert b["option"].dtype == torch.int64 and set(b["option"].unique().tolist()) <= {0, 1, 2}
    s, a, r, s2, o = transitions(b, "state")
    assert s.shape == (40, 2) and a.shape == (40, 1) and r.shape == (40,) and o.shape == (40,)
    # each sample's next state is the physics applied to its state and action
    s2_check, r_check, _ = pendulum_step(s, a.to(torch.float32).to(torch.float64), params)
    assert torch.allclose(s2, s2_check, atol=1e-9)
    assert torch.allclose(r, r_check, rtol=1e-6)


def test_policy_updates_are_seen_by_the_collector():
    pol = HierarchicalPolicy.create(1, 2, 1, init_std=torch.tensor([1e-6], dtype=torch.float64))
    collector = make_collector(
        lambda: PendulumSwingUpBatchEnv(2, seed=0),
        policy_module(pol),
        frames_per_batch=4,
        total_frames=8,
    )
    try:
        means = []
        for i, batch in enumerate(collector):
            means.append(float(batch["action"].mean()))
            pol.sub_policies[0].bias.fill_(1.0 + i)
    finally:
        shutdown_collector(collector)
    assert abs(means[0]) < 1e-3 and abs(means[1] - 1.0) < 1e-3


def test_deterministic_actor_uses_the_mean_of_the_most_probable_option():
    pol = HierarchicalPolicy.create(2, 2, 1)
    actor = policy_module(pol, deterministic=True)
    obs = torch.randn(5, 2, generator=torch.Generator().manual_seed(0))
    td = actor(TensorDict({"observation": obs}, batch_size=[5]))
    expected, option = pol.mean_action(obs.double())
    assert torch.allclose(td["action"], expected.float())
    assert torch.equal(td["option"], option)


def test_the_actor_module_writes_its_out_keys_into_a_tensordict_and_answers_keywords():
    pol = HierarchicalPolicy.create(2, 2, 1)
    actor = policy_module(pol, deterministic=True, observation_key="obs")
    obs = torch.randn(5, 2, generator=torch.Generator().manual_seed(1))
    td = TensorDict({"obs": obs}, batch_size=[5])
    assert actor(td) is td and set(td.keys()) == {"obs", "action", "option"}
    action, option = actor(obs=obs)
    assert torch.equal(action, td["action"]) and torch.equal(option, td["option"])
    assert (actor.in_keys, actor.out_keys) == (["obs"], ["action", "option"])
    out = TensorDict({}, batch_size=[5])
    assert actor(td, tensordict_out=out) is out and torch.equal(out["option"], td["option"])
    actor.out_keys = ["a", "o"]  # renamed outputs are written under their new names
    assert set(actor(TensorDict({"obs": obs}, batch_size=[5])).keys()) == {"obs", "a", "o"}
    with pytest.raises(KeyError, match="obs"):
        actor(TensorDict({"observation": obs}, batch_size=[5]))


def test_time_indexed_actor_acts_with_the_policy_of_each_step():
    # three one-option policies with far-apart means: the action tells which one acted
    pols = [
        HierarchicalPolicy.create(
            1, 2, 1, init_mean=torch.tensor([10.0 * k]), init_std=1e-3, spread=0.0
        )
        for k in range(3)
    ]
    actor = time_indexed_module(pols, deterministic=True)
    td = TensorDict(
        {
            "observation": torch.zeros(6, 2),
            "step_count": torch.tensor([[0], [1], [2], [2], [1], [0]]),
        },
        batch_size=[6],
    )
    out = actor(td)
    assert torch.allclose(out["action"][:, 0], torch.tensor([0.0, 10, 20, 20, 10, 0]), atol=1e-6)
    td["step_count"] = torch.full((6, 1), 3)
    with pytest.raises(ValueError, match=r"step_count must be in \[0, 3\), got \[3\]"):
        actor(td)


def test_episodes_cuts_whole_episodes_and_rejects_partial_ones():
    N, K = 4, 3
    done = torch.zeros(N * K, 1, dtype=torch.bool)
    done[K - 1 :: K] = True
    obs = torch.arange(N * K, dtype=torch.float64)[:, None].repeat(1, 2)
    batch = TensorDict(
        {
            "observation": obs,
            "action": torch.ones(N * K, 5),
            "next": {"observation": obs + 100, "reward": torch.ones(N * K, 1), "done": done},
        },
        batch_size=[N * K],
    )
    s, a, r, final = episodes(batch, K)
    assert s.shape == (N, K, 2) and a.shape == (N, K, 5) and r.shape == (N, K)
    assert torch.equal(s[1, :, 0], torch.tensor([3.0, 4, 5], dtype=torch.float64))
    assert torch.equal(final[:, 0], torch.tensor([102.0, 105, 108, 111], dtype=torch.float64))
    with pytest.raises(ValueError, match="whole number of 3-step episodes"):
        episodes(batch[:10], K)
    batch["next", "done"][4] = True  # an episode that ended early
    with pytest.raises(ValueError, match="done flags"):
        episodes(batch, K)


def test_time_indexed_actor_rejects_float_steps_and_mixed_dimensions():
    a = HierarchicalPolicy.create(1, 2, 1)
    b = HierarchicalPolicy.create(1, 2, 3)
    with pytest.raises(ValueError, match=r"sharing one action dimension, got dimensions \[1, 3\]"):
        time_indexed_module([a, b])
    actor = time_indexed_module([a, a])
    td = TensorDict(
        {"observation": torch.zeros(2, 2), "step_count": torch.tensor([[0.0], [1.5]])},
        batch_size=[2],
    )
    with pytest.raises(ValueError, match="step_count must be an integer tensor"):
        actor(td)


def test_episodes_need_a_positive_episode_length():
    batch = TensorDict({}, batch_size=[4])
    for K, error in ((0, ValueError), (-2, ValueError), (2.0, TypeError)):
        with pytest.raises(error, match="K must be"):
            episodes(batch, K)


def test_actors_take_an_empty_batch():
    pol = HierarchicalPolicy.create(2, 1, 3, generator=torch.Generator().manual_seed(0))
    for module in (policy_module(pol), time_indexed_module([pol, pol])):
        td = TensorDict(
            {"observation": torch.zeros(0, 1), "step_count": torch.zeros(0, 1, dtype=torch.long)},
            batch_size=[0],
        )
        out = module(td)
        assert out["action"].shape == (0, 3) and out["option"].shape == (0,)


def test_a_population_actor_pairs_the_last_batch_dimension_with_its_members():
    pop = HierarchicalPolicy.stack(
        [
            HierarchicalPolicy.create(3, 2, 1, generator=torch.Generator().manual_seed(s))
            for s in range(3)
        ]
    )
    actor = policy_module(pop, deterministic=True)
    obs = torch.randn(2, 6, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    both = actor(TensorDict({"observation": obs}, [2, 6]))
    for t in range(2):  # (T, S B, C) acts as T calls on (S B, C)
        one = actor(TensorDict({"observation": obs[t]}, [6]))
        assert torch.equal(both["action"][t], one["action"])
        assert torch.equal(both["option"][t], one["option"])
    with pytest.raises(
        ValueError, match=r"a population of 3 takes observations \(\.\.\., S B, C\)"
    ):
        actor(TensorDict({"observation": torch.zeros(10, 2)}, [10]))
    ints = actor(TensorDict({"observation": torch.zeros(6, 2, dtype=torch.long)}, [6]))
    assert ints["action"].dtype == torch.float64  # not truncated to the observation's integers
    for shape in [(0, 6), (0,)]:  # no time steps: empty actions, as for one policy
        out = actor(TensorDict({"observation": torch.zeros(*shape, 2)}, list(shape)))
        assert out["action"].shape == (*shape, 1) and out["option"].shape == shape


def test_cutting_a_batch_names_a_missing_entry_and_an_empty_batch():
    pol = HierarchicalPolicy.create(2, 2, 1, generator=torch.Generator().manual_seed(0))
    collector = make_collector(
        lambda: PendulumSwingUpBatchEnv(2, seed=0), policy_module(pol), frames_per_batch=4
    )
    try:
        batch = next(iter(collector))
    finally:
        shutdown_collector(collector)
    assert transitions(batch)[0].shape == (4, 2)
    for cut in (lambda b, key: transitions(b, key), lambda b, key: episodes(b, 2, key)):
        with pytest.raises(ValueError, match=r"the batch holds no 'stat' entry \(state_key"):
            cut(batch, "stat")
        with pytest.raises(ValueError, match=r"the batch holds no steps \(batch size \(2, 0\)\)"):
            cut(batch[:, :0], "observation")
    with pytest.raises(ValueError, match=r"no \('next', 'reward'\) entry"):
        transitions(batch.exclude(("next", "reward")))


def test_the_time_indexed_actor_names_a_population_and_a_bad_step_count():
    pop = HierarchicalPolicy.stack([HierarchicalPolicy.create(2, 2, 1) for _ in range(2)])
    with pytest.raises(
        ValueError, match="takes the policies of one run; policy 0 holds a population of 2"
    ):
        time_indexed_module([pop])
    actor = time_indexed_module([HierarchicalPolicy.create(2, 2, 1) for _ in range(3)])
    td = TensorDict(
        {"observation": torch.zeros(4, 2), "step_count": torch.zeros(4, 2, dtype=torch.long)}, [4]
    )
    with pytest.raises(ValueError, match=r"step_count must have shape \(4,\) or \(4, 1\)"):
        actor(td)


def test_actors_refuse_complex_observations():
    pol = HierarchicalPolicy.create(2, 1, 3, generator=torch.Generator().manual_seed(0))
    for module in (policy_module(pol), time_indexed_module([pol, pol])):
        td = TensorDict(
            {
                "observation": torch.ones(4, 1, dtype=torch.complex64),
                "step_count": torch.zeros(4, 1, dtype=torch.long),
            },
            batch_size=[4],
        )
        with pytest.raises(TypeError, match="observation must hold real numbers, got dtype"):
            module(td)


def test_actors_draw_from_the_generator_they_are_given():
    """policy_module / time_indexed_module(..., generator=g) sample from g (the same draws
    as the policy's own sample with a generator of that seed), not from the global RNG."""
    pol = HierarchicalPolicy.create(
        3, 2, 1, init_std=1.0, generator=torch.Generator().manual_seed(1)
    )
    obs = torch.randn(8, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    td = TensorDict({"observation": obs, "step_count": torch.zeros(8, 1, dtype=torch.long)}, [8])
    want = pol.sample(obs, torch.Generator().manual_seed(7))[0]
    for make in (policy_module, time_indexed_module):
        actor = make(
            pol if make is policy_module else [pol], generator=torch.Generator().manual_seed(7)
        )
        torch.manual_seed(0)
        assert torch.equal(actor(td.clone())["action"], want)
        torch.manual_seed(0)
        assert not torch.equal(
            make(pol if make is policy_module else [pol])(td.clone())["action"], want
        )


def test_a_shared_generator_is_refused_with_worker_processes_and_widths_are_named():
    """A collector with worker processes would copy the actor's generator into each (the same
    draws everywhere): refused before any process starts. Both actors name an observation of
    the wrong width."""
    pol = HierarchicalPolicy.create(3, 2, 1)
    actor = policy_module(pol, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="num_workers = 2 processes would each copy"):
        make_collector(lambda: PendulumSwingUpBatchEnv(4, PendulumParams()), actor,
                       frames_per_batch=8, num_workers=2)  # fmt: skip
    td = TensorDict(
        {"observation": torch.zeros(4, 3), "step_count": torch.zeros(4, 1, dtype=torch.long)}, [4]
    )
    for actor in (policy_module(pol), time_indexed_module([pol])):
        with pytest.raises(
            ValueError, match=r"observation must have shape \(\.\.\., 2\) .*got \(4, 3\)"
        ):
            actor(td.clone())
