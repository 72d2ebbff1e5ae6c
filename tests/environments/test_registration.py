"""gymnasium ids: ``import environments`` registers every id once, cheaply."""

import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import pytest

import environments


def test_every_id_is_registered_once_with_a_string_entry_point():
    assert set(environments.ENV_IDS) == {
        "hireps/PendulumSwingUp-v0",
        "hireps/BallOnBeam-v0",
        "hireps/RobotHockey-v0",
        "hireps/RobotHockeyEpisodic-v0",
    }
    for env_id in environments.ENV_IDS:
        spec = gym.spec(env_id)
        assert isinstance(spec.entry_point, str) and spec.entry_point.startswith("environments.")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is overridden
        importlib.reload(environments)
    assert sum(k.startswith("hireps/") for k in gym.registry) == 4


@pytest.mark.parametrize(
    "env_id, obs_shape",
    [(environments.PENDULUM_ID, (2,)), (environments.BALL_ON_BEAM_ID, (3,))],
)
def test_gym_make_builds_the_torch_tasks(env_id, obs_shape):
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    assert obs.shape == obs_shape
    env.action_space.seed(0)
    obs, reward, *_ = env.step(env.action_space.sample())
    assert obs.shape == obs_shape and isinstance(reward, float)
    env.close()


def test_import_registers_without_pybullet():
    code = (
        "import sys, gymnasium as gym, environments; "
        "assert 'pybullet' not in sys.modules and 'pytorch_kinematics' not in sys.modules; "
        "assert all(i in gym.registry for i in environments.ENV_IDS)"
    )
    root = Path(__file__).resolve().parents[2]
    subprocess.run([sys.executable, "-W", "error::UserWarning", "-c", code], check=True, cwd=root)
