"""Robot hockey with a KUKA iiwa in pybullet (see :mod:`hireps_torch.envs.hockey.env` for the spec).

``import hireps_torch.envs`` registers the gymnasium ids; pybullet and pytorch-kinematics (the
``robot`` extra) are only needed when an environment is created.
"""

from hireps_torch.envs.hockey.aim import (
    AimFeatures,
    aim_angle,
    aim_slopes,
    aimed_shot,
    turn_derivative,
)
from hireps_torch.envs.hockey.env import (
    ENV_ID,
    EPISODIC_ENV_ID,
    RobotHockeyEnv,
    RobotHockeyEpisodicEnv,
    clip_action,
    zone_reward,
)
from hireps_torch.envs.hockey.kinematics import ArmGeometry, ArmKinematics, demonstration
from hireps_torch.envs.hockey.params import HockeyParams
from hireps_torch.envs.hockey.sim import HockeySim, ShotResult, demo_action, shot_dmp

__all__ = [
    "ENV_ID",
    "AimFeatures",
    "EPISODIC_ENV_ID",
    "ArmGeometry",
    "ArmKinematics",
    "HockeyParams",
    "HockeySim",
    "RobotHockeyEnv",
    "RobotHockeyEpisodicEnv",
    "ShotResult",
    "aim_angle",
    "aim_slopes",
    "aimed_shot",
    "clip_action",
    "demo_action",
    "demonstration",
    "shot_dmp",
    "turn_derivative",
    "zone_reward",
]
