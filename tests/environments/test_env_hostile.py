"""The batched TorchRL environments and the gymnasium adapters under bad input: refused with
a message before anything changes."""

import warnings

import pytest
import torch
from tensordict import TensorDict

from hireps_torch.envs.ball_on_beam import BallOnBeamBatchEnv
from hireps_torch.envs.pendulum import PendulumSwingUpBatchEnv, PendulumSwingUpEnv

BATCHED = [lambda **k: PendulumSwingUpBatchEnv(4, **k), lambda **k: BallOnBeamBatchEnv(4, **k)]


def _snapshot(env):
    return env.task.state.clone(), env.task.t.clone(), env.task.gen.get_state()


def _same(a, b):
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("make", BATCHED, ids=["pendulum", "beam"])
def test_a_negative_seed_is_refused_and_reseeds_nothing(make):
    env = make(seed=3)
    env.reset()
    before = _snapshot(env)
    with pytest.raises(ValueError, match="seed must be >= 0, got -1"):
        env.set_seed(-1)
    assert _same(before, _snapshot(env))
    env.set_seed(5)  # a good seed still works


@pytest.mark.parametrize("make", BATCHED, ids=["pendulum", "beam"])
@pytest.mark.parametrize(
    "mask",
    [torch.ones(4, 1), torch.ones(4, dtype=torch.long)],
    ids=["float", "long"],
)
def test_a_reset_mask_of_another_kind_is_refused_before_any_draw(make, mask):
    env = make(seed=0)
    env.reset()
    env.rand_step(env.reset())
    before = _snapshot(env)
    with pytest.raises(ValueError, match="the reset mask must be a bool tensor of 4 entries"):
        env.reset(TensorDict({"_reset": mask}, batch_size=[4]))
    assert _same(before, _snapshot(env))
    with pytest.raises(ValueError, match="bool tensor of 4 entries"):
        env.task.reset(torch.ones(3, dtype=torch.bool))
    assert _same(before, _snapshot(env))


@pytest.mark.parametrize("make", BATCHED, ids=["pendulum", "beam"])
def test_a_device_without_values_or_absent_is_named(make):
    with pytest.raises(ValueError, match="device 'meta' holds no values"):
        make(device="meta")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda' is not available here"):
            make(device="cuda")


def test_a_step_after_the_episode_ended_warns_as_gymnasium_does():
    env = PendulumSwingUpEnv(max_decisions=2)
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning while the episode runs
        ended = [env.step([0.0])[3] for _ in range(2)]
    assert ended == [False, True]
    with pytest.warns(UserWarning, match="already returned terminated = True or truncated"):
        env.step([0.0])
    env.reset()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a reset starts a fresh episode
        env.step([0.0])


@pytest.mark.parametrize("make", BATCHED, ids=["pendulum", "beam"])
def test_a_tensor_seed_seeds_as_its_integer(make):
    a, b = make(seed=0), make(seed=0)
    a.set_seed(torch.tensor(5))
    b.set_seed(5)
    assert torch.equal(a.task.gen.get_state(), b.task.gen.get_state())


@pytest.mark.parametrize(
    "mask",
    [
        torch.ones(2, 2, dtype=torch.bool),
        torch.ones(1, 4, dtype=torch.bool),
        torch.ones(4, 1, 1, dtype=torch.bool),
        torch.ones(4, dtype=torch.bool, device="meta"),
    ],
    ids=["2x2", "1x4", "4x1x1", "meta"],
)
def test_a_reset_mask_of_another_shape_or_without_values_is_refused(mask):
    env = PendulumSwingUpBatchEnv(4, seed=0)
    env.reset()
    before = _snapshot(env)
    with pytest.raises(ValueError, match=r"bool tensor of 4 entries \(\(B,\) or \(B, 1\)\)"):
        env.task.reset(mask)
    assert _same(before, _snapshot(env))


def test_a_device_whose_backend_is_missing_is_named():
    from hireps_torch.checks import check_present_device

    for device in ("hpu", torch.device("ipu")):
        with pytest.raises(ValueError, match=r"device '(hpu|ipu)' is not available here") as e:
            check_present_device(device)
        assert len(str(e.value)) < 250  # torch's message is cut at its first sentence
