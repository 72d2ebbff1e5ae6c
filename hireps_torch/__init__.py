"""hireps-torch: Hierarchical Relative Entropy Policy Search in PyTorch.

``hireps_torch.load_run(run_dir)`` loads a trained run back."""

from typing import TYPE_CHECKING

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
    solve_episodic_dual,
    solve_time_indexed_dual,
)
from hireps_torch.policies import HierarchicalPolicy, LinearGaussian, SoftmaxGating
from hireps_torch.registration import register_envs

__version__ = "0.1.0"
register_envs()


if TYPE_CHECKING:
    from hireps_torch.experiments.saved import load_run


def __getattr__(name: str) -> object:
    # load_run needs the experiments (torchrl and the tasks): imported when first asked for
    if name == "load_run":
        from hireps_torch.experiments.saved import load_run

        return load_run
    raise AttributeError(f"module 'hireps_torch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), "load_run"})


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
    "TimeIndexedHiREPS",
    "load_run",
    "solve_episodic_dual",
    "solve_time_indexed_dual",
]
