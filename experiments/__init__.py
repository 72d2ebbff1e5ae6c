"""The paper's experiments (``hireps_torch.experiments``): one module each with a typed
config, ``algorithm(cfg)`` and ``run(cfg)``, which writes a run directory and returns its
summary. Adding an experiment: ARCHITECTURE.md.
"""

from __future__ import annotations

if __name__ != "hireps_torch.experiments":  # the folder experiments/ is installed so
    raise ImportError(
        f"import the experiments as hireps_torch.experiments, not {__name__!r}: one name, one "
        "copy of each class"
    )

import sys
from collections.abc import Callable
from typing import Any

from hireps_torch.algorithms import Algorithm
from hireps_torch.experiments import ball_on_beam, bimodal, hockey, pendulum

__all__ = ["ALGORITHMS", "EXPERIMENTS", "run_experiment"]

EXPERIMENTS: dict[str, tuple[type, Callable[[Any], dict[str, Any]]]] = {
    "bimodal": (bimodal.BimodalConfig, bimodal.run),
    "pendulum": (pendulum.PendulumConfig, pendulum.run),
    "ball-on-beam": (ball_on_beam.BallOnBeamConfig, ball_on_beam.run),
    "hockey-sequential": (hockey.HockeySequentialConfig, hockey.run),
    "hockey-episodic": (hockey.HockeyEpisodicConfig, hockey.run),
    "hockey-fixed-start": (hockey.HockeyFixedStartConfig, hockey.run),
}

ALGORITHMS: dict[str, Callable[[Any], Algorithm]] = {
    name: sys.modules[run.__module__].algorithm for name, (_, run) in EXPERIMENTS.items()
}
"""Each experiment's config checked and its untrained algorithm built, as ``run`` does,
writing nothing."""


def run_experiment(cfg: Any) -> dict[str, Any]:
    """Run the experiment whose config class ``cfg`` is an instance of (exact class)."""
    for config_cls, run in EXPERIMENTS.values():
        if type(cfg) is config_cls:
            return run(cfg)
    known = ", ".join(cls.__name__ for cls, _ in EXPERIMENTS.values())
    raise TypeError(f"no experiment takes a {type(cfg).__name__}; known configs: {known}")
