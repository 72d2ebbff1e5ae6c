"""hireps-torch: Hierarchical Relative Entropy Policy Search in PyTorch.

``hireps_torch.load_run(run_dir)`` loads a trained run back."""

import importlib
import importlib.util
from typing import TYPE_CHECKING

from hireps_torch.registration import register_envs

__version__ = "0.1.0"
register_envs()

_HOME = {
    "hireps_torch.algorithms": (
        "REPS",
        "Algorithm",
        "EpisodicHiREPS",
        "Experience",
        "InfiniteHorizonHiREPS",
        "TimeIndexedHiREPS",
    ),
    "hireps_torch.dmp": ("DMP", "DMPTrajectory"),
    "hireps_torch.dual": (
        "DegenerateWeightsWarning",
        "DualSolution",
        "solve_episodic_dual",
        "solve_infinite_horizon_dual",
        "solve_time_indexed_dual",
    ),
    "hireps_torch.policies": ("HierarchicalPolicy", "LinearGaussian", "SoftmaxGating"),
    "hireps_torch.experiments.saved": ("load_run",),
}
_MODULE = {name: module for module, names in _HOME.items() for name in names}

if TYPE_CHECKING:
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
        solve_infinite_horizon_dual,
        solve_time_indexed_dual,
    )
    from hireps_torch.experiments.saved import load_run
    from hireps_torch.policies import HierarchicalPolicy, LinearGaussian, SoftmaxGating


def __getattr__(name: str) -> object:
    # imported when first asked for: ``import hireps_torch`` (and the command line's first
    # second) needs no torch
    if name in _MODULE:
        return getattr(importlib.import_module(_MODULE[name]), name)
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")  # a subpackage: hireps_torch.dual
    raise AttributeError(f"module 'hireps_torch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_MODULE})


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
    "solve_infinite_horizon_dual",
    "solve_time_indexed_dual",
]
