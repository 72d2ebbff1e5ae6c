"""The tasks: toy multimodal objectives, the pendulum swing-up, the ball on a beam and robot
hockey (pybullet; needs the ``robot`` extra only when a hockey env is created)."""

from environments.ball_on_beam import BallOnBeamBatchEnv, BallOnBeamEnv, BeamParams
from environments.hockey import RobotHockeyEnv, RobotHockeyEpisodicEnv
from environments.pendulum import PendulumParams, PendulumSwingUpBatchEnv, PendulumSwingUpEnv
from environments.toy import ContextualTwoGaussians, TwoGaussians

__all__ = [
    "BallOnBeamBatchEnv",
    "BallOnBeamEnv",
    "BeamParams",
    "ContextualTwoGaussians",
    "PendulumParams",
    "RobotHockeyEnv",
    "RobotHockeyEpisodicEnv",
    "PendulumSwingUpBatchEnv",
    "PendulumSwingUpEnv",
    "TwoGaussians",
]
