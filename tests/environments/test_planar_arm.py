"""The four-goal planar arm: hand-checked postures, the four goals equally good, batches."""

import math

import gymnasium as gym
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from hireps_torch.envs import PLANAR_ARM_ID, PlanarArm
from hireps_torch.envs.planar_arm import end_effector


def _bend_reaching(distance: float) -> float:
    """The equal bend a of joints 2-10 whose arc of 10 unit links spans ``distance``."""
    lo, hi = 1e-6, 0.6  # sin(5a) / sin(a / 2) falls from 10 to below 7 on this interval
    for _ in range(200):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if math.sin(5 * mid) / math.sin(mid / 2) > distance else (lo, mid)
    return lo


def _posture(goal: int) -> torch.Tensor:
    """Joints reaching goal ``goal``: equal bends, the base turned to put the tip on it."""
    a = _bend_reaching(7.0)
    theta = torch.full((10,), a, dtype=torch.float64)
    theta[0] = -4.5 * a + goal * math.pi / 2  # the chord points at the base angle + 4.5 a
    return theta


def test_a_straight_arm_reaches_ten_along_x_and_no_goal():
    task = PlanarArm()
    theta = torch.zeros(1, 10, dtype=torch.float64)
    assert end_effector(theta).tolist() == [[10.0, 0.0]]
    assert task(None, theta).tolist() == [-9.0]  # 3 m from (7, 0), no posture cost
    assert task.solution_class(None, theta).tolist() == [-1]


def test_each_goal_is_reached_by_a_turned_base_at_the_same_reward():
    task = PlanarArm()
    theta = torch.stack([_posture(k) for k in range(4)])
    tips = end_effector(theta)
    torch.testing.assert_close(tips, task.goals(), atol=1e-9, rtol=0)
    assert task.solution_class(None, theta).tolist() == [0, 1, 2, 3]
    rewards = task(None, theta)
    cost = 0.01 * 9 * _bend_reaching(7.0) ** 2  # the posture cost alone: the tip is on the goal
    torch.testing.assert_close(rewards, torch.full((4,), -cost, dtype=torch.float64))


def test_the_tolerance_bounds_a_class():
    task = PlanarArm(tolerance=0.5)
    near, far = _posture(2).clone(), _posture(2).clone()
    near[0] += 0.49 / 7  # the tip moves about 0.49 m along the goal's circle
    far[0] += 0.52 / 7
    assert task.solution_class(None, torch.stack([near, far])).tolist() == [2, -1]


def test_a_population_batch_equals_one_sample_at_a_time():
    task = PlanarArm()
    theta = torch.randn(3, 5, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    batched = task(None, theta)
    one = torch.stack([torch.stack([task(None, t[None])[0] for t in member]) for member in theta])
    assert batched.shape == (3, 5)
    torch.testing.assert_close(batched, one, rtol=1e-12, atol=0)
    assert task.solution_class(None, theta).shape == (3, 5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_links": 1}, "n_links must be an integer >= 2, got 1"),
        ({"goal_distance": 10.0}, "below the arm's reach 10, got 10.0"),
        ({"posture_cost": -1.0}, "posture_cost must be finite and >= 0"),
        ({"tolerance": 0.0}, "tolerance must be finite and > 0"),
    ],
)
def test_bad_constants_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PlanarArm(**kwargs)


def test_bad_parameters_are_named():
    task = PlanarArm()
    with pytest.raises(ValueError, match=r"theta must have shape \(\[S,\] N, 10\), got \(4, 3\)"):
        task(None, torch.zeros(4, 3))
    with pytest.raises(ValueError, match="non-finite"):
        task(None, torch.full((1, 10), float("nan")))


def test_the_gymnasium_env_plays_one_step_episodes():
    env = gym.make(PLANAR_ARM_ID).unwrapped
    check_env(env)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (0,)
    obs, reward, terminated, truncated, info = env.step(_posture(1).numpy())
    assert terminated and not truncated and info["solution_class"] == 1
    assert reward == pytest.approx(-0.01 * 9 * _bend_reaching(7.0) ** 2)
    with pytest.raises(gym.error.ResetNeeded):
        env.step(_posture(1).numpy())
