"""The options every experiment shares (a base of every experiment's config dataclass)."""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import re
import types
import typing
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hireps_torch.algorithms.base import stream_seed
from hireps_torch.checks import check_device, check_present_device
from hireps_torch.experiments.migrations import ABSENT_MEANS
from hireps_torch.experiments.rundir import (
    LoggerName,
    check_logger,
    check_new_run_dir,
    jsonable,
)
from hireps_torch.features import MAX_FOURIER_TERMS
from hireps_torch.policies.linear_gaussian import FLOOR_RANGE

__all__ = [
    "RunOptions",
    "check_fourier_bases",
    "check_options",
    "check_types",
    "config_dict",
    "option_error",
    "member_seeds",
    "parse_seeds",
    "stream_seed",
]


@dataclass(frozen=True)
class RunOptions:
    """Options of the run itself rather than of the experiment."""

    seed: int = 0
    """Seed of every random generator of the run (same seed, same run)."""
    seeds: str | None = None
    """Run these seeds as one population in one process (0-19, 0,3,7 or 0-2,9; replaces
    --seed): member s writes what --seed s writes, in <run-dir>/seed<s>; <run-dir> gets the
    population's summary, table and band plot (hockey plays the members' episodes one member
    after the other)."""
    run_dir: Path | None = None
    """Where to write the run (default runs/<experiment>/<timestamp>); new or empty."""
    resume: Path | None = None
    """Continue the interrupted run in this directory (options given again must agree)."""
    checkpoint_every: int = 1
    """Write checkpoint.pt after every this many iterations (and on SIGINT/SIGTERM)."""
    progress: bool = True
    """Show a progress bar."""
    logger: LoggerName = "csv"
    """csv: metrics.csv only; tensorboard / wandb: also send every row to that TorchRL logger."""
    device: str = "cpu"
    """Where the run computes: cpu, cuda, cuda:1, ... (the sampling generators stay on the
    CPU: a seed draws the same noise on every device; hockey runs on the CPU)."""

    def check_run_options(self) -> None:
        """Refuse bad run options (types, ranges, a ``--run-dir`` in the way) before anything
        is built or written."""
        check_types(self)
        if not -(2**62) <= self.seed <= 2**62:
            raise ValueError(f"seed must be an integer in [-2**62, 2**62], got {self.seed}")
        if self.seeds is not None:
            parse_seeds(self.seeds)
            if self.seed != 0 and self.resume is None:
                raise ValueError(
                    f"--seed {self.seed} and --seeds {self.seeds} both name the seeds to run; "
                    "pass one (--seeds replaces --seed)"
                )
        device = self.device
        try:
            dev = check_device(device)
        except ValueError:
            raise option_error("device", device, "a torch device such as cpu or cuda") from None
        if dev.type == "meta":
            raise option_error("device", device, "a device that holds values (meta holds none)")
        try:
            check_present_device(dev)
        except ValueError as exc:
            raise option_error("device", device, f"a device present here ({exc})") from None
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be >= 1, got {self.checkpoint_every}")
        check_logger(self.logger)
        if self.resume is not None and self.run_dir is not None:
            if Path(self.run_dir).resolve() != Path(self.resume).resolve():
                raise ValueError(
                    f"--resume {self.resume} and --run-dir {self.run_dir} name different "
                    "directories; a run is resumed in its own directory"
                )
        if self.resume is None and self.run_dir is not None:
            check_new_run_dir(Path(self.run_dir))


def member_seeds(cfg: RunOptions) -> list[int]:
    """The seeds a run learns: ``--seeds`` (a population), else ``[--seed]``."""
    return [cfg.seed] if cfg.seeds is None else parse_seeds(cfg.seeds)


def option_error(
    name: str, value: Any, want: str, error: type[Exception] = ValueError
) -> Exception:
    """The error ``name (--flag) must be <want>, got <value>`` of an option."""
    flag = "--" + name.replace("_", "-")
    return error(f"{name} ({flag}) must be {want}, got {value!r}")


def check_types(cfg: Any) -> None:
    """Every field of ``cfg`` of its annotated type (bools are not numbers); a ``TypeError`` (a
    ``ValueError`` outside a ``Literal``) names the option and the value."""
    hints = typing.get_type_hints(type(cfg))
    for f in dataclasses.fields(cfg):
        _check_type(f.name, getattr(cfg, f.name), hints[f.name])


def _check_type(name: str, value: Any, hint: Any) -> None:
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return
        (hint,) = [a for a in args if a is not type(None)]
        args = typing.get_args(hint)
    if typing.get_origin(hint) is typing.Literal:
        if value not in args or isinstance(value, bool) != isinstance(args[0], bool):
            raise option_error(name, value, f"one of {', '.join(map(repr, args))}")
        return
    ok = {
        bool: lambda v: isinstance(v, bool),
        int: lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool),
        float: lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool),
        Path: lambda v: isinstance(v, str | os.PathLike),
    }.get(hint)
    if ok is not None and not ok(value):
        want = {bool: "True or False", int: "an integer", float: "a number", Path: "a path"}
        raise option_error(name, value, want[hint], TypeError)


def config_dict(experiment: str, cfg: Any) -> dict[str, Any]:
    """``config.json``'s content: the experiment's name and every option, JSON-ready
    (``seeds`` only for a population; options at their :data:`ABSENT_MEANS` value left out)."""
    options = dataclasses.asdict(cfg)
    if options.get("seeds", "") is None:
        del options["seeds"]
    for key, before in ABSENT_MEANS.items():  # as before these options existed
        if key in options and options[key] == before:
            del options[key]
    out: dict[str, Any] = jsonable({"experiment": experiment, **options})
    return out


MAX_SEEDS = 10_000
"""The most seeds one ``--seeds`` names (a population or a sweep)."""


def parse_seeds(text: str) -> list[int]:
    """``"0-4"`` -> [0, 1, 2, 3, 4]; ``"0,3,7"``; ``"0-2,9"``. A repeated seed, an empty or
    reversed range and anything else are a ValueError naming the text."""
    seeds: list[int] = []
    for part in str(text).split(","):
        m = re.fullmatch(r"\s*(-?[0-9]+)\s*(?:-\s*(-?[0-9]+)\s*)?", part)
        if m is None or (m[2] is not None and int(m[2]) < int(m[1])):
            raise ValueError(f"--seeds must look like 0-4, 0,3,7 or 0-2,9, got {text!r}")
        lo, hi = int(m[1]), int(m[2] if m[2] is not None else m[1])
        if not -(2**62) <= lo <= hi <= 2**62 or hi - lo >= MAX_SEEDS:
            raise ValueError(
                f"--seeds {text!r}: seeds must lie in [-2**62, 2**62] and a range hold at most "
                f"{MAX_SEEDS} seeds, got {part.strip()!r}"
            )
        seeds.extend(range(lo, hi + 1))
        if len(seeds) > MAX_SEEDS:
            raise ValueError(f"--seeds {text!r} names more than {MAX_SEEDS} seeds")
    repeated = sorted(s for s, n in Counter(seeds).items() if n > 1)
    if repeated:
        raise ValueError(f"--seeds {text!r} names seed(s) {repeated} more than once")
    return seeds


def check_options(
    cfg: Any,
    *,
    counts: tuple[str, ...] = (),
    positive: tuple[str, ...] = (),
    nonnegative: tuple[str, ...] = (),
) -> None:
    """Refuse bad values before anything is built: ``counts`` integers >= 1, ``positive``
    finite > 0, ``nonnegative`` finite >= 0 (None where the type allows it), after
    :func:`check_types`; the message names the option and the value."""
    check_types(cfg)
    for name in counts:
        value = getattr(cfg, name)
        if value is not None and (isinstance(value, bool) or int(value) != value or value < 1):
            raise option_error(name, value, "an integer >= 1")
    for name, strict in [(n, True) for n in positive] + [(n, False) for n in nonnegative]:
        value = getattr(cfg, name)
        if value is not None and not (
            math.isfinite(float(value)) and (value > 0.0 if strict else value >= 0.0)
        ):
            raise option_error(name, value, "finite and > 0" if strict else "finite and >= 0")


def check_variance_floor(cfg: Any) -> None:
    """``cfg.min_variance`` within :data:`~hireps_torch.policies.linear_gaussian.FLOOR_RANGE`."""
    value, (low, high) = cfg.min_variance, FLOOR_RANGE
    if not low <= value <= high:  # nan and +-inf fail it
        raise option_error("min_variance", value, f"in [{low:g}, {high:g}] (a variance)")


def check_fourier_bases(cfg: Any, state_dim: int) -> None:
    """``cfg.fourier_bases`` (bases per dimension of a ``state_dim``-dimensional Fourier
    basis) >= 2 and small enough for :class:`~hireps_torch.features.FourierFeatures`."""
    n = cfg.fourier_bases
    if n < 2 or n**state_dim > MAX_FOURIER_TERMS:
        top = int(round(MAX_FOURIER_TERMS ** (1 / state_dim)))
        raise option_error("fourier_bases", n, f"an integer in 2..{top} ({state_dim}-D states)")
