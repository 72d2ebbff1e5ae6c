"""Run the paper's experiments: ``python train.py <experiment> [--options]``.

The experiments live in :mod:`experiments` (one module each); this file is the command line
only. ``python train.py <experiment> --help`` lists an experiment's options. Every run writes
a run directory (default ``runs/<experiment>/<timestamp>``, ``--run-dir`` overrides) with
``config.json``, ``metrics.csv`` (one row per iteration), ``checkpoint.pt``,
``learning_curve.png`` and, when it finished, ``summary.json``. ``--logger tensorboard`` or
``--logger wandb`` also sends every row to that TorchRL logger.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from typing import Any

import tyro

from experiments import EXPERIMENTS, run_experiment


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Parse the command line, run the chosen experiment, print its summary."""
    argv = sys.argv[1:] if argv is None else argv
    defaults: dict[str, Callable[..., Any]] = {name: cls for name, (cls, _) in EXPERIMENTS.items()}
    cfg = tyro.extras.subcommand_cli_from_dict(defaults, args=argv, description=__doc__)
    summary = run_experiment(cfg)
    print(json.dumps({k: v for k, v in summary.items() if k != "options"}, indent=2))
    return summary


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileExistsError, ImportError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
