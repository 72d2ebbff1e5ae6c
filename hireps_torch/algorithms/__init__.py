"""HiREPS algorithms: weights from the dual, then the policy's weighted refit."""

from hireps_torch.algorithms.episodic import REPS, EpisodicHiREPS
from hireps_torch.algorithms.infinite_horizon import InfiniteHorizonHiREPS

__all__ = ["REPS", "EpisodicHiREPS", "InfiniteHorizonHiREPS"]
