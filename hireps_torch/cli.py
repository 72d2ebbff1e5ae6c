"""Run the paper's experiments: hireps-train <experiment> [--options].

- In the repository: python train.py <experiment> [--options].
- hireps-train <experiment> --help lists an experiment's options.
- A run writes config.json, metrics.csv (a row per iteration), checkpoint.pt (after every
  iteration and on Ctrl-C / SIGTERM), learning_curve.png and, once finished, summary.json.
- Its directory: --run-dir, by default runs/<experiment>/<timestamp>.
- hireps-train <experiment> --resume RUN_DIR continues an interrupted run exactly.
- hireps-train sweep --experiment E --seeds 0-4 --grid OPTION=V1,V2 runs a grid of
  configurations x seeds; run it again to finish an interrupted sweep.

The experiments are the modules of hireps_torch.experiments, to call from Python too.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["entry", "main", "parse"]


def _resume_dir(argv: list[str]) -> Path | None:
    for i, arg in enumerate(argv):
        if arg.startswith("--resume="):
            return Path(arg.split("=", 1)[1])
        if arg == "--resume" and i + 1 < len(argv):
            return Path(argv[i + 1])
    return None


def parse(argv: list[str]) -> Any:
    """The chosen experiment's config; ``--resume RUN_DIR``: the saved options as defaults."""
    import tyro

    from hireps_torch.experiments import EXPERIMENTS
    from hireps_torch.experiments.checkpoint import saved_config
    from hireps_torch.experiments.sweep import SweepConfig

    resume = _resume_dir(argv)
    if argv and argv[0] in EXPERIMENTS and resume is not None:
        config_cls = EXPERIMENTS[argv[0]].config
        default = saved_config(config_cls, argv[0], resume)
        return tyro.cli(config_cls, default=default, args=argv[1:], description=__doc__)
    commands: dict[str, Callable[..., Any]] = {name: e.config for name, e in EXPERIMENTS.items()}
    commands["sweep"] = SweepConfig
    return tyro.extras.subcommand_cli_from_dict(commands, args=argv, description=__doc__)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Parse the command line, run the chosen experiment, print its summary."""
    argv = sys.argv[1:] if argv is None else argv
    from hireps_torch.experiments import run_experiment
    from hireps_torch.experiments.sweep import SweepConfig
    from hireps_torch.experiments.sweep import main as run_sweep

    cfg = parse(argv)
    summary = run_sweep(cfg) if isinstance(cfg, SweepConfig) else run_experiment(cfg)
    print(json.dumps({k: v for k, v in summary.items() if k != "options"}, indent=2))
    return summary


def entry() -> None:
    """``hireps-train``: :func:`main` in ``MKL_CBWR=COMPATIBLE`` (unless set; as its worker
    processes compute) and with exit codes (130 on Ctrl-C, 143 on SIGTERM, 2 on bad options or
    an unwritable run directory, 1 when memory runs out)."""
    os.environ.setdefault("MKL_CBWR", "COMPATIBLE")  # before MKL's first call (pool.MKL_MODE)
    try:  # the imports too: Ctrl-C while they load is an interrupt like any other
        from hireps_torch.experiments.checkpoint import RunFinished

        try:
            main()
        except RunFinished as done:
            print(done, file=sys.stderr)
    except KeyboardInterrupt as stop:  # RunInterrupted: the checkpoint is written
        while not str(stop) and isinstance(stop.__context__, KeyboardInterrupt):  # a Ctrl-C in
            stop = stop.__context__  # the clean-up after the first: tell what the first did
        print(f"\ninterrupted: {stop}" if str(stop) else "\ninterrupted", file=sys.stderr)
        raise SystemExit(143 if getattr(stop, "signame", None) == "SIGTERM" else 130) from None
    except (ValueError, TypeError, OSError, ImportError) as exc:  # OSError: FileExistsError,
        print(f"error: {exc}", file=sys.stderr)  # a --run-dir that cannot be written
        raise SystemExit(2) from None
    except (MemoryError, RuntimeError) as exc:
        if isinstance(exc, RuntimeError) and "allocate" not in str(exc):
            raise
        print(
            f"error: out of memory ({exc}): fewer --episodes-per-iteration or seeds need less",
            file=sys.stderr,
        )
        raise SystemExit(1) from None
