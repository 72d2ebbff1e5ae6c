"""gymnasium ids: ``import hireps_torch`` registers every id once, cheaply."""

import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import pytest

from hireps_torch import envs, registration

ROOT = Path(__file__).resolve().parents[2]


def test_every_id_is_registered_once_with_a_string_entry_point():
    assert set(envs.ENV_IDS) == {
        "hireps/PendulumSwingUp-v0",
        "hireps/BallOnBeam-v0",
        "hireps/RobotHockey-v0",
        "hireps/RobotHockeyEpisodic-v0",
        "hireps/PlanarArm-v0",
        "hireps/Tetherball-v0",
    }
    for env_id in envs.ENV_IDS:
        spec = gym.spec(env_id)
        assert isinstance(spec.entry_point, str)
        assert spec.entry_point.startswith("hireps_torch.envs.")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is overridden
        importlib.reload(registration).register_envs()
    assert sum(k.startswith("hireps/") for k in gym.registry) == len(envs.ENV_IDS)


@pytest.mark.parametrize(
    "env_id, obs_shape",
    [
        (envs.PENDULUM_ID, (2,)),
        (envs.BALL_ON_BEAM_ID, (3,)),
        (envs.PLANAR_ARM_ID, (0,)),
        (envs.TETHERBALL_ID, (1,)),
    ],
)
def test_gym_make_builds_the_torch_tasks(env_id, obs_shape):
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    assert obs.shape == obs_shape
    env.action_space.seed(0)
    obs, reward, *_ = env.step(env.action_space.sample())
    assert obs.shape == obs_shape and isinstance(reward, float)
    env.close()


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-W", "error::UserWarning", "-c", code],
        cwd=cwd,
        capture_output=True,
        text=True,
    )


def test_importing_the_library_registers_the_ids_without_importing_the_tasks(tmp_path):
    code = (
        "import sys, gymnasium as gym, hireps_torch; "
        "assert 'hireps_torch.envs' not in sys.modules and 'pybullet' not in sys.modules; "
        "assert all(i in gym.registry for i in hireps_torch.registration.ENV_IDS)"
    )
    done = _python(code, tmp_path)
    assert done.returncode == 0, done.stderr


def test_the_module_form_of_an_id_works_with_nothing_imported(tmp_path):
    code = (
        "import gymnasium as gym; "
        "env = gym.make('hireps_torch:hireps/PendulumSwingUp-v0'); "
        "assert env.reset(seed=0)[0].shape == (2,)"
    )
    done = _python(code, tmp_path)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(
    "folder, name",
    [("environments", "hireps_torch.envs"), ("experiments", "hireps_torch.experiments")],
)
def test_a_folder_imported_under_its_own_name_is_refused_with_the_installed_name(folder, name):
    """From the repository root the folders are importable by their own names; that would
    load a second copy of every class (and register nothing twice only by luck)."""
    done = _python(f"import {folder}", ROOT)
    assert done.returncode != 0
    assert f"import the {'tasks' if folder == 'environments' else 'experiments'} as {name}" in (
        done.stderr
    )
