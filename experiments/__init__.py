"""The paper's experiments, one module each: a typed config, its builders and its ``run``.

``EXPERIMENTS`` maps each command-line name to ``(Config, run)``; ``train.py`` turns it into
tyro subcommands. Every ``run(cfg)`` writes one run directory (see :mod:`experiments.rundir`)
(one seed, or a population of seeds: see :class:`experiments.loop.Members`) and returns
the summary it wrote to ``summary.json``. To add an experiment, copy the module
closest to it (``bimodal.py`` for an ask/tell objective, ``ball_on_beam.py`` for a batched
TorchRL environment, ``hockey.py`` for a gymnasium environment with whole episodes) and add
one line here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from experiments import ball_on_beam, bimodal, hockey, pendulum

__all__ = ["CHECKS", "EXPERIMENTS", "run_experiment"]

EXPERIMENTS: dict[str, tuple[type, Callable[[Any], dict[str, Any]]]] = {
    "bimodal": (bimodal.BimodalConfig, bimodal.run),
    "pendulum": (pendulum.PendulumConfig, pendulum.run),
    "ball-on-beam": (ball_on_beam.BallOnBeamConfig, ball_on_beam.run),
    "hockey-sequential": (hockey.HockeySequentialConfig, hockey.run),
    "hockey-episodic": (hockey.HockeyEpisodicConfig, hockey.run),
    "hockey-fixed-start": (hockey.HockeyFixedStartConfig, hockey.run),
}

CHECKS: dict[str, Callable[[Any], None]] = {
    "bimodal": bimodal.check,
    "pendulum": pendulum.check,
    "ball-on-beam": ball_on_beam.check,
    "hockey-sequential": hockey.check,
    "hockey-episodic": hockey.check,
    "hockey-fixed-start": hockey.check,
}
"""Each experiment's check of a config: what its ``run`` refuses, refused without a run
(a sweep checks every configuration before its first run)."""


def run_experiment(cfg: Any) -> dict[str, Any]:
    """Run the experiment whose config class ``cfg`` is an instance of (exact class)."""
    for config_cls, run in EXPERIMENTS.values():
        if type(cfg) is config_cls:
            return run(cfg)
    known = ", ".join(cls.__name__ for cls, _ in EXPERIMENTS.values())
    raise TypeError(f"no experiment takes a {type(cfg).__name__}; known configs: {known}")
