"""Robot hockey on Ray: one hockey-sequential run with 1 local worker against the same run
with W Ray workers, side by side in one process.

Measures, per run: the wall time, the time spent playing episodes (inside the episode pool)
and the rest of each iteration (the update, logging, checkpoint). From those parts:

- simulation time per episode (1 local worker: play time / episodes);
- Ray overhead per iteration: the W-worker play time per iteration minus the ideal share of
  the 1-worker play time (ceil(B / W) episodes per worker), after the first iteration (the
  first one also starts Ray's worker processes and their pybullet environments: reported
  separately as start-up);
- a projection of the wall time for 8, 32 and 128 workers,
  ``startup + iterations * (ceil(B / N) * t_episode + overhead + update)``, and the worker
  count from which the update costs more than the simulation of an iteration.

It checks that both runs wrote the same ``metrics.csv``, prints the wall-time ratio and writes
``results.json`` / ``results.md`` to ``--out``.

    OMP_NUM_THREADS=1 python benchmarks/distributed_hockey.py [--episodes 1500] [--workers 2]
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("MKL_CBWR", "COMPATIBLE")  # before torch (experiments/workers.py)
import math
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import start_benchmark, write_results  # noqa: E402
from hireps_torch.experiments import hockey  # noqa: E402


class TimedPool:
    """An episode pool that records the wall time of every ``play`` call."""

    def __init__(self, pool: Any) -> None:
        self.pool = pool
        self.workers = pool.workers
        self.times: list[float] = []

    def play(self, *args: Any, **kwargs: Any) -> Any:
        t = time.perf_counter()
        out = self.pool.play(*args, **kwargs)
        self.times.append(time.perf_counter() - t)
        return out

    def close(self) -> None:
        self.pool.close()


def timed_run(cfg: hockey.HockeySequentialConfig) -> dict[str, Any]:
    """Run ``cfg`` with its pool timed; returns wall time and play times per iteration."""
    pools: list[TimedPool] = []
    real = hockey.make_pool

    def make_timed(*args: Any, **kwargs: Any) -> TimedPool:
        pools.append(TimedPool(real(*args, **kwargs)))
        return pools[-1]

    hockey.make_pool = make_timed  # type: ignore[assignment]
    try:
        t = time.perf_counter()
        summary = hockey.run(cfg)
        wall = time.perf_counter() - t
    finally:
        hockey.make_pool = real
    return {"wall": wall, "play": pools[0].times, "summary": summary}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--episodes", type=int, default=1500)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "distributed_hockey")
    args = ap.parse_args()
    out = start_benchmark(args.out, 1)
    W = args.workers
    common = dict(seed=args.seed, episodes=args.episodes, progress=False)
    runs = {}
    for name, extra in (
        ("local, 1 worker", dict(workers=1, backend="local")),
        (f"ray, {W} workers", dict(workers=W, backend="ray")),
    ):
        run_dir = out / name.replace(", ", "_")
        cfg = hockey.HockeySequentialConfig(run_dir=run_dir, **common, **extra)
        runs[name] = r = timed_run(cfg)
        print(
            f"{name:16s}: {r['wall']:7.1f} s wall, {sum(r['play']):7.1f} s playing episodes, "
            f"final average reward {r['summary']['final_average_reward']:.3f}",
            flush=True,
        )
    one, many = runs.values()
    same = (out / "local_1 worker" / "metrics.csv").read_text() == (
        out / f"ray_{W} workers" / "metrics.csv"
    ).read_text()
    B = hockey.HockeySequentialConfig.episodes_per_iteration
    iters = len(one["play"])
    t_episode = sum(one["play"]) / (iters * B)
    update = (one["wall"] - sum(one["play"])) / iters
    ideal = math.ceil(B / W) * t_episode
    overhead = sum(many["play"][1:]) / (iters - 1) - ideal
    startup = many["play"][0] - ideal
    ratio = many["wall"] / one["wall"]

    def projected(n: int) -> float:
        return startup + iters * (math.ceil(B / n) * t_episode + overhead + update)

    bound = next((n for n in range(1, B + 1) if math.ceil(B / n) * t_episode < update), None)
    lines = [
        f"| hockey-sequential, {args.episodes} episodes, seed {args.seed} | wall (s) | ratio |",
        "|---|--:|--:|",
        f"| 1 local worker (measured) | {one['wall']:.1f} | 1.00 |",
        f"| {W} Ray workers (measured) | {many['wall']:.1f} | {ratio:.2f} |",
    ]
    for n in (8, 32, 128):
        p = projected(n)
        lines.append(f"| {n} Ray workers (projected) | {p:.1f} | {p / one['wall']:.2f} |")
    table = "\n".join(lines)
    print(table)
    print(
        f"same metrics.csv: {same}; simulation {1000 * t_episode:.1f} ms per episode; update + "
        f"logging {1000 * update:.1f} ms per iteration; Ray overhead {1000 * overhead:.1f} ms per "
        f"iteration ({W} tasks); Ray start-up {startup:.1f} s"
    )
    if bound is None:
        print(f"the update stays below an iteration's simulation up to {B} workers")
    else:
        print(
            f"from {bound} workers on, the update ({1000 * update:.0f} ms) costs more than an "
            f"iteration's simulation ({math.ceil(B / bound)} episode(s) per worker); beyond "
            f"{B} workers (episodes per iteration) nothing more is gained"
        )
    results = {
        "same_metrics": same,
        "wall_one": one["wall"],
        "wall_many": many["wall"],
        "ratio": ratio,
        "workers": W,
        "seconds_per_episode": t_episode,
        "update_seconds_per_iteration": update,
        "ray_overhead_seconds_per_iteration": overhead,
        "ray_startup_seconds": startup,
        "projected": {n: projected(n) for n in (8, 32, 128)},
        "update_bound_workers": bound,
    }
    write_results(out, results, one["wall"] + many["wall"], table)


if __name__ == "__main__":
    main()
