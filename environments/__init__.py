"""The tasks: toy multimodal objectives and the pendulum swing-up (ball on a beam, hockey next)."""

from environments.pendulum import PendulumParams, PendulumSwingUpBatchEnv, PendulumSwingUpEnv
from environments.toy import ContextualTwoGaussians, TwoGaussians

__all__ = [
    "ContextualTwoGaussians",
    "PendulumParams",
    "PendulumSwingUpBatchEnv",
    "PendulumSwingUpEnv",
    "TwoGaussians",
]
