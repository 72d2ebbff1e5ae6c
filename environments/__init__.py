"""The tasks: toy multimodal objectives, the pendulum swing-up and the ball on a beam (hockey
next)."""

from environments.ball_on_beam import BallOnBeamBatchEnv, BallOnBeamEnv, BeamParams
from environments.pendulum import PendulumParams, PendulumSwingUpBatchEnv, PendulumSwingUpEnv
from environments.toy import ContextualTwoGaussians, TwoGaussians

__all__ = [
    "BallOnBeamBatchEnv",
    "BallOnBeamEnv",
    "BeamParams",
    "ContextualTwoGaussians",
    "PendulumParams",
    "PendulumSwingUpBatchEnv",
    "PendulumSwingUpEnv",
    "TwoGaussians",
]
