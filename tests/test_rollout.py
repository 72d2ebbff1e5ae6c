"""TorchRL glue: the policy as a TensorDictModule, a Collector over the batched pendulum."""

import torch

from environments.pendulum import PendulumParams, PendulumSwingUpBatchEnv, pendulum_step
from hireps_torch.policies import HierarchicalPolicy
from hireps_torch.rollout import make_collector, policy_module, shutdown_collector, transitions


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
    from tensordict import TensorDict

    obs = torch.randn(5, 2)
    td = actor(TensorDict({"observation": obs}, batch_size=[5]))
    expected, option = pol.mean_action(obs.double())
    assert torch.allclose(td["action"], expected.float())
    assert torch.equal(td["option"], option)
