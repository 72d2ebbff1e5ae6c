"""Run directories: ``config.json``, ``metrics.csv`` (one row per iteration),
``checkpoint.pt``, ``learning_curve.png`` and, last, ``summary.json`` (a directory without it is
an unfinished run). Files are written atomically; a non-empty directory is never reused.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import tempfile
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import torch
from matplotlib.figure import Figure

__all__ = [
    "LOGGERS",
    "DirectoryLock",
    "LoggerName",
    "RunWriter",
    "atomic_write",
    "check_new_run_dir",
    "default_run_dir",
    "jsonable",
    "make_logger",
    "parse_rows",
]

LoggerName = Literal["csv", "tensorboard", "wandb"]
LOGGERS: tuple[str, ...] = ("csv", "tensorboard", "wandb")


def default_run_dir(experiment: str, root: str | Path = "runs") -> Path:
    """``runs/<experiment>/<YYYYmmdd-HHMMSS>`` (a numeric suffix is added if it exists)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    base = Path(root) / experiment / stamp
    path, k = base, 1
    while path.exists():
        path = base.with_name(f"{stamp}-{k}")
        k += 1
    return path


def atomic_write(path: Path, write: Callable[[Path], object]) -> None:
    """Call ``write(tmp)`` on a temporary file next to ``path``, then move it into place; a
    failed write is an ``OSError`` naming ``path`` (the file there before is kept)."""
    kept = f"the previous {path.name} is kept" if path.exists() else "nothing was written"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:  # a read-only directory, one without permission, ...
        raise OSError(f"cannot write {path} ({exc.strerror or exc}): {kept}") from exc
    os.close(fd)
    try:
        try:
            write(Path(tmp))
        except (OSError, RuntimeError) as exc:  # torch.save wraps the OSError in a RuntimeError
            why = next(iter(str(exc).splitlines()), "")[:200] or type(exc).__name__
            raise OSError(f"cannot write {path} ({why}; is the disk full?): {kept}") from exc
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp's 0600 would hide results from a group
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")
"""The names :func:`atomic_write`'s temporary files take (``mkstemp``'s 8 random characters)."""


def parse_rows(text: str) -> list[dict[str, Any]]:
    """The rows of a ``metrics.csv`` text as :meth:`RunWriter.log` had them (numbers, booleans,
    None for an empty cell; a cell is read as a number only where it reads back as the same
    text, so the rows written again give the same file); a ``ValueError`` for a row that does
    not fit the header."""
    rows = list(csv.DictReader(io.StringIO(text, newline="")))
    for k, r in enumerate(rows, 1):
        if None in r or None in r.values():
            raise ValueError(f"its metrics row {k} does not fit the header")
    return [{key: _cell(v) for key, v in r.items()} for r in rows]


def _cell(text: str) -> Any:
    if text in ("True", "False"):
        return text == "True"
    if text == "":
        return None
    for kind in (int, float):
        with contextlib.suppress(ValueError):
            if str(value := kind(text)) == text:
                return value
    return text


class DirectoryLock:
    """An exclusive ``flock`` on a directory (one writer per run directory) until
    :meth:`release`, garbage collection or the process's end; one another process holds is a
    ``BlockingIOError``. Without such locks (Windows, some network mounts) it does nothing."""

    def __init__(self, directory: Path) -> None:
        self.release: Callable[[], Any] = lambda: None
        try:
            import fcntl
        except ImportError:
            return
        fd = os.open(directory, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise BlockingIOError(
                f"{directory} is being written by another process (a run, resume, population "
                "or sweep that is still going); wait for it to end, or stop it first (nothing "
                "was changed)"
            ) from None
        except OSError:  # no locks on this file system
            pass
        self.release = weakref.finalize(self, os.close, fd)


def jsonable(x: Any) -> Any:
    """``x`` with paths as strings, tensors as lists and non-finite floats as strings."""
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, torch.Tensor):
        return x.tolist()
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    return x


def check_new_run_dir(run_dir: Path) -> None:
    """Refuse a new run's directory that is a file or non-empty (``FileExistsError``) or that
    cannot be created (``ValueError``); creates nothing."""
    if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
        what = "is not empty" if run_dir.is_dir() else "is a file"
        raise FileExistsError(
            f"run directory {run_dir} already exists and {what}; pass a new --run-dir, or "
            "--resume a run (nothing was overwritten)"
        )
    parent = run_dir.absolute()
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"--run-dir {run_dir}: {parent} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"--run-dir {run_dir}: no permission to write in {parent}")


class RunWriter:
    """Writes one run directory.

    Args:
        run_dir: the directory; created, and refused if it exists and is not empty (unless
            ``rows`` is given: a run being resumed).
        config: written to ``config.json`` (kept as it is when resuming).
        logger: ``csv`` (``metrics.csv`` only), ``tensorboard`` or ``wandb`` (also that TorchRL
            logger, under ``run_dir``; W&B offline unless ``WANDB_MODE`` says otherwise).
        rows: when resuming, the checkpoint's rows: ``metrics.csv`` is rewritten to hold them.
        elapsed: when resuming, the seconds the run had taken so far.
    """

    def __init__(
        self,
        run_dir: str | Path,
        config: Mapping[str, Any],
        logger: LoggerName = "csv",
        *,
        rows: Sequence[Mapping[str, Any]] | None = None,
        elapsed: float = 0.0,
    ) -> None:
        self.dir = Path(run_dir)
        resuming = rows is not None
        if not resuming:
            check_new_run_dir(self.dir)
        if self.dir.is_symlink() and not self.dir.exists():
            raise FileExistsError(
                f"run directory {self.dir} is a link to {os.readlink(self.dir)}, which does not "
                "exist; pass another --run-dir or create its target (nothing was written)"
            )
        made: list[Path] = []  # the directories this writer creates, outermost first
        try:
            try:
                for d in [*reversed(self.dir.parents), self.dir]:
                    if not d.exists():
                        with contextlib.suppress(FileExistsError):  # made meanwhile elsewhere
                            d.mkdir()
                            made.append(d)
            except OSError as exc:
                raise OSError(f"cannot create the run directory {self.dir}: {exc}") from None
            self.lock = DirectoryLock(self.dir)
            name = f"{config.get('experiment', 'run')} seed {config.get('seed', 0)}"
            self.logger = make_logger(logger, self.dir, name)
        except BaseException:
            for d in reversed(made):  # a refused run leaves nothing behind
                if any(d.iterdir()):
                    break
                d.rmdir()
            raise
        if resuming:  # what an earlier session's atomic_write left when it was killed
            for tmp in self.dir.iterdir():
                if _TEMPORARY.fullmatch(tmp.name) and tmp.is_file():
                    with contextlib.suppress(OSError):  # a read-only directory: said below
                        tmp.unlink()
        self.start = time.perf_counter() - elapsed
        self._fields: list[str] | None = None
        self.rows: list[dict[str, Any]] = []
        self._text: list[str] = []  # metrics.csv's text: header, then one piece per row
        if resuming:
            self._rewrite_metrics(rows or [])
        if not resuming or not (self.dir / "config.json").is_file():  # a member's, deleted
            self.write_json("config.json", config)

    def elapsed(self) -> float:
        """Seconds the run has taken (over all its sessions)."""
        return time.perf_counter() - self.start

    def _rewrite_metrics(self, rows: Sequence[Mapping[str, Any]]) -> None:
        self.rows = [dict(r) for r in rows]
        path = self.dir / "metrics.csv"
        if not self.rows:
            path.unlink(missing_ok=True)
            return
        self._fields = list(self.rows[0])
        self._text = [self._csv(self.rows, header=True)]
        atomic_write(path, lambda p: p.write_text(self._text[0], newline=""))

    def _csv(self, rows: Sequence[Mapping[str, Any]], header: bool = False) -> str:
        out = io.StringIO(newline="")
        writer = csv.DictWriter(out, self._fields or [], extrasaction="ignore")
        if header:
            writer.writeheader()
        writer.writerows(rows)
        return out.getvalue()

    def csv_text(self) -> str:
        """What ``metrics.csv`` holds."""
        return "".join(self._text)

    def write_json(self, name: str, data: Mapping[str, Any]) -> None:
        text = json.dumps(jsonable(data), indent=2, sort_keys=False) + "\n"
        atomic_write(self.dir / name, lambda p: p.write_text(text))

    def log(self, row: Mapping[str, Any]) -> None:
        """Append one row to ``metrics.csv`` (columns fixed by the first row)."""
        clean = {k: (v if not isinstance(v, (list, tuple)) else len(v)) for k, v in row.items()}
        first = self._fields is None
        if first:
            self._fields = list(clean)
        text = self._csv([clean], header=first)
        with (self.dir / "metrics.csv").open("w" if first else "a", newline="") as f:
            f.write(text)
        self._text.append(text)
        self.rows.append(dict(clean))
        if self.logger is not None:
            step = int(clean.get("iteration", len(self.rows)))
            for key, value in clean.items():
                if isinstance(value, (bool, int, float)) and key != "iteration":
                    if isinstance(value, float) and math.isnan(value):
                        continue  # not measured in this row (e.g. no evaluation)
                    self.logger.log_scalar(key, float(value), step=step)

    def checkpoint(self, state: Mapping[str, Any], name: str = "checkpoint.pt") -> None:
        atomic_write(self.dir / name, lambda p: torch.save(dict(state), p))

    def finish(self, summary: Mapping[str, Any]) -> dict[str, Any]:
        """Write ``summary.json`` (adds ``wall_seconds``) and return what it holds."""
        out = {**summary, "wall_seconds": round(self.elapsed(), 3)}
        self.write_json("summary.json", out)
        self.release()
        written: dict[str, Any] = jsonable(out)  # what summary.json holds (NaN -> None)
        return written

    def release(self) -> None:
        """Flush and close the TorchRL logger (if any; ``metrics.csv`` is always flushed) and
        drop the directory's lock: this writer writes no more."""
        experiment = getattr(self.logger, "experiment", None)
        for name in ("flush", "close", "finish"):
            fn = getattr(experiment, name, None)
            if callable(fn):
                fn()
        self.logger = None
        self.lock.release()


def check_logger(kind: str) -> None:
    """A ``ValueError`` for an unknown logger kind, an ``ImportError`` naming a missing
    package."""
    if kind not in LOGGERS:
        raise ValueError(f"logger must be one of {', '.join(LOGGERS)}, got {kind!r}")
    import importlib.util

    if kind != "csv" and importlib.util.find_spec(kind) is None:  # named as the logger
        raise ImportError(
            f"--logger {kind} needs the {kind} package: pip install '{kind}' "
            f"(or the project's '{kind}' extra: pip install -e '.[{kind}]')"
        )
    if kind == "wandb":  # a W&B run per population member: wandb.init(reinit="create_new")
        from importlib.metadata import version

        have = version("wandb")
        if tuple(int(x) for x in re.findall(r"\d+", have)[:3]) < (0, 19, 10):
            raise ImportError(
                f"--logger wandb needs wandb >= 0.19.10, got {have}: pip install -U wandb"
            )


def make_logger(kind: str, run_dir: Path, name: str) -> Any:
    """The TorchRL logger that mirrors ``metrics.csv`` (None for ``csv``), ``name`` naming its
    run; errors as :func:`check_logger`."""
    check_logger(kind)
    if kind == "csv":
        return None
    from torchrl.record.loggers import get_logger

    if kind == "wandb":
        os.environ.setdefault("WANDB_MODE", "offline")  # no account needed
        os.environ.setdefault("WANDB_SILENT", "true")
        return get_logger(
            "wandb",
            str(run_dir),
            name,
            # one W&B run per run directory, also for a population's members in one process
            wandb_kwargs={"project": "hireps-torch", "dir": str(run_dir), "reinit": "create_new"},
        )
    return get_logger(kind, str(run_dir), kind)


def plot_learning_curves(
    writers: Sequence[RunWriter],
    x: str,
    ys: Sequence[str],
    title: str,
    ylabel: str = "return",
    name: str = "learning_curve.png",
) -> None:
    """Line plot of metric columns ``ys`` against column ``x`` in each writer's directory: one
    figure, its lines' data swapped per writer."""
    fig = Figure(figsize=(6, 4))  # no pyplot: a notebook's backend is left as it is
    ax = fig.subplots()
    lines = [ax.plot([], [], label=y.replace("_", " "))[0] for y in ys]
    ax.set_xlabel(x)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.ticklabel_format(style="sci", scilimits=(-3, 4), useMathText=True)  # short tick labels
    fig.subplots_adjust(left=0.14, right=0.97, bottom=0.12, top=0.92)  # that fit these margins
    for writer in writers:
        xs = [r[x] for r in writer.rows]
        for line, y in zip(lines, ys, strict=True):
            line.set_data(xs, [r[y] for r in writer.rows])
        ax.relim()
        if all(map(math.isfinite, ax.dataLim.bounds)):
            ax.autoscale_view()
        else:  # nothing finite to show: a fresh figure's limits, not the last writer's
            ax.set_xlim(-0.055, 0.055, auto=None)
            ax.set_ylim(-0.055, 0.055, auto=None)
        atomic_write(writer.dir / name, lambda p: fig.savefig(p, format="png", dpi=110))
