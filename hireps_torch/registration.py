"""The tasks' gymnasium ids, registered by ``import hireps_torch``.

Every id has a string entry point: ``gymnasium.make`` imports a task's module
(:mod:`hireps_torch.envs`) only when it creates one, so importing the library stays cheap and
never needs pybullet. ``gymnasium.make("hireps/PendulumSwingUp-v0")`` works after ``import
hireps_torch``; ``gymnasium.make("hireps_torch:hireps/PendulumSwingUp-v0")`` works with nothing
imported first.
"""

from __future__ import annotations

import gymnasium as gym

__all__ = [
    "BALL_ON_BEAM_ID",
    "ENV_IDS",
    "HOCKEY_EPISODIC_ID",
    "HOCKEY_ID",
    "PENDULUM_ID",
    "PLANAR_ARM_ID",
    "TETHERBALL_ID",
    "register_envs",
]

PENDULUM_ID = "hireps/PendulumSwingUp-v0"
BALL_ON_BEAM_ID = "hireps/BallOnBeam-v0"
HOCKEY_ID = "hireps/RobotHockey-v0"
HOCKEY_EPISODIC_ID = "hireps/RobotHockeyEpisodic-v0"
PLANAR_ARM_ID = "hireps/PlanarArm-v0"
TETHERBALL_ID = "hireps/Tetherball-v0"

_ENTRY_POINTS = {
    PENDULUM_ID: "hireps_torch.envs.pendulum:PendulumSwingUpEnv",
    BALL_ON_BEAM_ID: "hireps_torch.envs.ball_on_beam:BallOnBeamEnv",
    HOCKEY_ID: "hireps_torch.envs.hockey.env:RobotHockeyEnv",
    HOCKEY_EPISODIC_ID: "hireps_torch.envs.hockey.env:RobotHockeyEpisodicEnv",
    PLANAR_ARM_ID: "hireps_torch.envs.planar_arm:PlanarArmEnv",
    TETHERBALL_ID: "hireps_torch.envs.tetherball:TetherballEnv",
}
ENV_IDS: tuple[str, ...] = tuple(_ENTRY_POINTS)


def register_envs() -> None:
    """Register the ids not registered yet (a re-import or reload does not register twice)."""
    for env_id, entry_point in _ENTRY_POINTS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, disable_env_checker=True)
