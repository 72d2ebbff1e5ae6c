"""Run the paper's experiments: ``python train.py <experiment> [--options]``.

The experiments live in :mod:`experiments` (one module each); this file is the command line
only. ``python train.py <experiment> --help`` lists an experiment's options. Every run writes
a run directory (default ``runs/<experiment>/<timestamp>``, ``--run-dir`` overrides) with
``config.json``, ``metrics.csv`` (one row per iteration), ``checkpoint.pt`` (after every
iteration and on Ctrl-C), ``learning_curve.png`` and, when it finished, ``summary.json``.
``python train.py <experiment> --resume RUN_DIR`` continues an interrupted run exactly.
``python train.py sweep --experiment E --seeds 0-4 --grid OPTION=V1,V2 [--backend ray]`` runs
a grid of configurations x seeds (see :mod:`experiments.sweep`); run it again to finish an
interrupted sweep.
"""

from __future__ import annotations

import os
import sys

if any("hockey-" in arg for arg in sys.argv[1:]):  # before torch: see experiments.workers
    os.environ.setdefault("MKL_CBWR", "COMPATIBLE")

import json  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import tyro  # noqa: E402

from experiments import EXPERIMENTS, run_experiment  # noqa: E402
from experiments.checkpoint import RunFinished, saved_config  # noqa: E402
from experiments.sweep import SweepConfig  # noqa: E402
from experiments.sweep import main as run_sweep  # noqa: E402


def _resume_dir(argv: list[str]) -> Path | None:
    for i, arg in enumerate(argv):
        if arg.startswith("--resume="):
            return Path(arg.split("=", 1)[1])
        if arg == "--resume" and i + 1 < len(argv):
            return Path(argv[i + 1])
    return None


def parse(argv: list[str]) -> Any:
    """The config of the chosen experiment; with ``--resume RUN_DIR`` the run's saved
    options are the defaults (options given again must agree with them)."""
    resume = _resume_dir(argv)
    if argv and argv[0] in EXPERIMENTS and resume is not None:
        config_cls = EXPERIMENTS[argv[0]][0]
        default = saved_config(config_cls, argv[0], resume)
        return tyro.cli(config_cls, default=default, args=argv[1:], description=__doc__)
    commands: dict[str, Callable[..., Any]] = {name: c for name, (c, _) in EXPERIMENTS.items()}
    commands["sweep"] = SweepConfig
    return tyro.extras.subcommand_cli_from_dict(commands, args=argv, description=__doc__)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Parse the command line, run the chosen experiment, print its summary."""
    cfg = parse(sys.argv[1:] if argv is None else argv)
    summary = run_sweep(cfg) if isinstance(cfg, SweepConfig) else run_experiment(cfg)
    print(json.dumps({k: v for k, v in summary.items() if k != "options"}, indent=2))
    return summary


if __name__ == "__main__":
    try:
        main()
    except RunFinished as done:
        print(done, file=sys.stderr)
    except KeyboardInterrupt as stop:  # RunInterrupted: the checkpoint is written
        print(f"\ninterrupted: {stop}", file=sys.stderr)
        raise SystemExit(130) from None
    except (ValueError, TypeError, OSError, ImportError) as exc:  # OSError: FileExistsError,
        print(f"error: {exc}", file=sys.stderr)  # a --run-dir that cannot be written
        raise SystemExit(2) from None
