"""Wall time of pendulum populations of growing size on one device (a GPU where one is lent).

For each size S in ``--sizes``: ``train.py pendulum --seeds 0-(S-1) --device DEVICE`` (S = 1:
``--seed 0``), the same episodes, one after the other in this run. Prints seconds, seconds
per member and the ratio to the first size, with the share of members ending with success
>= 0.9, and where the time went: the algorithm's updates (the duals and refits), the
noise-free evaluations, the learning-curve plots, and the rest (the collector's stepping,
checkpoints). results.json is rewritten after each size, so a run cut short keeps what it
measured.

    python benchmarks/population_scaling.py [--device cuda] [--sizes 1,100,1000]
        [--episodes 1000] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import start_benchmark  # noqa: E402
from hireps_torch.experiments import run_experiment  # noqa: E402
from hireps_torch.experiments.pendulum import PendulumConfig  # noqa: E402
from hireps_torch.experiments.rundir import atomic_write  # noqa: E402


class Stopwatch:
    """Seconds spent in the wrapped functions, by name (wrapped where the run looks them up)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def wrap(self, owner: object, attr: str, name: str) -> None:
        fn = getattr(owner, attr)

        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t

        setattr(owner, attr, timed)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", default="1,100,1000", help="population sizes, comma-separated")
    ap.add_argument("--episodes", type=int, default=PendulumConfig.episodes)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "population_scaling")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    out = start_benchmark(args.out, min(sizes), args.threads)
    import torch

    dev = torch.device(args.device)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    print(f"torch {torch.__version__}, device {dev} ({name}), threads {torch.get_num_threads()}")
    from hireps_torch.algorithms import InfiniteHorizonHiREPS
    from hireps_torch.experiments import loop, pendulum

    watch = Stopwatch()
    watch.wrap(InfiniteHorizonHiREPS, "update", "updates")
    watch.wrap(pendulum, "evaluate_swing_up", "evaluations")
    watch.wrap(loop, "plot_learning_curves", "plots")
    report: dict = {"device": str(dev), "device_name": name, "episodes": args.episodes, "runs": []}
    for S in sizes:
        seeds = {"seed": 0} if S == 1 else {"seeds": f"0-{S - 1}"}
        cfg = PendulumConfig(
            episodes=args.episodes,
            device=args.device,
            run_dir=out / f"S{S}",
            progress=False,
            **seeds,
        )
        watch.seconds.clear()
        t = time.perf_counter()
        result = run_experiment(cfg)
        seconds = time.perf_counter() - t
        parts = dict(watch.seconds)
        parts["rest"] = seconds - sum(parts.values())
        success = result["per_seed"].values() if "per_seed" in result else [result["success_rate"]]
        good = sum(float(v) >= 0.9 for v in success)
        first = report["runs"][0]["seconds"] if report["runs"] else seconds
        report["runs"].append({"members": S, "seconds": seconds, "succeeded": good, **parts})
        print(
            f"S = {S:5d}: {seconds:7.1f} s, {seconds / S:.3f} s per member, "
            f"{seconds / first:.2f} x S = {sizes[0]}; {good}/{S} end with success >= 0.9\n    "
            + ", ".join(f"{k} {v:.1f} s" for k, v in parts.items()),
            flush=True,
        )
        atomic_write(out / "results.json", lambda p: p.write_text(json.dumps(report, indent=1)))
    print(f"written to {out}")


if __name__ == "__main__":
    main()
