"""The options every experiment shares (a base of every experiment's config dataclass)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.rundir import LoggerName, jsonable

__all__ = ["RunOptions", "check_options", "config_dict"]


@dataclass(frozen=True)
class RunOptions:
    """Options of the run itself rather than of the experiment."""

    seed: int = 0
    """Seed of every random generator of the run (same seed, same run)."""
    run_dir: Path | None = None
    """Where to write the run (default runs/<experiment>/<timestamp>); must not exist or be
    empty."""
    resume: Path | None = None
    """Continue the interrupted run in this directory (its config.json gives the options;
    options given again must agree). A finished run is reported, not rerun."""
    checkpoint_every: int = 1
    """Write checkpoint.pt after every this many iterations (and on SIGINT/SIGTERM)."""
    progress: bool = True
    """Show a progress bar."""
    logger: LoggerName = "csv"
    """csv: metrics.csv only; tensorboard / wandb: also send every row to that TorchRL logger."""

    def check_run_options(self) -> None:
        """Refuse bad run options before anything is built or written."""
        if not -(2**62) <= self.seed <= 2**62:
            raise ValueError(f"seed must be an integer in [-2**62, 2**62], got {self.seed}")
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be >= 1, got {self.checkpoint_every}")
        if self.resume is not None and self.run_dir is not None:
            if Path(self.run_dir).resolve() != Path(self.resume).resolve():
                raise ValueError(
                    f"--resume {self.resume} and --run-dir {self.run_dir} name different "
                    "directories; a run is resumed in its own directory"
                )


def config_dict(experiment: str, cfg: Any) -> dict[str, Any]:
    """``config.json``'s content: the experiment's name and every option, JSON-ready."""
    out: dict[str, Any] = jsonable({"experiment": experiment, **dataclasses.asdict(cfg)})
    return out


def check_options(
    cfg: Any,
    *,
    counts: tuple[str, ...] = (),
    positive: tuple[str, ...] = (),
    nonnegative: tuple[str, ...] = (),
) -> None:
    """Refuse bad option values before anything is built or written: ``counts`` must be
    integers >= 1, ``positive`` finite numbers > 0, ``nonnegative`` finite numbers >= 0
    (None is allowed where the option's type allows it). The message names the option (as
    spelled on the command line) and the value."""
    import math

    def bad(name: str, value: Any, want: str) -> ValueError:
        flag = "--" + name.replace("_", "-")
        return ValueError(f"{name} ({flag}) must be {want}, got {value!r}")

    for name in counts:
        value = getattr(cfg, name)
        if value is not None and (isinstance(value, bool) or int(value) != value or value < 1):
            raise bad(name, value, "an integer >= 1")
    for name, low, strict in [(n, 0.0, True) for n in positive] + [
        (n, 0.0, False) for n in nonnegative
    ]:
        value = getattr(cfg, name)
        if value is None:
            continue
        ok = math.isfinite(float(value)) and (value > low if strict else value >= low)
        if not ok:
            raise bad(name, value, "finite and > 0" if strict else "finite and >= 0")
