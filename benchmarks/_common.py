"""Small helpers shared by the benchmark scripts (not part of the library)."""

from __future__ import annotations

import contextlib
import csv
import json
import statistics
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

FIGURES = Path(__file__).resolve().parents[1] / "docs" / "figures"
"""Where the README's figures live; a benchmark run with ``--figures`` writes its own there."""


def add_figures_option(ap: Any) -> None:
    """``--figures DIR``: also write the benchmark's figures to DIR under fixed names (the
    README's are regenerated with ``--figures docs/figures``)."""
    ap.add_argument(
        "--figures",
        type=Path,
        default=None,
        help=f"also copy the figures to this folder under fixed names (the README's: {FIGURES})",
    )


def publish(figures: Path | None, made: dict[str, Path]) -> None:
    """Copy each made figure to ``figures/<name>`` (atomically; nothing without ``--figures``)."""
    if figures is None:
        return
    from hireps_torch.experiments.rundir import atomic_write

    figures.mkdir(parents=True, exist_ok=True)
    for name, src in made.items():
        data = src.read_bytes()
        atomic_write(figures / name, lambda p, data=data: p.write_bytes(data))
        print(f"figure: {figures / name}")


@contextlib.contextmanager
def baseline_worktree(root: Path, commit: str) -> Iterator[Path]:
    """A ``git worktree`` of ``commit`` of the repository at ``root`` in a temporary folder,
    removed on exit: the code to compare with, side by side."""
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "baseline"
        git = ["git", "-C", str(root), "worktree"]
        subprocess.run([*git, "add", "--detach", str(old), commit], check=True, capture_output=True)
        try:
            yield old
        finally:
            subprocess.run([*git, "remove", "--force", str(old)], check=False)


def start_benchmark(out_base: Path, seeds: int, threads: int | None = 1) -> Path:
    """Check ``--seeds``, run torch on ``threads`` threads (None: torch's default) and create
    ``out_base/<timestamp>`` (a fresh folder: an existing one is never written into)."""
    if seeds < 1:
        raise SystemExit(f"--seeds must be >= 1, got {seeds}")
    if threads is not None:
        torch.set_num_threads(threads)
    out = out_base / time.strftime("%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=False)
    return out


def read_curve(run_dir: Path, key: str = "average_return") -> tuple[list[float], list[float]]:
    """(episodes, ``key``) per iteration from a run directory's metrics.csv."""
    with (run_dir / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    return [float(r["episodes"]) for r in rows], [float(r[key]) for r in rows]


def mean_std(xs: list[float], digits: int = 1) -> str:
    """'mean ± std' (``digits`` decimals), or the value alone for one sample."""
    if len(xs) == 1:
        return f"{xs[0]:.{digits}f}"
    return f"{statistics.mean(xs):.{digits}f} ± {statistics.stdev(xs):.{digits}f}"


def plot_band(ax: Any, x: list[float], curves: list[list[float]], label: str) -> None:
    """Mean curve with a ±1 std band over seeds."""
    c = torch.tensor(curves, dtype=torch.float64)
    m = c.mean(0)
    s = c.std(0) if c.shape[0] > 1 else torch.zeros_like(m)
    ax.plot(x, m.numpy(), label=label)
    ax.fill_between(x, (m - s).numpy(), (m + s).numpy(), alpha=0.2)


def write_results(out: Path, results: Any, total_seconds: float, table: str) -> None:
    """results.json (every run) and results.md (the printed table), each written atomically."""
    from hireps_torch.experiments.rundir import atomic_write

    payload = json.dumps({"results": results, "total_seconds": total_seconds})
    atomic_write(out / "results.json", lambda p: p.write_text(payload))
    atomic_write(out / "results.md", lambda p: p.write_text(table + "\n"))
    print(f"written to {out}")
