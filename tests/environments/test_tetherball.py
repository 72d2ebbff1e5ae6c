"""Tetherball: the string's geometry, speed kept while taut, hand-checked flights, classes."""

import math

import gymnasium as gym
import pytest
import torch

from hireps_torch.envs.tetherball import Tetherball, simulate

TASK = Tetherball()


def _fly(task, x0, theta):
    c = torch.tensor([[x0]], dtype=torch.float64)
    t = torch.tensor([theta], dtype=torch.float64)
    return task.flight(c, t, keep_path=True), task(c, t), task.solution_class(c, t)


def test_a_ball_at_rest_stays_where_it_started():
    f, R, k = _fly(TASK, 0.2, [0.0, 0.0])
    assert torch.equal(f.path[-1, 0], torch.tensor([0.2, -0.9], dtype=torch.float64))
    closest = math.hypot(0.2, 1.6)
    assert float(f.closest[0]) == pytest.approx(closest)
    assert float(R[0]) == pytest.approx(-(closest**2)) and int(k[0]) == -1


def test_a_slack_flight_is_straight_and_slowed_by_drag_alone():
    task = Tetherball(drag=0.5)
    f, *_ = _fly(task, 0.0, [0.1, 0.0])  # sideways, slow: the string stays slack
    assert f.free.max() < task.string_length
    travelled = f.path[-1, 0, 0] - f.path[0, 0, 0]
    # sum over steps of dt * v0 * decay^k, k = 1 .. n (the drag applies before each move)
    decay, n = math.exp(-0.5 * task.dt), task.steps
    expected = task.dt * 0.1 * decay * (1 - decay**n) / (1 - decay)
    assert float(travelled) == pytest.approx(expected, rel=1e-12)
    assert torch.all(f.path[:, 0, 1] == -0.9)


def test_the_string_never_exceeds_its_length_and_a_taut_string_keeps_the_speed():
    task = Tetherball(drag=0.0)
    gen = torch.Generator().manual_seed(0)
    theta = (torch.rand(200, 2, generator=gen, dtype=torch.float64) * 2 - 1) * 4
    ctx = (torch.rand(200, 1, generator=gen, dtype=torch.float64) * 2 - 1) * 0.3
    f = task.flight(ctx, theta, keep_path=True)
    assert float(f.free.max()) <= task.string_length + 1e-9
    taut = f.free >= task.string_length - 1e-9
    moving = f.speed > 0
    # from one taut step to the next (no catch between, no pole hit) the speed is unchanged
    both = taut[1:] & taut[:-1] & moving[1:]
    assert int(both.sum()) > 1000  # many taut steps were checked
    torch.testing.assert_close(f.speed[1:][both], f.speed[:-1][both], rtol=1e-12, atol=0)
    # without drag the speed only drops at a catch or when the ball hits the pole
    assert torch.all(f.speed[1:] <= f.speed[:-1] + 1e-12)


def test_a_ball_hitting_the_pole_stops_there():
    f, _, k = _fly(TASK, 0.0, [0.0, 3.0])  # straight at the pole
    assert float(f.speed[-1, 0]) == 0.0
    rest = float(f.path[-1, 0].norm())
    assert rest < TASK.pole_radius + TASK.ball_radius and int(k[0]) == -1


@pytest.mark.parametrize("x0", [-0.3, 0.0, 0.3])
def test_both_sides_reach_the_target_from_every_start(x0):
    """Hit sideways hard enough, the ball swings around the pole on a taut string and passes
    the target: to the right it winds counter-clockwise (class 0), to the left clockwise."""
    for theta, side in (([3.0, 0.5], 0), ([-3.0, 0.5], 1)):
        f, R, k = _fly(TASK, x0, theta)
        assert int(k[0]) == side, (x0, theta, float(f.closest[0]))
        assert (float(f.wound[0]) > 0) == (side == 0)
        assert float(R[0]) > -0.01 - TASK.effort * sum(t * t for t in theta)


def test_the_classes_are_mirror_images_at_the_centre():
    gen = torch.Generator().manual_seed(1)
    theta = (torch.rand(300, 2, generator=gen, dtype=torch.float64) * 2 - 1) * 4
    mirror = theta * torch.tensor([-1.0, 1.0], dtype=torch.float64)
    ctx = torch.zeros(300, 1, dtype=torch.float64)
    k, km = TASK.solution_class(ctx, theta), TASK.solution_class(ctx, mirror)
    swapped = torch.where(k >= 0, 1 - k, k)
    assert float((km == swapped).double().mean()) > 0.98  # but rounding at a class's edge
    assert {0, 1} <= set(k.tolist())


def test_a_population_batch_equals_one_episode_at_a_time():
    gen = torch.Generator().manual_seed(2)
    theta = (torch.rand(2, 4, 2, generator=gen, dtype=torch.float64) * 2 - 1) * 4
    ctx = (torch.rand(2, 4, 1, generator=gen, dtype=torch.float64) * 2 - 1) * 0.3
    R = TASK(ctx, theta)
    assert R.shape == (2, 4)
    one = torch.stack(
        [
            torch.stack([TASK(c[i : i + 1], t[i : i + 1])[0] for i in range(4)])
            for c, t in zip(ctx, theta, strict=True)
        ]
    )
    torch.testing.assert_close(R, one, rtol=0, atol=0)
    start = torch.stack([ctx[0, :, 0], torch.full((4,), -0.9, dtype=torch.float64)], -1)
    assert torch.equal(
        simulate(TASK, start, theta[0]).closest, TASK.flight(ctx[0], theta[0]).closest
    )


def test_contexts_are_drawn_from_the_generator_in_range():
    a = TASK.sample_contexts(500, torch.Generator().manual_seed(3))
    b = TASK.sample_contexts(500, torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and a.shape == (500, 1) and float(a.abs().max()) <= 0.3


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"pole_radius": 0.0}, "pole_radius must be finite and > 0"),
        ({"string_length": 0.7}, "within the string's reach"),
        ({"string_length": 0.6, "pole_radius": 0.1, "start_y": -0.3}, "circumference"),
        ({"target_y": float("nan")}, "target_y must be finite"),
    ],
)
def test_bad_constants_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Tetherball(**kwargs)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match=r"contexts must have shape \(3, 1\), got None"):
        TASK(None, torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"theta must have shape"):
        TASK(torch.zeros(3, 1), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="theta holds non-finite"):
        TASK(torch.zeros(1, 1), torch.tensor([[float("inf"), 0.0]]))


def test_the_gymnasium_env_plays_one_step_episodes():
    from gymnasium.utils.env_checker import check_env

    from hireps_torch.envs import TETHERBALL_ID

    env = gym.make(TETHERBALL_ID).unwrapped
    check_env(env)
    obs, _ = env.reset(seed=5)
    assert obs.shape == (1,) and abs(obs[0]) <= 0.3
    _, reward, terminated, _, info = env.step([3.0, 0.5])
    assert terminated and info["solution_class"] == 0 and reward < 0
