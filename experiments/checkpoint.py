"""Checkpoints that continue a run exactly, and the interruption that writes one.

``checkpoint.pt`` holds :class:`RunState`'s entries, each member's ``metrics.csv`` ``rows``,
``iteration``, ``elapsed``, ``config``, ``experiment``, ``finished`` and ``threads`` (torch's, as
the run computed): plain data that
``torch.load(path)`` reads with ``weights_only=True``.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import sys
import types
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol

import torch

from hireps_torch.experiments.migrations import (
    ABSENT_MEANS,
    READABLE_FORMATS,
    current_config,
    no_config_note,
)
from hireps_torch.experiments.options import parse_seeds
from hireps_torch.experiments.rundir import parse_rows

__all__ = [
    "RUN_ONLY_OPTIONS",
    "CheckpointState",
    "RunFinished",
    "RunInterrupted",
    "RunState",
    "StopRequest",
    "changed_options",
    "check_same_run",
    "checkpoint_dir",
    "load_checkpoint",
    "read_config",
    "run_config",
    "saved_config",
    "stop_on_signals",
]

FORMAT = 3
"""The format this version writes (those it reads: ``migrations.READABLE_FORMATS``)."""
CHECKPOINT_KEYS = ("algorithm", "rng", "env", "rows", "iteration", "elapsed")
"""The entries of a checkpoint that a resume reads (besides ``format``)."""
RUN_ONLY_OPTIONS = ("run_dir", "resume", "progress", "checkpoint_every", "backend", "ray_address")
"""Options that may differ between a run and its resumption (they do not change results)."""


class RunInterrupted(KeyboardInterrupt):
    """The run stopped at an iteration boundary after a signal; its checkpoint is written."""

    def __init__(self, run_dir: Path, iteration: int, signame: str) -> None:
        super().__init__(
            f"{signame}: stopped after iteration {iteration}; checkpoint written to "
            f"{run_dir / 'checkpoint.pt'}. Continue with: --resume {run_dir}"
        )
        self.run_dir = run_dir
        self.iteration = iteration
        self.signame = signame


class RunFinished(Exception):
    """``--resume`` of a run that already wrote ``summary.json``."""


class Stateful(Protocol):
    """An algorithm: its ``state_dict`` a copy that later updates leave as it is."""

    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: Mapping[str, Any]) -> None: ...


class EnvState(Protocol):
    """The running state of a run's environments (see :mod:`hireps_torch.experiments.envstate`),
    its ``state_dict`` a copy."""

    def state_dict(self) -> dict[str, Any] | None: ...
    def load_state_dict(self, state: Mapping[str, Any] | None) -> None: ...


@dataclasses.dataclass
class RunState:
    """What a run must save to continue exactly: the algorithm, named generators and the
    environments' running state (None: nothing carries over)."""

    algorithm: Stateful
    generators: dict[str, torch.Generator] = dataclasses.field(default_factory=dict)
    env: EnvState | None = None

    def state_dict(self) -> dict[str, Any]:
        return {
            "algorithm": self.algorithm.state_dict(),
            "rng": {
                "torch": torch.get_rng_state(),
                **{name: g.get_state() for name, g in self.generators.items()},
            },
            "env": None if self.env is None else self.env.state_dict(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore after everything was built (building consumes random numbers)."""
        rng = state["rng"]
        if not isinstance(rng, Mapping):
            raise ValueError(f"the checkpoint's rng must be a mapping, got {type(rng).__name__}")
        if missing := [name for name in ("torch", *self.generators) if name not in rng]:
            raise ValueError(f"the checkpoint has no state for the generators {missing}")
        for name in ("torch", *self.generators):  # checked before anything is restored
            try:
                torch.Generator().set_state(rng[name])
            except (RuntimeError, TypeError) as exc:
                raise ValueError(f"the checkpoint's {name!r} generator state: {exc}") from None
        self.algorithm.load_state_dict(state["algorithm"])
        if self.env is not None:
            self.env.load_state_dict(state["env"])
        for name, g in self.generators.items():
            g.set_state(state["rng"][name])
        torch.set_rng_state(state["rng"]["torch"])


CheckpointState = dict[str, Any]


def load_checkpoint(run_dir: Path, map_location: str | None = None) -> CheckpointState | None:
    """The run's checkpoint (None if it stopped before its first iteration finished), its
    tensors on the devices they were saved from (or on ``map_location``)."""
    path = run_dir / "checkpoint.pt"
    if path.exists() and not path.is_file():
        raise ValueError(f"{path} is not a file; move it away (nothing was changed)")
    if not path.is_file():
        return None
    try:
        ckpt: CheckpointState = torch.load(path, map_location=map_location)
    except Exception as exc:  # truncated, empty, not a torch file, pickled objects, ...
        why = next(iter(str(exc).splitlines()), "")[:200] or "no message"
        raise ValueError(
            f"{path} cannot be read ({type(exc).__name__}: {why}); restore it, or move the "
            "run directory away and start the run again (nothing was changed)"
        ) from exc
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path} holds a {type(ckpt).__name__}, not a checkpoint of this code")
    if ckpt.get("format") not in READABLE_FORMATS:
        raise ValueError(
            f"{path} was written by another version of this code (format "
            f"{ckpt.get('format')!r}, expected {FORMAT}): this version can neither resume nor "
            "load it (nothing was changed)"
        )
    if missing := [k for k in CHECKPOINT_KEYS if k not in ckpt]:
        raise ValueError(f"{path} is not a complete checkpoint: it has no {missing}")
    it, members = ckpt["iteration"], ckpt["rows"]
    if ckpt["format"] == FORMAT:
        members = ckpt["rows"] = _parsed_rows(path, members)
    if not (
        isinstance(members, list)
        and members
        and all(isinstance(rows, list) for rows in members)
        and all(isinstance(r, dict) for rows in members for r in rows)
    ):
        raise ValueError(
            f"{path} is damaged: its rows are not one list of metrics.csv rows per member"
        )
    counts = sorted({len(rows) for rows in members})
    if isinstance(it, bool) or not isinstance(it, int) or counts != [it]:
        raise ValueError(
            f"{path} is damaged: it is at iteration {it!r} but holds {counts} metrics row(s) "
            "per member; restore it, or move the run directory away and start the run again"
        )
    if isinstance(ckpt["elapsed"], bool) or not isinstance(ckpt["elapsed"], (int, float)):
        raise ValueError(f"{path} is damaged: its elapsed time is {ckpt['elapsed']!r}")
    return ckpt


def _parsed_rows(path: Path, texts: Any) -> list[list[dict[str, Any]]]:
    """The rows of a format-3 checkpoint at ``path`` (``texts``: each member's metrics.csv
    text), or a ``ValueError`` saying it is damaged."""
    if not (isinstance(texts, list) and texts and all(isinstance(t, str) for t in texts)):
        raise ValueError(f"{path} is damaged: its rows are not one metrics.csv text per member")
    try:
        return [parse_rows(text) for text in texts]
    except ValueError as exc:
        raise ValueError(f"{path} is damaged: {exc}") from None


def read_config(run_dir: Path) -> dict[str, Any]:
    """A run directory's ``config.json`` as a dict, as this version writes it
    (:func:`~hireps_torch.experiments.migrations.current_config`; a ``ValueError`` naming the
    file if not)."""
    path = run_dir / "config.json"
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path} cannot be read as JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path} holds a JSON {type(data).__name__}, not the options of a run")
    return current_config(data)


def changed_options(
    saved: Mapping[str, Any],
    now: Mapping[str, Any],
    labels: tuple[str, str] = ("run", "now"),
    run_only: tuple[str, ...] = (),
) -> list[str]:
    """Differing options as ``name (run: saved, now: current)`` (``labels`` name the two
    sides), ignoring :data:`RUN_ONLY_OPTIONS` and the experiment's own ``run_only``."""
    a, b = labels
    ignored = RUN_ONLY_OPTIONS + run_only

    def given(options: Mapping[str, Any], key: str) -> Any:  # left out: the value it meant
        return options.get(key, ABSENT_MEANS.get(key, "<absent>"))

    return [
        f"{key} ({a}: {given(saved, key)!r}, {b}: {given(now, key)!r})"
        for key in sorted(set(saved) | set(now))
        if key not in ignored and _meaning(key, given(saved, key)) != _meaning(key, given(now, key))
    ]


def checkpoint_dir(run_dir: Path, seed: int) -> tuple[Path, tuple[int, int] | None]:
    """Where the checkpoint of the run in ``run_dir`` (its config's ``seed``) is, and for a
    population's member (its index, S); a ``ValueError`` for a directory inside a population
    that is not one of its members."""
    if (run_dir / "checkpoint.pt").exists():
        return run_dir, None
    real = run_dir.resolve()
    parent = real.parent
    if not (parent / "config.json").is_file():
        return run_dir, None
    seeds = read_config(parent).get("seeds")
    if seeds is None:
        return run_dir, None

    try:
        members = parse_seeds(seeds)
    except ValueError as exc:
        raise ValueError(f"{parent / 'config.json'}: its seeds {seeds!r}: {exc}") from None
    if real.name != f"seed{seed}" or seed not in members:
        raise ValueError(
            f"{run_dir} is inside the population {parent} (seeds {seeds}) but is not one of "
            f"its members: its config.json has seed {seed}, and member s lives in seed<s>"
        )
    return parent, (members.index(seed), len(members))


def check_same_run(
    run_dir: Path, ckpt: Mapping[str, Any], saved: Mapping[str, Any], run_only: tuple[str, ...] = ()
) -> None:
    """A ``ValueError`` unless the checkpoint in ``run_dir`` was written by the run that its
    ``config.json`` (``saved``) describes: the same experiment and options."""
    checkpoint, config = run_dir / "checkpoint.pt", run_dir / "config.json"
    ckpt = current_config(ckpt)
    if ckpt.get("experiment") != saved.get("experiment"):
        raise ValueError(
            f"{checkpoint} is of a {ckpt.get('experiment')!r} run, but {config} of a "
            f"{saved.get('experiment')!r} run"
        )
    theirs = ckpt.get("config")
    if diff := changed_options(
        current_config(theirs) if isinstance(theirs, dict) else {},
        saved,
        ("checkpoint.pt", "config.json"),
        run_only,
    ):
        raise ValueError(
            f"{checkpoint} was written by a run with other options than {config} holds: "
            + "; ".join(diff)
            + " (was one of them copied or edited?)"
        )


def _meaning(key: str, value: Any) -> Any:
    """What an option's value means when two are compared: ``seeds`` as the seeds it names
    (``0-2`` and ``0,1,2`` are the same population), a CPU ``device`` as ``cpu`` (``cpu:0`` is
    the same device), anything else as it is."""
    if key == "seeds" and isinstance(value, str):
        try:
            return parse_seeds(value)
        except ValueError:
            return value
    if key == "device" and isinstance(value, str) and value.partition(":")[0].strip() == "cpu":
        return "cpu"
    return value


def run_config(config_cls: type, experiment: str, run_dir: Path) -> Any:
    """The config a run directory was started with (``config.json``), as a ``config_cls``,
    with ``run_dir`` set to where it is now and no ``resume``."""
    path = run_dir / "config.json"
    if not path.is_file():
        note = no_config_note(run_dir)
        raise ValueError(f"{run_dir}: no config.json there; is it a run directory?{note}")
    data = read_config(run_dir)
    if data.get("experiment", experiment) != experiment:
        raise ValueError(
            f"{run_dir}: that run is a {data.get('experiment')!r} run, not {experiment!r}"
        )
    fields = {f.name for f in dataclasses.fields(config_cls)}
    # an option left out of config.json was at its ABSENT_MEANS value
    values = {k: v for k, v in (ABSENT_MEANS | data).items() if k in fields}
    values |= {"run_dir": run_dir, "resume": None}
    try:
        return config_cls(**values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path} does not hold the options of a {experiment} run: {exc}") from None


def saved_config(config_cls: type, experiment: str, run_dir: Path) -> Any:
    """The config a run directory was started with, ``resume`` set to where it is now: the
    defaults of ``--resume RUN_DIR``."""
    try:
        cfg = run_config(config_cls, experiment, run_dir)
    except ValueError as exc:
        raise ValueError(f"--resume {exc}") from None
    return dataclasses.replace(cfg, run_dir=None, resume=run_dir)


@dataclasses.dataclass
class StopRequest:
    """Set by SIGINT/SIGTERM (``signals`` counts them) or :func:`request_stop`; the training loop
    stops at the next iteration boundary."""

    signame: str | None = None
    signals: int = 0


EARLY = StopRequest()
"""A stop asked for before :func:`stop_on_signals` took over: stop after iteration 1."""
ACTIVE: StopRequest | None = None
"""The request of the :func:`stop_on_signals` in force (None outside one)."""


def record_early_stops() -> None:
    """Until :func:`stop_on_signals` takes over, SIGINT / SIGTERM only set :data:`EARLY`."""

    def handler(signum: int, frame: types.FrameType | None) -> None:
        EARLY.signame = EARLY.signame or signal.Signals(signum).name
        EARLY.signals += 1

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)


def stop_requested() -> bool:
    """Whether a stop was asked for (a signal, :func:`request_stop`) and not yet taken."""
    return (ACTIVE or EARLY).signame is not None


def request_stop(reason: str) -> None:
    """Ask, from any thread, for a stop at the next iteration boundary, as a first signal does
    (a signal after it still counts as the first)."""
    request = ACTIVE or EARLY
    request.signame = request.signame or reason


@contextmanager
def stop_on_signals(then: str = "then saving the checkpoint") -> Iterator[StopRequest]:
    """While active, a first SIGINT/SIGTERM requests a stop at the next iteration boundary
    (printing ``then``), a second interrupts at once; does nothing outside the main thread."""
    request = StopRequest()
    names: dict[int, str] = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}
    previous: dict[int, Any] = {}

    def handler(signum: int, frame: types.FrameType | None) -> None:
        request.signals += 1
        name = names.get(signum, str(signum))
        if request.signals > 1:
            stop = KeyboardInterrupt(f"second {name}: stopping now")
            stop.signame = name  # type: ignore[attr-defined]  # hireps-train's exit code: 143
            raise stop
        request.signame = request.signame or name
        print(
            f"\n{name}: finishing this iteration, {then} (send it again to stop at once)",
            file=sys.stderr,
        )

    try:
        for sig in names:
            previous[sig] = signal.signal(sig, handler)
    except ValueError:  # not the main thread: leave the signals alone
        previous.clear()
    global ACTIVE
    outer, ACTIVE = ACTIVE, (request if previous else ACTIVE)
    # read once ours is in place, so that nothing is lost in between
    request.signame = request.signame or EARLY.signame
    request.signals += EARLY.signals
    try:
        yield request
    finally:
        ACTIVE = outer
        for sig, old in previous.items():
            signal.signal(sig, old)
