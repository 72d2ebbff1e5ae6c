"""HiREPS algorithms: weights from the dual, then the policy's weighted refit."""

from hireps_torch.algorithms.episodic import REPS, EpisodicHiREPS
from hireps_torch.algorithms.infinite_horizon import InfiniteHorizonHiREPS
from hireps_torch.algorithms.time_indexed import TimeIndexedHiREPS

__all__ = ["REPS", "EpisodicHiREPS", "InfiniteHorizonHiREPS", "TimeIndexedHiREPS"]
