"""hireps-torch: Hierarchical Relative Entropy Policy Search in PyTorch."""

from hireps_torch.algorithms import (
    REPS,
    Algorithm,
    EpisodicHiREPS,
    Experience,
    InfiniteHorizonHiREPS,
    TimeIndexedHiREPS,
)
from hireps_torch.dmp import DMP, DMPTrajectory
from hireps_torch.dual import (
    DegenerateWeightsWarning,
    DualSolution,
    TimeIndexedDualSolution,
    solve_episodic_dual,
    solve_time_indexed_dual,
)
from hireps_torch.policies import HierarchicalPolicy, LinearGaussian, SoftmaxGating

__version__ = "0.1.0"
__all__ = [
    "DMP",
    "REPS",
    "Algorithm",
    "DMPTrajectory",
    "DegenerateWeightsWarning",
    "DualSolution",
    "EpisodicHiREPS",
    "Experience",
    "HierarchicalPolicy",
    "InfiniteHorizonHiREPS",
    "LinearGaussian",
    "SoftmaxGating",
    "TimeIndexedDualSolution",
    "TimeIndexedHiREPS",
    "solve_episodic_dual",
    "solve_time_indexed_dual",
]
