"""The paper's experiments, installed as ``hireps_torch.experiments``, one module each: a
typed config, its builders and its ``run``.

``EXPERIMENTS`` maps each command-line name to ``(Config, run)``; :mod:`hireps_torch.cli`
turns it into tyro subcommands. Every ``run(cfg)`` writes one run directory (see
:mod:`hireps_torch.experiments.rundir`) (one seed, or a population of seeds: see
:class:`hireps_torch.experiments.loop.Members`) and returns the summary it wrote to
``summary.json``. To add an experiment, copy the module closest to it (``bimodal.py`` for
an ask/tell objective, ``ball_on_beam.py`` for a batched TorchRL environment, ``hockey.py``
for a gymnasium environment with whole episodes) and name it in :data:`EXPERIMENTS`,
:data:`ALGORITHMS` and the sweeps' ``METRICS`` (:mod:`hireps_torch.experiments.sweep`).
"""

from __future__ import annotations

if __name__ != "hireps_torch.experiments":  # the folder experiments/ is installed so
    raise ImportError(
        f"import the experiments as hireps_torch.experiments, not {__name__!r}: one name, one "
        "copy of each class"
    )

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
    "bimodal": bimodal.algorithm,
    "pendulum": pendulum.algorithm,
    "ball-on-beam": ball_on_beam.algorithm,
    "hockey-sequential": hockey.algorithm,
    "hockey-episodic": hockey.algorithm,
    "hockey-fixed-start": hockey.algorithm,
}
"""Each experiment's config checked and its untrained algorithm built, as its ``run`` does,
without a run directory (sweeps check every run's config before the first starts;
:func:`~hireps_torch.experiments.saved.load_run` loads a run's state into it)."""


def run_experiment(cfg: Any) -> dict[str, Any]:
    """Run the experiment whose config class ``cfg`` is an instance of (exact class)."""
    for config_cls, run in EXPERIMENTS.values():
        if type(cfg) is config_cls:
            return run(cfg)
    known = ", ".join(cls.__name__ for cls, _ in EXPERIMENTS.values())
    raise TypeError(f"no experiment takes a {type(cfg).__name__}; known configs: {known}")
