"""HiREPS algorithms: weights from the dual, then the policy's weighted refit."""

from hireps_torch.algorithms.episodic import REPS, EpisodicHiREPS

__all__ = ["REPS", "EpisodicHiREPS"]
