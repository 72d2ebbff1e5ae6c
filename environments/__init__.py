"""The tasks: toy multimodal objectives, the pendulum swing-up, the ball on a beam and robot
hockey (pybullet; needs the ``robot`` extra only when a hockey env is created).

Importing this package registers every task's gymnasium id (:data:`ENV_IDS`), once, with
string entry points: ``gym.make`` imports an environment's module only when it creates one.
"""

import gymnasium as gym

from environments.ball_on_beam import ENV_ID as BALL_ON_BEAM_ID
from environments.ball_on_beam import BallOnBeamBatchEnv, BallOnBeamEnv, BeamParams
from environments.hockey import ENV_ID as HOCKEY_ID
from environments.hockey import EPISODIC_ENV_ID as HOCKEY_EPISODIC_ID
from environments.hockey import RobotHockeyEnv, RobotHockeyEpisodicEnv
from environments.pendulum import ENV_ID as PENDULUM_ID
from environments.pendulum import PendulumParams, PendulumSwingUpBatchEnv, PendulumSwingUpEnv
from environments.toy import ContextualTwoGaussians, TwoGaussians

__all__ = [
    "BALL_ON_BEAM_ID",
    "ENV_IDS",
    "HOCKEY_EPISODIC_ID",
    "HOCKEY_ID",
    "PENDULUM_ID",
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

# id -> entry point of every gymnasium environment of the package
_ENTRY_POINTS = {
    PENDULUM_ID: "environments.pendulum:PendulumSwingUpEnv",
    BALL_ON_BEAM_ID: "environments.ball_on_beam:BallOnBeamEnv",
    HOCKEY_ID: "environments.hockey.env:RobotHockeyEnv",
    HOCKEY_EPISODIC_ID: "environments.hockey.env:RobotHockeyEpisodicEnv",
}
ENV_IDS: tuple[str, ...] = tuple(_ENTRY_POINTS)


def _register() -> None:
    """Register the ids not registered yet (a re-import or reload does not register twice)."""
    for env_id, entry_point in _ENTRY_POINTS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, disable_env_checker=True)


_register()
