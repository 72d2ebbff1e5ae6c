"""Ball on a beam: physics, the two adapters, rewards, falls, bad input."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs.utils import check_env_specs

from hireps_torch.envs.ball_on_beam import (
    ENV_ID,
    BallOnBeamBatchEnv,
    BallOnBeamEnv,
    BeamParams,
    beam_step,
    control_step,
    evaluate_beam,
    sample_start,
    step_reward,
)


def f64(*rows):
    return torch.tensor(rows, dtype=torch.float64)


def test_gymnasium_env_passes_check_env():
    check_env(gym.make(ENV_ID).unwrapped)


def test_torchrl_env_passes_check_env_specs():
    check_env_specs(BallOnBeamBatchEnv(4, seed=1))


def test_adapters_give_the_same_trajectory_for_the_same_seed_and_actions():
    p = BeamParams()
    g = BallOnBeamEnv(p)
    t = BallOnBeamBatchEnv(1, p, seed=99)
    for episode in range(2):  # the second episode starts on the other side in both
        obs, info = g.reset(seed=5) if episode == 0 else g.reset()
        if episode == 0:
            t.set_seed(5)
        td = t.reset()
        assert np.array_equal(td["state"][0].numpy(), info["state"])
        assert math.copysign(1.0, info["state"][0]) == (1.0 if episode == 0 else -1.0)
        for k in range(p.decisions_per_episode):
            x, v, _ = info["state"]  # a stabilising controller plus a wobble, fed to both
            a = 0.3 * (x - math.copysign(p.goal, x)) + 0.5 * v + 0.02 * math.sin(k)
            obs, r, term, trunc, info = g.step(np.array([a], dtype=np.float32))
            td["action"] = torch.tensor([[a]], dtype=torch.float32)
            td = t.step(td)["next"]
            assert np.array_equal(td["state"][0].numpy(), info["state"])
            assert float(td["reward"][0, 0]) == pytest.approx(r, rel=1e-6)
            assert bool(td["terminated"][0, 0]) == term
            assert bool(td["truncated"][0, 0]) == trunc
            assert not term
        assert trunc  # 20 s


def test_level_beam_with_the_ball_at_rest_stays_at_rest():
    p = BeamParams()
    s = f64([0.2, 0.0, 0.0], [-0.37, 0.0, 0.0], [0.0, 0.0, 0.0])
    for _ in range(40):
        s, r, fell, _ = beam_step(s, torch.zeros(3, dtype=torch.float64), p)
    assert torch.equal(s, f64([0.2, 0.0, 0.0], [-0.37, 0.0, 0.0], [0.0, 0.0, 0.0]))
    assert not bool(fell.any())


@pytest.mark.parametrize("resistance", [0.0, 0.2])
def test_tilted_beam_accelerates_the_ball_downhill_at_the_model_rate(resistance):
    # beam already at the commanded angle (alpha' = 0): x'' = 5/7 (-g sin a - c x'), closed form
    p = BeamParams(rolling_resistance=resistance)
    a0, x0 = 0.05, 0.3
    s = f64([x0, 0.0, a0])
    t = 0.0
    for _ in range(50):  # 1 s
        s = control_step(s, torch.tensor([a0], dtype=torch.float64), p)
        t += p.dt
    acc = 5.0 / 7.0 * p.gravity * math.sin(a0)
    k = 5.0 / 7.0 * resistance
    if k == 0:
        x, v = x0 - 0.5 * acc * t**2, -acc * t
    else:
        v = -acc / k * (1 - math.exp(-k * t))
        x = x0 - acc / k * (t - (1 - math.exp(-k * t)) / k)
    assert float(s[0, 0]) == pytest.approx(x, abs=1e-9)
    assert float(s[0, 1]) == pytest.approx(v, abs=1e-9)
    assert float(s[0, 1]) < 0  # downhill: the raised right end sends the ball to -x


def test_servo_follows_the_command_as_a_first_order_lag():
    p = BeamParams()
    s = f64([0.0, 0.0, 0.0])
    _, _, _, path = beam_step(s, torch.tensor([0.1], dtype=torch.float64), p)
    t = p.dt * torch.arange(1, p.steps_per_decision + 1, dtype=torch.float64)
    expected = 0.1 * (1 - torch.exp(-t / p.servo_tau))
    # RK4 with dt / tau = 0.2: measured truncation error 5.8e-7 rad
    assert torch.allclose(path[0, :, 2], expected, atol=5e-6, rtol=0)


def test_reward_formula_at_hand_computed_states():
    p = BeamParams()
    s = f64([0.3, 0.2, 0.0], [-0.05, 0.0, 0.1], [0.1, 0.0, 0.0], [0.0, -0.5, 0.0])
    # closer goal: +0.1, -0.1 (0.05 away), +0.1 (at it), either (0.1 away)
    assert step_reward(s, p).tolist() == pytest.approx([-0.08, -0.0025, 0.0, -0.26])
    # a decision sums its control steps
    _, r, _, path = beam_step(s[:1], torch.tensor([0.02], dtype=torch.float64), p)
    assert path.shape == (1, p.steps_per_decision, 3)
    assert float(r[0]) == pytest.approx(float(step_reward(path, p).sum()))


def test_a_falling_ball_ends_the_episode_with_the_penalty():
    p = BeamParams()
    s = f64([0.45, 0.5, 0.0], [0.0, 0.0, 0.0])
    nxt, r, fell, path = beam_step(s, f64(0.0, 0.0), p)
    assert fell.tolist() == [True, False]
    steps_on = int((path[0, :, 0].abs() <= p.half_length).sum())
    assert steps_on < p.steps_per_decision
    on_beam = float(step_reward(path[0, : steps_on + 1], p).sum())  # up to the step it fell
    assert float(r[0]) == pytest.approx(on_beam - p.fall_penalty)
    with pytest.raises(ValueError, match="already off the beam"):
        beam_step(nxt, f64(0.0, 0.0), p)
    env = BallOnBeamEnv(p)
    env.reset(seed=0)
    for _ in range(10):
        _, _, term, trunc, _ = env.step(np.array([-0.15], dtype=np.float32))  # right end down
        if term:
            break
    assert term and not trunc


def test_episodes_alternate_sides_in_the_order_they_start():
    """Episodes are numbered as they start, even numbers on the right: R L R, then L R L for
    the next three; a reset before any decision keeps the numbers (fresh noise), a beam that
    restarts alone takes the next number."""
    env = BallOnBeamBatchEnv(3, seed=0)
    first = env.reset()["state"][:, 0]
    again = env.reset()["state"][:, 0]  # nothing played: the same episodes 0, 1, 2
    assert torch.sign(first).tolist() == [1.0, -1.0, 1.0]
    assert torch.sign(again).tolist() == [1.0, -1.0, 1.0]
    assert not torch.equal(first, again)  # drawn again
    assert bool((first.abs() - 0.45).abs().max() < 0.05)
    td = env.reset()
    td["action"] = torch.zeros(3, 1)
    env.step(td)  # a level beam: the balls stay put
    second = env.reset()["state"][:, 0]  # episodes 3, 4, 5
    assert torch.sign(second).tolist() == [-1.0, 1.0, -1.0]
    td = env.reset()
    td["action"] = torch.zeros(3, 1)
    env.step(td)
    td = env.reset(td.set("_reset", torch.tensor([[False], [True], [False]])))
    assert env.task.episodes.tolist() == [3, 6, 5]
    assert float(td["state"][1, 0]) > 0  # episode 6: right


def test_a_collector_that_resets_every_iteration_alternates_sides():
    """The ordinary run's collector (reset at each iteration after the end-of-episode reset)
    starts iteration after iteration on R L R, L R L, R L R: the end-of-episode reset and the
    iteration's reset count as one episode each beam, not two."""
    from hireps_torch.rollout import make_collector

    p = BeamParams()
    B, T = 3, p.decisions_per_episode
    collector = make_collector(
        lambda: BallOnBeamBatchEnv(B, p, seed=1),
        lambda td: td.set("action", torch.zeros(*td.batch_size, 1)),
        frames_per_batch=B * T,
        total_frames=3 * B * T,
        reset_at_each_iter=True,
        seed=1,
    )
    try:
        firsts = [
            torch.sign(batch["state"].reshape(B, T, 3)[:, 0, 0]).tolist() for batch in collector
        ]
    finally:
        collector.shutdown()
    assert firsts == [[1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, -1.0, 1.0]]


def test_commands_beyond_the_limit_are_clipped_and_bad_actions_are_named():
    p = BeamParams()
    s = sample_start(torch.tensor([1.0, -1.0]), p, None)
    far = beam_step(s, f64(3.0, -3.0), p)[0]
    lim = beam_step(s, f64(p.max_angle, -p.max_angle), p)[0]
    assert torch.equal(far, lim)
    with pytest.raises(ValueError, match="non-finite beam angle at index 1"):
        beam_step(s, f64(0.0, math.nan), p)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        beam_step(s, torch.zeros(3, dtype=torch.float64), p)
    with pytest.raises(ValueError, match="state must have shape"):
        beam_step(s[:, :2], f64(0.0, 0.0), p)
    env = BallOnBeamEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([np.nan], dtype=np.float32))
    with pytest.raises(ValueError, match="one beam angle"):
        env.step(np.zeros(2, dtype=np.float32))
    with pytest.raises(ValueError, match="max_angle"):
        BeamParams(max_angle=0.0)


def test_evaluation_tells_a_stabilising_controller_from_a_level_beam():
    p = BeamParams()

    def pd(s):
        goal = torch.where(s[:, 0] > 0, p.goal, -p.goal)
        return 0.3 * (s[:, 0] - goal) + 0.5 * s[:, 1]

    good = evaluate_beam(pd, p, n_episodes=4)
    assert good.success_rate == 1.0 and good.fell_share == 0.0
    assert good.positions.shape == (4, p.decisions_per_episode * p.steps_per_decision)
    level = evaluate_beam(lambda s: torch.zeros(s.shape[0], dtype=torch.float64), p, n_episodes=4)
    assert level.success_rate == 0.0
    assert level.average_return < good.average_return
    tip = evaluate_beam(lambda s: torch.full((s.shape[0],), 0.15, dtype=torch.float64), p)
    assert tip.fell_share == 1.0 and tip.success_rate == 0.0


@pytest.mark.parametrize(
    "make, error, match",
    [
        (lambda: BeamParams(episode_seconds=0.0), ValueError, "episode_seconds must be finite"),
        (lambda: BeamParams(dt=math.inf), ValueError, "dt must be finite and > 0"),
        (lambda: BallOnBeamBatchEnv(0), ValueError, "batch_size must be >= 1"),
        (lambda: evaluate_beam(abs, n_episodes=0), ValueError, "n_episodes must be >= 1"),
        (lambda: evaluate_beam(abs, hold_seconds=math.nan), ValueError, "hold_seconds"),
        (lambda: evaluate_beam(abs, tolerance=0.0), ValueError, "tolerance must be finite"),
        (
            lambda: beam_step(f64([0.1, math.nan, 0.0]), torch.zeros(1), BeamParams()),
            ValueError,
            "state contains non-finite",
        ),
    ],
)
def test_bad_counts_params_and_states_are_named(make, error, match):
    with pytest.raises(error, match=match):
        make()


def _episodes(env, decisions, act):
    """``decisions`` decisions of every system of ``env`` with ``act`` (states -> actions),
    each system restarted where its episode ended (as a TorchRL collector does)."""
    for _ in range(decisions):
        _, term, trunc, _ = env.step(act(env.state))
        if bool((term | trunc).any()):
            env.reset(term | trunc)


def test_members_of_a_population_of_beams_alternate_sides_over_iterations():
    """MemberTasks (a reset at each iteration after the end-of-episode restarts) gives every
    member R L R, then L R L, as its ordinary run's collector."""
    from hireps_torch.envs._common import MemberTasks
    from hireps_torch.envs.ball_on_beam import BeamTask

    p = BeamParams()
    env = MemberTasks([BeamTask(3, p, seed=1), BeamTask(3, p, seed=2)])
    sides = []
    for _ in range(3):
        env.reset()
        sides.append(torch.sign(env.state[:, 0]).reshape(2, 3).tolist())
        _episodes(env, p.decisions_per_episode, lambda s: torch.zeros(s.shape[0]))
    r, l = [1.0, -1.0, 1.0], [-1.0, 1.0, -1.0]
    assert sides == [[r, r], [l, l], [r, r]]


@pytest.mark.parametrize("kind", ["beam", "pendulum"])
def test_a_member_task_steps_as_it_does_alone(kind):
    """Member 1 of MemberTasks draws its starts and restarts from its own task: its systems
    are those of its task alone, bit for bit, whatever the other member does."""
    from hireps_torch.envs._common import MemberTasks
    from hireps_torch.envs.ball_on_beam import BeamTask
    from hireps_torch.envs.pendulum import PendulumParams, PendulumTask

    def task(seed):
        if kind == "beam":
            return BeamTask(3, BeamParams(), seed=seed)
        return PendulumTask(3, PendulumParams(), seed=seed)

    pair, alone = MemberTasks([task(1), task(2)]), MemberTasks([task(2)])
    g = torch.Generator().manual_seed(0)
    for env in (pair, alone):
        env.reset()
    for _ in range(3):
        a = 0.3 * torch.randn(6, generator=g, dtype=torch.float64)
        _episodes(pair, 150, lambda s, a=a: a)
        _episodes(alone, 150, lambda s, a=a: a[3:])
        assert torch.equal(pair.state[3:], alone.state) and torch.equal(pair.t[3:], alone.t)


def test_beam_step_returns_a_state_that_shares_no_memory_with_its_path():
    s = torch.tensor([[0.1, 0.0, 0.0]], dtype=torch.float64)
    nxt, _, _, path = beam_step(s, torch.tensor([0.05], dtype=torch.float64), BeamParams())
    assert torch.equal(nxt, path[:, -1])
    path[:, -1] = 7.0
    assert float(nxt[0, 0]) != 7.0


def test_the_numpy_control_steps_of_the_cpu_equal_the_torch_ones():
    # beam_step runs the control steps in numpy on the CPU and in torch elsewhere: the same
    # arithmetic, so the same numbers (falls included: the start spread reaches the ends)
    from hireps_torch.envs.ball_on_beam import _control_steps

    g = torch.Generator().manual_seed(5)
    scale = torch.tensor([0.98, 0.8, 0.3], dtype=torch.float64)
    s = (2.0 * torch.rand(64, 3, generator=g, dtype=torch.float64) - 1.0) * scale
    a = 0.3 * (2.0 * torch.rand(64, generator=g, dtype=torch.float64) - 1.0)
    p = BeamParams()
    on_torch = _control_steps(s, a, p, torch)
    on_numpy = _control_steps(s.numpy(), a.numpy(), p, np)
    assert bool(on_torch[2].any()) and not bool(on_torch[2].all())
    for t, n in zip(on_torch[:2], on_numpy[:2], strict=True):  # path, reward
        assert torch.allclose(t, torch.from_numpy(n), rtol=1e-12, atol=1e-15)
    assert torch.equal(on_torch[2], torch.from_numpy(on_numpy[2]))
