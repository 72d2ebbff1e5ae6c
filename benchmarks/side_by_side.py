"""Whole runs of one experiment with the code of a given commit and with the current code, seed
by seed in one run: wall time, the dual's iterations and convergence, and the final policy's
success.

For each seed, ``train.py EXPERIMENT --seed S`` runs first from a ``git worktree`` of the
baseline commit, then from this checkout (one after the other, so both see the same machine
load), each in its own process with one thread. Printed per seed and side: ``wall_seconds`` of
``summary.json``, the median and largest ``dual_iterations`` of ``metrics.csv``, the updates
whose ``dual_converged`` is False, and the last row's ``eval_success_rate``; then the totals and
the baseline / current time ratio.

    OMP_NUM_THREADS=1 python benchmarks/side_by_side.py ball-on-beam --seeds 0-9 \
        [--baseline f73bf30] [--set episodes=30 ...]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import baseline_worktree  # noqa: E402


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def one_run(
    root: Path, experiment: str, seed: int, run_dir: Path, extra: list[str]
) -> dict[str, Any]:
    """Run ``train.py`` of ``root`` and read back what the run wrote."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    subprocess.run(
        [
            sys.executable,
            str(root / "train.py"),
            experiment,
            "--seed",
            str(seed),
            "--run-dir",
            str(run_dir),
            "--no-progress",
            *extra,
        ],
        env=env,
        check=True,
        capture_output=True,
    )
    summary = json.loads((run_dir / "summary.json").read_text())
    with open(run_dir / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    its = [int(r["dual_iterations"]) for r in rows]
    return {
        "wall": float(summary["wall_seconds"]),
        "iter_median": statistics.median(its),
        "iter_max": max(its),
        "unconverged": [i + 1 for i, r in enumerate(rows) if r["dual_converged"] != "True"],
        "success": float(rows[-1].get("eval_success_rate", "nan") or "nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("experiment")
    parser.add_argument("--seeds", default="0-9")
    parser.add_argument("--baseline", default="f73bf30")
    parser.add_argument("--set", nargs="*", default=[], help="OPTION=VALUE for both sides")
    args = parser.parse_args()
    extra = [
        a
        for kv in args.set
        for a in (f"--{kv.split('=')[0].replace('_', '-')}", kv.split("=", 1)[1])
    ]
    results: dict[str, list[dict[str, Any]]] = {args.baseline: [], "current": []}
    with tempfile.TemporaryDirectory() as tmp, baseline_worktree(ROOT, args.baseline) as old:
        print(
            f"{'seed':>4} {'code':<9} {'wall s':>7} {'iter med':>8} {'iter max':>8} "
            f"{'success':>7}  unconverged updates",
            flush=True,
        )
        for seed in _seeds(args.seeds):
            for label, root in ((args.baseline, old), ("current", ROOT)):
                r = one_run(root, args.experiment, seed, Path(tmp) / f"{label}-{seed}", extra)
                results[label].append(r)
                print(
                    f"{seed:>4} {label:<9} {r['wall']:>7.2f} {r['iter_median']:>8g} "
                    f"{r['iter_max']:>8} {r['success']:>7.2f}  {r['unconverged'] or '-'}",
                    flush=True,
                )
    for label, rs in results.items():
        walls = [r["wall"] for r in rs]
        ok = sum(r["success"] >= 0.9 for r in rs)
        unconv = sum(len(r["unconverged"]) for r in rs)
        print(
            f"{label:<9} wall total {sum(walls):.1f} s (mean {statistics.mean(walls):.2f}); "
            f"final success >= 0.9 in {ok}/{len(rs)}; unconverged updates {unconv}"
        )
    a = sum(r["wall"] for r in results[args.baseline])
    b = sum(r["wall"] for r in results["current"])
    print(f"current / baseline wall time: {b / a:.2f}")


if __name__ == "__main__":
    main()
