"""The duals real runs produce, solved by the code of a given commit and by the current code
side by side in one run.

The problems (``benchmarks/dual_problems.pt``, written by ``benchmarks/record_duals.py``) are
the checked K-block inputs of :func:`hireps_torch.dual.solver.solve_blocks`, one per update of a
few seeds of every experiment. Each side runs in its own subprocess (the baseline from a
``git worktree`` of the commit, so both import their own ``hireps_torch``), one thread, and
solves every problem ``--repeats`` times. Printed per experiment and side: LBFGS iterations per
solve (Newton steps counted as iterations; median, max), the share that converged, the median
time per solve, and the baseline / current ratios.

    OMP_NUM_THREADS=1 python benchmarks/dual_speed.py [--baseline f73bf30] [--repeats 3]
        [--problems benchmarks/dual_problems.pt]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import baseline_worktree  # noqa: E402

PROBLEMS = ROOT / "benchmarks" / "dual_problems.pt"


def solve_all(root: Path, problems: Path, repeats: int) -> list[dict[str, Any]]:
    """Solve every recorded problem with the ``hireps_torch`` under ``root``; one row each."""
    sys.path.insert(0, str(root))
    import torch

    torch.set_num_threads(1)
    from hireps_torch.dual.solver import LbfgsSettings, solve_blocks

    settings = LbfgsSettings()
    rows = []
    for p in torch.load(problems, weights_only=False):
        args = [
            None if p[k] is None else p[k][None].double()
            for k in ("R", "log_resp", "eps", "D", "c", "kappa")
        ]
        times = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for _ in range(repeats):
                t0 = time.perf_counter()
                sol = solve_blocks(*args, settings)
                times.append(time.perf_counter() - t0)
        rows.append(
            {
                "experiment": p["experiment"],
                "iterations": int(sol.iterations),
                "converged": bool(sol.converged.all()),
                "ms": 1e3 * statistics.median(times),
                "kl_over": float((sol.kl / p["eps"][None]).max()),
            }
        )
    return rows


def _side(root: Path, problems: Path, repeats: int) -> list[dict[str, Any]]:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, __file__, "--solve", str(root), "--problems", str(problems)]
        + ["--repeats", str(repeats)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    rows: list[dict[str, Any]] = json.loads(out.strip().splitlines()[-1])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", default="f73bf30", help="commit to compare with")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--problems", type=Path, default=PROBLEMS, help="recorded problems")
    parser.add_argument("--solve", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    problems = args.problems.resolve()
    if args.solve is not None:
        print(json.dumps(solve_all(args.solve, problems, args.repeats)))
        return
    with baseline_worktree(ROOT, args.baseline) as old:
        sides = {
            args.baseline: _side(old, problems, args.repeats),
            "current": _side(ROOT, problems, args.repeats),
        }
    experiments = list(dict.fromkeys(r["experiment"] for r in sides["current"]))
    print(
        f"{'experiment':<18} {'code':<9} {'solves':>6} {'iter median':>11} {'iter max':>8} "
        f"{'converged':>9} {'ms/solve':>8}"
    )
    for name in [*experiments, "all"]:
        stats = {}
        for label, rows in sides.items():
            mine = [r for r in rows if name in ("all", r["experiment"])]
            its = [r["iterations"] for r in mine]
            stats[label] = (
                statistics.median(its),
                max(its),
                statistics.median(r["ms"] for r in mine),
            )
            conv = sum(r["converged"] for r in mine)
            print(
                f"{name:<18} {label:<9} {len(mine):>6} {stats[label][0]:>11g} "
                f"{max(its):>8} {conv:>4}/{len(mine):<4} {stats[label][2]:>8.2f}"
            )
        (a_it, a_max, a_ms), (b_it, b_max, b_ms) = stats[args.baseline], stats["current"]
        print(
            f"{'':<18} {'ratio':<9} {'':>6} {a_it / max(b_it, 1):>10.1f}x "
            f"{a_max / max(b_max, 1):>7.1f}x {'':>9} {a_ms / b_ms:>7.1f}x"
        )
    unconverged = [
        (r["experiment"], i) for i, r in enumerate(sides["current"]) if not r["converged"]
    ]
    print(f"current code, unconverged problems (experiment, index): {unconverged or 'none'}")


if __name__ == "__main__":
    main()
