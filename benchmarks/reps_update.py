"""One REPS update, hireps_torch against MushroomRL 1.10.1, on the same problems in one run.

MushroomRL runs in its own virtualenv (``bash ../shared/anchors/setup.sh`` builds it; default
``~/.cache/hireps-anchors/venv``), through the anchor's own benchmark script
(``../shared/anchors/mushroom_reps_bench.py``), which times ``REPS._update`` (median of its
repeats, one thread). This script then times ``REPS.create(D, epsilon=eps).tell(None, theta,
R)`` on the arrays of the anchor's ``make_problem(N, D)`` (a fresh algorithm per repeat,
outside the timed region; median; one thread) and prints both and their ratio.

    OMP_NUM_THREADS=1 python benchmarks/reps_update.py [--N 30 300 3000 30000] [--D 14 42]
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hireps_torch.algorithms import REPS  # noqa: E402

ANCHORS = ROOT.parent / "shared" / "anchors"
VENV = Path(os.environ.get("ANCHORS_DIR", Path.home() / ".cache" / "hireps-anchors")) / "venv"


def _anchor_module():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("anchor", ANCHORS / "mushroom_reps_bench.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def ours_ms(N: int, D: int, eps: float, repeats: int) -> tuple[float, float]:
    """(median ms of one tell, its realised KL) on the anchor's problem (N, D)."""
    theta, R, _ = _anchor_module().make_problem(N, D)
    theta_t, R_t = torch.as_tensor(theta), torch.as_tensor(R)
    times, kl = [], float("nan")
    for _ in range(repeats + 1):
        algo = REPS.create(D, epsilon=eps, seed=0)
        gc.disable()
        t0 = time.perf_counter()
        report = algo.tell(None, theta_t, R_t)
        times.append(time.perf_counter() - t0)
        gc.enable()
        kl = report["kl"]
    return 1e3 * statistics.median(times[1:]), kl


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--N", type=int, nargs="+", default=[30, 300, 3000, 30000])
    parser.add_argument("--D", type=int, nargs="+", default=[14, 42])
    parser.add_argument("--eps", type=float, default=0.5)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if not (VENV / "bin" / "python").exists():
        raise SystemExit(f"no MushroomRL virtualenv at {VENV}: run bash {ANCHORS}/setup.sh first")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "mushroom.json"
        subprocess.run(
            [
                str(VENV / "bin" / "python"),
                str(ANCHORS / "mushroom_reps_bench.py"),
                "--out",
                str(out),
                "--N",
                *map(str, args.N),
                "--D",
                *map(str, args.D),
                "--eps",
                str(args.eps),
                "--repeats",
                str(max(args.repeats, 7)),
                "--threads",
                "1",
                "--no-api-check",
                "--no-breakdown",
            ],
            check=True,
            capture_output=True,
        )
        rows = json.loads(out.read_text())["rows"]
    print(f"REPS update, eps {args.eps}, one thread, median of {args.repeats}")
    print(f"{'N':>6} {'D':>3} | {'MushroomRL ms':>13} {'ours ms':>8} {'ours / MR':>9} | ours KL")
    for row in rows:
        N, D = row["N"], row["D"]
        mr = row.get("mushroom", {}).get("update", {}).get("median_ms")
        ours, kl = ours_ms(N, D, args.eps, args.repeats)
        ratio = f"{ours / mr:8.2f}x" if mr else "     -"
        mr_text = f"{mr:13.3f}" if mr else f"{'FAIL/SKIP':>13}"
        print(f"{N:>6} {D:>3} | {mr_text} {ours:8.3f} {ratio} | {kl:.6f}", flush=True)


if __name__ == "__main__":
    main()
