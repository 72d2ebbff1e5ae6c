"""The table and band plot of runs over seeds: a population's (``population.*``) and a
sweep's (``sweep.*``)."""

from __future__ import annotations

import csv
import json
import math
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np
from matplotlib.figure import Figure  # no pyplot: a notebook's backend is left alone

from hireps_torch.experiments.rundir import atomic_write

__all__ = ["Labelled", "Member", "summarize"]


class Labelled(Protocol):
    """One run of a table: its experiment, configuration ``name``, seed and directory."""

    @property
    def experiment(self) -> str: ...
    @property
    def name(self) -> str: ...
    @property
    def seed(self) -> int: ...
    @property
    def run_dir(self) -> Path: ...


class Member(NamedTuple):
    """A population's member as a :class:`Labelled` run."""

    experiment: str
    name: str
    seed: int
    run_dir: Path


def _mean_std(xs: Sequence[float]) -> str:
    if len(xs) == 1:
        return f"{xs[0]:.3g}"
    return f"{statistics.mean(xs):.3g} ± {statistics.stdev(xs):.2g}"


def summarize(
    runs: Sequence[Labelled],
    results: Mapping[tuple[str, int], Mapping[str, Any]],
    out: Path,
    metric: str,
    curve: str,
    stem: str = "sweep",
    seconds: str = "s/run",
) -> str:
    """Write ``<stem>.md`` (table of the summaries' ``metric``), ``.json`` (summaries) and
    ``.png`` (mean +- sample std bands of the ``metrics.csv`` column ``curve``) to ``out``;
    returns the table. ``results`` maps (configuration, seed) to a run's summary;
    ``seconds``: the header of the mean ``wall_seconds`` column."""
    if not runs:
        raise ValueError("nothing to summarize: the sweep has no runs")
    experiment = runs[0].experiment
    lines = [
        f"| configuration | seeds | {metric} (mean ± std) | per seed | {seconds} |",
        "|---|--:|--:|---|--:|",
    ]
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    for name in dict.fromkeys(r.name for r in runs):
        mine = [r for r in runs if r.name == name]
        ends = [results[(r.name, r.seed)] for r in mine]  # None in summary.json: NaN
        vals = [math.nan if e[metric] is None else float(e[metric]) for e in ends]
        walls = [float(e.get("wall_seconds", float("nan"))) for e in ends]
        per_seed = ", ".join(f"{r.seed}: {v:.3g}" for r, v in zip(mine, vals, strict=True))
        lines.append(
            f"| {name} | {len(mine)} | {_mean_std(vals)} | {per_seed} | "
            f"{statistics.mean(walls):.1f} |"
        )
        logs = []
        for r in mine:
            with (r.run_dir / "metrics.csv").open() as f:
                logs.append(list(csv.DictReader(f)))
        k = min(map(len, logs))
        x = np.array([float(w["episodes"]) for w in logs[0][:k]])
        ys = np.array([[float(w[curve]) for w in log[:k]] for log in logs])
        mean = ys.mean(0)
        std = ys.std(0, ddof=1) if len(ys) > 1 else np.zeros_like(mean)  # as the table's
        ax.plot(x, mean, label=name)
        ax.fill_between(x, mean - std, mean + std, alpha=0.2)
    table = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    ordered = {f"{r.name}/seed{r.seed}": dict(results[(r.name, r.seed)]) for r in runs}
    as_json = json.dumps(ordered, indent=1)  # in the order of ``runs``
    atomic_write(out / f"{stem}.json", lambda p: p.write_text(as_json))
    atomic_write(out / f"{stem}.md", lambda p: p.write_text(table + "\n"))
    ax.set_xlabel("episodes")
    ax.set_title(f"{experiment}: {curve} (mean ± std over seeds)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_write(out / f"{stem}.png", lambda p: fig.savefig(p, format="png", dpi=110))
    return table
