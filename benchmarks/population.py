"""A population of seeds in one process against one seed alone, side by side.

1. ``train.py pendulum --seed 0`` (the ordinary run), ``train.py pendulum --seeds 0-(S-1)``
   (one population), the same seeds as a sweep of ``--workers`` populations (``train.py sweep
   --members ceil(S / workers) --workers``: one process per population, each on cores of its
   own; 0 workers: skipped) and ``--seed 0`` again, the same episodes, one after the other in
   this run: wall times, and each against the mean of the two single seeds (the machine's
   speed drifts between runs minutes apart).
2. The population's learning: final success per seed, and the share of seeds ending with
   success >= 0.9, next to separate runs of the same seeds (``--separate DIR``: a finished
   ``train.py sweep --experiment pendulum`` whose ``sweep.json`` is read, or
   ``--run-separate`` to run that sweep here, two at a time). The two are compared with
   Fisher's exact test on the 2 x 2 table (population / separate x success / not): a member
   draws what its ordinary run draws, but batched arithmetic may round differently, which a
   long run can amplify, so the two are compared in distribution.

    python benchmarks/population.py [--seeds 20] [--episodes 1000] [--workers CORES]
        [--separate DIR] [--run-separate] [--out DIR]

Threads: torch's default (2 on the 2-core reference machine) for the runs in this process, or
``--threads``; one in each of the sweep's processes.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import start_benchmark  # noqa: E402
from hireps_torch.experiments import run_experiment  # noqa: E402
from hireps_torch.experiments.pendulum import PendulumConfig  # noqa: E402


def separate_results(folder: Path) -> dict[int, float]:
    """Final success per seed of a finished pendulum sweep (its ``sweep.json``)."""
    path = next(folder.rglob("sweep.json"), None)
    if path is None:
        raise SystemExit(f"--separate {folder}: no sweep.json below it")
    data = json.loads(path.read_text())
    return {int(v["seed"]): float(v["success_rate"]) for v in data.values()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--episodes", type=int, default=PendulumConfig.episodes)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "population_benchmark")
    ap.add_argument("--separate", type=Path, default=None, help="a finished pendulum sweep")
    ap.add_argument("--run-separate", action="store_true", help="run the separate sweep here")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    ap.add_argument(
        "--workers", type=int, default=cores or 1, help="processes of the sweep (default: cores)"
    )
    args = ap.parse_args()
    out = start_benchmark(args.out, args.seeds, args.threads)
    import torch

    print(f"torch threads: {torch.get_num_threads()}")
    S = args.seeds

    def one_seed(folder: str) -> tuple[float, dict[str, Any]]:
        cfg = PendulumConfig(episodes=args.episodes, seed=0, run_dir=out / folder, progress=False)
        t = time.perf_counter()
        result = run_experiment(cfg)
        return time.perf_counter() - t, result

    t_before, one = one_seed("one")
    t = time.perf_counter()
    pop = run_experiment(
        PendulumConfig(
            episodes=args.episodes, seeds=f"0-{S - 1}", run_dir=out / "population", progress=False
        )
    )
    t_pop = time.perf_counter() - t
    t_sweep = math.nan
    if args.workers > 0:
        from hireps_torch.experiments.sweep import plan, run_sweep

        members = -(-S // args.workers)
        pops = plan(
            "pendulum",
            {"default": {"episodes": args.episodes}},
            list(range(S)),
            out / "sweep",
            members,
        )
        t = time.perf_counter()
        run_sweep(pops, workers=args.workers, progress=False)
        t_sweep = time.perf_counter() - t
    t_after, _ = one_seed("one_after")  # the machine's speed drifts: one seed on either side
    t_one = (t_before + t_after) / 2
    print(
        f"one seed ({args.episodes} episodes): {t_before:.1f} s before, {t_after:.1f} s after "
        f"the population (success {one['success_rate']})"
    )
    print(
        f"population of {S} seeds: {t_pop:.1f} s = {t_pop / t_one:.2f} x one seed (their mean; "
        f"{t_pop / max(t_before, t_after):.2f}-{t_pop / min(t_before, t_after):.2f} x either)"
    )
    if args.workers > 0:
        print(
            f"the same seeds as {len(pops)} population(s) of at most {members} on "
            f"{args.workers} worker(s) (train.py sweep --members {members} --workers "
            f"{args.workers}): {t_sweep:.1f} s = {t_sweep / t_one:.2f} x one seed"
        )

    success = {int(k): float(v) for k, v in pop["per_seed"].items()}
    good = sum(v >= 0.9 for v in success.values())
    print(f"population: {good}/{S} seeds end with success >= 0.9")
    print("  " + ", ".join(f"{s}: {v:.2f}" for s, v in success.items()))
    separate = None
    if args.run_separate:
        from hireps_torch.experiments.sweep import SweepConfig
        from hireps_torch.experiments.sweep import main as sweep

        folder = out / "separate"
        sweep(
            SweepConfig(
                experiment="pendulum",
                seeds=f"0-{S - 1}",
                set=(f"episodes={args.episodes}",),
                out=folder,
                workers=2,
                progress=False,
            )
        )
        separate = separate_results(folder)
    elif args.separate is not None:
        separate = separate_results(args.separate)
    report: dict[str, Any] = {
        "seeds": S,
        "episodes": args.episodes,
        "one_seed_seconds": t_one,
        "one_seed_seconds_before_after": [t_before, t_after],
        "population_seconds": t_pop,
        "ratio": t_pop / t_one,
        "sweep_workers": args.workers,
        "sweep_seconds": t_sweep,
        "sweep_ratio": t_sweep / t_one,
        "population_success": success,
    }
    if separate is not None:
        from scipy.stats import fisher_exact

        sep_good = sum(separate.get(s, 0.0) >= 0.9 for s in success)
        table = [[good, S - good], [sep_good, S - sep_good]]
        p = float(fisher_exact(table).pvalue)
        print(f"separate runs: {sep_good}/{S} seeds end with success >= 0.9")
        print("  " + ", ".join(f"{s}: {separate.get(s, float('nan')):.2f}" for s in success))
        print(f"Fisher's exact test, population vs separate: p = {p:.3f}")
        report |= {"separate_success": separate, "fisher_p": p}
    (out / "results.json").write_text(json.dumps(report, indent=1))
    print(f"written to {out}")


if __name__ == "__main__":
    main()
