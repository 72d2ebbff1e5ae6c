"""The paper's experiments (``hireps_torch.experiments``): one module each with a typed
config, ``algorithm(cfg)``, ``run(cfg)`` (its loop in view; it writes a run directory and
returns its summary) and its registry entry. Adding an experiment: ARCHITECTURE.md.
"""

from __future__ import annotations

if __name__ != "hireps_torch.experiments":  # the folder experiments/ is installed so
    raise ImportError(
        f"import the experiments as hireps_torch.experiments, not {__name__!r}: one name, one "
        "copy of each class"
    )

from typing import Any

from hireps_torch.experiments import ball_on_beam, bimodal, hockey, pendulum, solutions
from hireps_torch.experiments.runner import Experiment

__all__ = ["EXPERIMENTS", "Experiment", "run_experiment"]

EXPERIMENTS: dict[str, Experiment] = {
    e.name: e
    for e in (
        bimodal.EXPERIMENT,
        pendulum.EXPERIMENT,
        ball_on_beam.EXPERIMENT,
        *hockey.VARIANTS,
        *solutions.EXPERIMENTS,
    )
}
"""The registry: command-line name -> :class:`Experiment` (config class, ``run``,
``algorithm``, summary metric, curve column)."""


def run_experiment(cfg: Any) -> dict[str, Any]:
    """Run the experiment whose config class ``cfg`` is an instance of (exact class)."""
    for entry in EXPERIMENTS.values():
        if type(cfg) is entry.config:
            return entry.run(cfg)
    known = ", ".join(e.config.__name__ for e in EXPERIMENTS.values())
    raise TypeError(f"no experiment takes a {type(cfg).__name__}; known configs: {known}")
