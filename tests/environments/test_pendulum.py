"""Pendulum swing-up: physics, the two adapters, bad input."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs.utils import check_env_specs

from hireps_torch.envs.pendulum import (
    ENV_ID,
    PendulumParams,
    PendulumSwingUpBatchEnv,
    PendulumSwingUpEnv,
    control_step,
    energy,
    evaluate_swing_up,
    mirror_decisions,
    mirror_states,
    pd_torque,
    pendulum_step,
    sample_start,
    step_reward,
    wrap_angle,
)


def test_gymnasium_env_passes_check_env():
    env = gym.make(ENV_ID)
    check_env(env.unwrapped)


def test_torchrl_env_passes_check_env_specs():
    check_env_specs(PendulumSwingUpBatchEnv(5, seed=1))


def test_adapters_give_the_same_trajectory_for_the_same_seed_and_actions():
    params = PendulumParams(restart_probability=0.0)
    actions = (
        torch.linspace(-3.0, 3.0, 40, dtype=torch.float64).reshape(-1, 1)
        * torch.tensor([1.0, -1.0]).repeat(20)[:, None]
    )
    g = PendulumSwingUpEnv(params)
    obs_g, info = g.reset(seed=7)
    t = PendulumSwingUpBatchEnv(1, params, seed=123)
    t.set_seed(7)
    td = t.reset()
    assert np.allclose(td["state"][0].numpy(), info["state"], atol=0, rtol=0)
    for a in actions:
        obs_g, r_g, term, trunc, info = g.step(a.numpy().astype(np.float32))
        td["action"] = a.to(torch.float32).reshape(1, 1)
        td = t.step(td)["next"]
        assert np.array_equal(td["state"][0].numpy(), info["state"])
        assert float(td["reward"][0, 0]) == pytest.approx(r_g, rel=1e-6)
        assert not term and not trunc and not bool(td["done"].any())


def test_restarts_happen_at_the_stated_rate():
    params = PendulumParams(steps_per_decision=1, restart_probability=0.2)
    env = PendulumSwingUpBatchEnv(2000, params, seed=0)
    td = env.reset()
    td["action"] = torch.zeros(2000, 1)
    out = env.step(td)["next"]
    rate = float(out["truncated"].float().mean())
    assert rate == pytest.approx(0.2, abs=0.03)
    assert not bool(out["terminated"].any())
    assert PendulumParams(steps_per_decision=5).gamma == pytest.approx(1 - 0.004)


def test_pd_controller_never_exceeds_the_torque_limit():
    p = PendulumParams()
    g = torch.Generator().manual_seed(0)
    state = torch.randn(5000, 2, generator=g, dtype=torch.float64) * torch.tensor([3.0, 40.0])
    target = torch.randn(5000, generator=g, dtype=torch.float64) * 20
    u = pd_torque(state, target, p)
    assert float(u.abs().max()) <= p.max_torque
    assert float(u.abs().max()) == pytest.approx(p.max_torque)  # it does saturate
    # and along a trajectory driven by extreme targets
    s = sample_start(64, p, g)
    for k in range(50):
        a = torch.full((64,), 6.0 if k % 2 else -6.0, dtype=torch.float64)
        u = pd_torque(s, a.clamp(-p.action_limit, p.action_limit), p)
        assert float(u.abs().max()) <= p.max_torque
        s, _, _ = pendulum_step(s, a, p)


def test_energy_is_conserved_without_friction_and_torque():
    p = PendulumParams(friction=0.0)
    s = torch.tensor([[2.0, 0.0], [0.3, 5.0], [-3.0, -1.0]], dtype=torch.float64)
    e0 = energy(s, p)
    zero = torch.zeros(3, dtype=torch.float64)
    for _ in range(1000):  # 10 s
        s = control_step(s, zero, p)
    rel = ((energy(s, p) - e0).abs() / e0).max()
    assert float(rel) < 1e-6


def test_friction_dissipates_energy():
    p = PendulumParams()
    s = torch.tensor([[2.0, 0.0]], dtype=torch.float64)
    e0 = energy(s, p)
    for _ in range(300):
        s = control_step(s, torch.zeros(1, dtype=torch.float64), p)
    assert float(energy(s, p)) < float(e0)


def test_hanging_at_rest_stays_and_upright_is_unstable():
    p = PendulumParams()
    zero = torch.zeros(1, dtype=torch.float64)
    s = torch.tensor([[-math.pi, 0.0]], dtype=torch.float64)
    for _ in range(100):
        s = control_step(s, zero, p)
    assert float(wrap_angle(s[0, 0] - math.pi).abs()) < 1e-9
    s = torch.tensor([[1e-3, 0.0]], dtype=torch.float64)
    for _ in range(100):
        s = control_step(s, zero, p)
    assert float(s[0, 0].abs()) > 1e-2  # falls


def test_reward_formula_at_hand_computed_states():
    s = torch.tensor([[0.0, 0.0], [math.pi / 2, 0.0], [-math.pi / 2, 3.0], [-math.pi, 0.0]])
    half = 500.0 * math.sqrt(0.5)  # tip at l sqrt(2) from upright, over 2 l
    assert step_reward(s).tolist() == pytest.approx([500.0, 500 - half, 470 - half, 0.0])
    # a decision sums d per-step rewards
    p = PendulumParams(steps_per_decision=3)
    state = torch.tensor([[0.2, 0.1]], dtype=torch.float64)
    _, r, path = pendulum_step(state, torch.tensor([0.0], dtype=torch.float64), p)
    assert path.shape == (1, 3, 2)
    assert float(r[0]) == pytest.approx(float(step_reward(path).sum()))


def test_bad_actions_raise_clear_errors():
    p = PendulumParams()
    s = sample_start(3, p, None)
    with pytest.raises(ValueError, match="non-finite desired angle at index 1"):
        pendulum_step(s, torch.tensor([0.0, math.nan, 0.0], dtype=torch.float64), p)
    with pytest.raises(ValueError, match="shape"):
        pendulum_step(s, torch.zeros(2, dtype=torch.float64), p)
    env = PendulumSwingUpEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([np.inf], dtype=np.float32))
    with pytest.raises(ValueError, match="steps_per_decision"):
        PendulumParams(steps_per_decision=0)
    # out-of-range targets are clipped, not an error
    far = pendulum_step(s, torch.full((3,), 100.0, dtype=torch.float64), p)[0]
    lim = pendulum_step(s, torch.full((3,), p.action_limit, dtype=torch.float64), p)[0]
    assert torch.equal(far, lim)


def test_evaluation_of_an_energy_pumping_controller_succeeds():
    p = PendulumParams()
    e_up = 2 * p.mass * p.gravity * p.length

    def act(s):
        th, om = s[:, 0], s[:, 1]
        pump = th + 3 * torch.sign(om + 1e-9) * (energy(s, p) < e_up).double()
        return torch.where(th.abs() < 0.6, -th - 0.3 * om, pump - 0.5 * om * (energy(s, p) >= e_up))

    ev = evaluate_swing_up(act, p, n_rollouts=10)
    assert ev.success_rate == 1.0
    assert 0.5 < ev.time_to_upright < 3.0
    idle = evaluate_swing_up(lambda s: torch.full((s.shape[0],), math.pi), p, n_rollouts=10)
    assert idle.success_rate == 0.0 and idle.reached_share == 0.0


def test_the_task_is_mirror_symmetric_and_mirror_decisions_use_it():
    p = PendulumParams()
    g = torch.Generator().manual_seed(3)
    s = torch.randn(200, 2, generator=g, dtype=torch.float64) * torch.tensor([2.0, 6.0])
    s = torch.stack([wrap_angle(s[:, 0]), s[:, 1]], -1)
    a = torch.randn(200, generator=g, dtype=torch.float64) * 4  # some beyond the clip
    nxt, r, path = pendulum_step(s, a, p)
    m_nxt, m_r, m_path = pendulum_step(mirror_states(s), -a, p)
    gap = m_path - mirror_states(path)
    assert float(wrap_angle(gap[..., 0]).abs().max()) < 1e-9
    assert float(gap[..., 1].abs().max()) < 1e-9
    assert torch.allclose(m_r, r, atol=1e-9)
    down = torch.tensor([[-math.pi, 0.0]], dtype=torch.float64)
    assert float(mirror_states(down)[0, 0]) == -math.pi  # stays in [-pi, pi)
    term = torch.zeros(200, dtype=torch.bool)
    ms, ma, mr, mn, mt = mirror_decisions(s, a[:, None], r, nxt, term)
    assert ms.shape == (400, 2) and ma.shape == (400, 1) and mt.shape == (400,)
    assert torch.equal(ms[:200], s) and torch.equal(ma[200:, 0], -a) and torch.equal(mr[200:], r)
    assert torch.equal(mn[200:], mirror_states(nxt))


@pytest.mark.parametrize(
    "make, error, match",
    [
        (lambda: PendulumSwingUpEnv(max_decisions=0), ValueError, "max_decisions must be >= 1"),
        (lambda: PendulumSwingUpBatchEnv(4, max_decisions=-1), ValueError, "max_decisions"),
        (lambda: PendulumSwingUpBatchEnv(4, max_decisions=2.5), TypeError, "max_decisions"),
        (lambda: PendulumSwingUpBatchEnv(0), ValueError, "batch_size must be >= 1"),
        (lambda: PendulumSwingUpBatchEnv(2.0), TypeError, "batch_size must be an integer"),
        (lambda: PendulumSwingUpBatchEnv(2, seed=1.5), TypeError, "seed must be an integer"),
        (lambda: PendulumParams(steps_per_decision=2.5), TypeError, "steps_per_decision"),
        (lambda: PendulumParams(steps_per_decision=0), ValueError, "steps_per_decision"),
        (lambda: PendulumParams(dt=math.inf), ValueError, "dt must be finite and > 0"),
        (lambda: PendulumParams(kp=math.nan), ValueError, "kp must be finite and >= 0"),
        (lambda: sample_start(-3, PendulumParams(), None), ValueError, "n must be >= 0"),
        (lambda: evaluate_swing_up(abs, n_rollouts=0), ValueError, "n_rollouts must be >= 1"),
        (lambda: evaluate_swing_up(abs, seconds=math.nan), ValueError, "seconds must be finite"),
        (lambda: evaluate_swing_up(abs, hold_seconds=-1), ValueError, "hold_seconds"),
    ],
)
def test_bad_counts_and_params_are_named(make, error, match):
    with pytest.raises(error, match=match):
        make()


def test_a_non_finite_state_is_named_not_propagated():
    state = torch.tensor([[0.1, math.nan]], dtype=torch.float64)
    with pytest.raises(ValueError, match="state contains non-finite"):
        pendulum_step(state, torch.zeros(1), PendulumParams())


@pytest.mark.parametrize("env_cls", ["pendulum", "ball_on_beam"])
def test_maybe_reset_gives_what_torchrl_s_generic_reset_gives(env_cls, monkeypatch):
    """The batched adapters' own partial reset against EnvBase.maybe_reset: collected batches
    (restarts and terminations included) equal entry for entry."""
    from tensordict.nn import TensorDictModule
    from torchrl.envs import EnvBase

    from hireps_torch.envs._common import ScalarActionBatchEnv
    from hireps_torch.envs.ball_on_beam import BallOnBeamBatchEnv
    from hireps_torch.rollout import make_collector

    make = {
        "pendulum": lambda: PendulumSwingUpBatchEnv(
            30, PendulumParams(restart_probability=0.05), 3
        ),
        "ball_on_beam": lambda: BallOnBeamBatchEnv(30, seed=3),
    }[env_cls]

    class Noise(torch.nn.Module):
        def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor]:
            return (torch.randn(obs.shape[0], 1) * 0.5,)

    def collect() -> list:
        torch.manual_seed(0)
        actor = TensorDictModule(Noise(), in_keys=["observation"], out_keys=["action"])
        col = make_collector(make, actor, frames_per_batch=900, total_frames=2700)
        return [batch.clone() for batch in col]

    ours = collect()
    monkeypatch.setattr(ScalarActionBatchEnv, "maybe_reset", EnvBase.maybe_reset)
    generic = collect()
    assert sum(int(b["next", "done"].sum()) for b in ours) > 20  # resets did happen
    for a, b in zip(ours, generic, strict=True):
        assert set(a.keys(True, True)) == set(b.keys(True, True))
        for key in a.keys(True, True):
            assert torch.equal(a[key], b[key]), key


def test_maybe_reset_keeps_the_rows_that_did_not_end_and_names_bad_flags():
    """Rows not done keep whatever the tensordict holds; missing done keys are allowed (as in
    TorchRL); a non-bool flag is refused by name and resets nothing."""
    from tensordict import TensorDict

    B = 4
    env = PendulumSwingUpBatchEnv(B, seed=0)
    env.reset()
    before = env.task.state.clone()
    d = torch.tensor([[True], [False], [False], [False]])
    td = TensorDict({"done": d, "observation": torch.full((B, 2), 7.0)}, [B])
    out = env.maybe_reset(td)
    assert torch.equal(out["observation"][1:], torch.full((3, 2), 7.0))
    assert torch.equal(out["observation"][0], env.task.state[0].to(torch.float32))
    assert not bool(out["done"].any()) and torch.equal(env.task.state[1:], before[1:])
    assert env.maybe_reset(TensorDict({}, [B])).is_empty()
    state = env.task.state.clone()
    with pytest.raises(ValueError, match="'done' must be a bool tensor"):
        env.maybe_reset(TensorDict({"done": torch.ones(B, 1)}, [B]))
    assert torch.equal(env.task.state, state)


def test_an_all_false_reset_mask_does_not_count_as_the_first_reset():
    from tensordict import TensorDict

    from hireps_torch.envs._common import ResetNeeded

    env = PendulumSwingUpBatchEnv(3, seed=0)
    env.reset(TensorDict({"_reset": torch.zeros(3, 1, dtype=torch.bool)}, [3]))
    with pytest.raises(ResetNeeded):
        env.step(TensorDict({"action": torch.zeros(3, 1)}, [3]))


def test_the_constructor_seed_starts_the_episodes_that_set_seed_and_gym_start():
    # the adapters' provisional state at construction draws nothing from the task's generator
    built = PendulumSwingUpBatchEnv(1, seed=4).reset()["state"]
    env = PendulumSwingUpBatchEnv(1)
    env.set_seed(4)
    assert torch.equal(built, env.reset()["state"])
    obs, _ = gym.make("hireps/PendulumSwingUp-v0").reset(seed=4)
    np.testing.assert_array_equal(obs, built[0].numpy().astype(obs.dtype))  # gym: float32


def test_a_held_task_keeps_its_systems_through_one_reset_and_draws_nothing():
    from hireps_torch.envs.pendulum import PendulumParams, PendulumTask

    task = PendulumTask(3, PendulumParams(), seed=4)
    task.reset()
    task.step(torch.zeros(3, dtype=torch.float64))
    state, t, gen = task.state.clone(), task.t.clone(), task.gen.get_state()
    task.hold = True
    task.reset()  # as a resumed run's collector resets: the systems go on where they were
    assert torch.equal(task.state, state) and torch.equal(task.t, t) and not task.hold
    assert torch.equal(task.gen.get_state(), gen)
    task.reset()  # the next one restarts them
    assert not torch.equal(task.state, state) and int(task.t.sum()) == 0
