"""The tasks, installed as ``hireps_torch.envs``: toy multimodal objectives, the four-goal
planar arm, tetherball, the pendulum swing-up, the ball on a beam and robot hockey (pybullet;
needs the ``robot`` extra only when a hockey env is created).

``import hireps_torch`` registers every task's gymnasium id (:data:`ENV_IDS`), once, with
string entry points (:mod:`hireps_torch.registration`).
"""

if __name__ != "hireps_torch.envs":  # the folder environments/ is installed under that name
    raise ImportError(
        f"import the tasks as hireps_torch.envs, not {__name__!r}: one name, one copy of each class"
    )

from hireps_torch.envs.ball_on_beam import BallOnBeamBatchEnv, BallOnBeamEnv, BeamParams
from hireps_torch.envs.hockey import RobotHockeyEnv, RobotHockeyEpisodicEnv
from hireps_torch.envs.pendulum import PendulumParams, PendulumSwingUpBatchEnv, PendulumSwingUpEnv
from hireps_torch.envs.planar_arm import PlanarArm, PlanarArmEnv
from hireps_torch.envs.tetherball import Tetherball, TetherballEnv
from hireps_torch.envs.toy import ContextualTwoGaussians, TwoGaussians
from hireps_torch.registration import (
    BALL_ON_BEAM_ID,
    ENV_IDS,
    HOCKEY_EPISODIC_ID,
    HOCKEY_ID,
    PENDULUM_ID,
    PLANAR_ARM_ID,
    TETHERBALL_ID,
)

__all__ = [
    "BALL_ON_BEAM_ID",
    "ENV_IDS",
    "HOCKEY_EPISODIC_ID",
    "HOCKEY_ID",
    "PENDULUM_ID",
    "PLANAR_ARM_ID",
    "TETHERBALL_ID",
    "BallOnBeamBatchEnv",
    "BallOnBeamEnv",
    "BeamParams",
    "ContextualTwoGaussians",
    "PendulumParams",
    "RobotHockeyEnv",
    "RobotHockeyEpisodicEnv",
    "PendulumSwingUpBatchEnv",
    "PendulumSwingUpEnv",
    "PlanarArm",
    "PlanarArmEnv",
    "Tetherball",
    "TetherballEnv",
    "TwoGaussians",
]
