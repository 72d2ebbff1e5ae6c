"""HiREPS algorithms: weights from the dual, then the policy's weighted refit.

Every variant implements :class:`Algorithm` (``sample`` / ``mean_action`` / ``learn`` from an
:class:`Experience` / ``state_dict``), so one loop or checkpoint handles them all.
"""

from typing import TYPE_CHECKING

from hireps_torch.algorithms.base import Algorithm, Experience
from hireps_torch.algorithms.cmaes import CMAES
from hireps_torch.algorithms.episodic import REPS, EpisodicHiREPS
from hireps_torch.algorithms.infinite_horizon import InfiniteHorizonHiREPS
from hireps_torch.algorithms.time_indexed import TimeIndexedHiREPS

__all__ = [
    "CMAES",
    "REPS",
    "Algorithm",
    "EpisodicHiREPS",
    "Experience",
    "InfiniteHorizonHiREPS",
    "TimeIndexedHiREPS",
]

if TYPE_CHECKING:  # mypy checks that every variant implements the interface

    def _implements(
        a: EpisodicHiREPS, b: TimeIndexedHiREPS, c: InfiniteHorizonHiREPS, d: CMAES
    ) -> list[Algorithm]:
        return [a, b, c, d]
