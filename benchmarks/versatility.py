"""Does each algorithm find, and keep, the tasks' distinct solutions? (issue 70)

Every algorithm on every task with several solutions, as one population of ``--seeds`` per
(task, algorithm), on the same seeds and episode budgets; prints per task and algorithm:

* success: the share of the final policy's samples that solve the task (mean over seeds);
* purity, solutions held at the end and at the first iteration whose samples succeed half of
  the time, behaviour entropy (:mod:`hireps_torch.versatility`; means over seeds);
* reached: the seeds whose exploring policy's mean return reached the task's threshold, and
  the median episodes until then (seeds that never reached it count as never).

Intervals: 95% bootstrap over seeds for means and medians (``scipy.stats.bootstrap``), Wilson
for shares of seeds. Seeds 20-39 by default: settings were chosen on seeds 0-9.

    python benchmarks/versatility.py [--seeds 20-39] [--tasks planar-arm,tetherball]
        [--out benchmarks/results/versatility] [--figures docs/figures]

A run directory that finished is reused, so an interrupted benchmark goes on where it stopped.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from scipy import stats

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import add_figures_option, publish  # noqa: E402
from hireps_torch.experiments import EXPERIMENTS  # noqa: E402
from hireps_torch.experiments.options import parse_seeds  # noqa: E402

HIREPS = ("hireps", "hireps-unbounded", "hireps-versatile")
# task -> (experiment, its options, algorithms, return threshold of the exploring policy)
TASKS: dict[str, tuple[str, dict[str, Any], tuple[str, ...], float]] = {
    "bimodal": ("bimodal", {}, (*HIREPS, "reps", "cmaes"), 0.9),
    "bimodal-12000": ("bimodal", {"episodes": 12000}, (*HIREPS, "reps", "cmaes"), 0.9),
    "planar-arm": ("planar-arm", {}, (*HIREPS, "reps", "cmaes"), -0.5),
    "tetherball": ("tetherball", {}, (*HIREPS, "reps"), -0.03),
}


def wilson(k: int, n: int) -> tuple[float, float]:
    """95% Wilson interval of a share of k in n."""
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


NEVER = 1e12  # an infinite value (never reached) while resampling: a median may be "never"


def bootstrap(values: list[float], statistic: Any = np.mean) -> tuple[float, float, float]:
    """The statistic over seeds and its 95% bootstrap interval (percentile; a constant sample
    gives a zero-width interval); inf values stay inf."""
    x = np.minimum(np.asarray(values, dtype=np.float64), NEVER)
    point = float(statistic(x))
    if len(x) < 2 or np.all(x == x[0]):
        low = high = point
    else:
        ci = stats.bootstrap(
            (x,), statistic, confidence_level=0.95, method="percentile", random_state=0
        ).confidence_interval
        low, high = float(ci.low), float(ci.high)
    return tuple(math.inf if v >= NEVER / 2 else v for v in (point, low, high))  # type: ignore[return-value]


def cmaes_popsize(param_dim: int) -> int:
    """pycma's default population size, 4 + floor(3 ln D): what a CMA-ES user gets."""
    return 4 + int(3 * math.log(param_dim))


def run_population(task: str, algorithm: str, seeds: str, out: Path) -> Path:
    """The population's run directory, run now unless it finished before (CMA-ES with
    pycma's default population size, in the same episode budget)."""
    name, options, _, _ = TASKS[task]
    if algorithm == "cmaes":
        D = EXPERIMENTS[name].algorithm(EXPERIMENTS[name].config(algorithm="cmaes")).param_dim
        options = {**options, "samples_per_iteration": cmaes_popsize(D)}
    run_dir = out / task / algorithm
    if (run_dir / "summary.json").exists():
        return run_dir
    entry = EXPERIMENTS[name]
    resume = run_dir if (run_dir / "checkpoint.pt").exists() else None
    cfg = entry.config(
        algorithm=algorithm,
        seeds=seeds,
        run_dir=None if resume else run_dir,
        resume=resume,
        progress=True,
        checkpoint_every=25,  # CMA-ES's many short iterations: a checkpoint each would dominate
        **options,
    )
    t0 = time.perf_counter()
    entry.run(cfg)
    print(f"  {task}/{algorithm}: {time.perf_counter() - t0:.0f} s", flush=True)
    return run_dir


def member_results(run_dir: Path, seeds: list[int], threshold: float) -> dict[str, list[float]]:
    """Per seed: the final versatility measures, solutions at first success and episodes to
    the threshold (inf: never), and the curve of solutions held."""
    out: dict[str, list[Any]] = {
        k: []
        for k in (
            "success_rate",
            "purity",
            "solutions_found",
            "solutions_at_first_success",
            "behaviour_entropy",
            "episodes_to_threshold",
            "curve",
            "episodes",
        )
    }
    for s in seeds:
        rows = list(csv.DictReader((run_dir / f"seed{s}" / "metrics.csv").open()))
        last = rows[-1]
        for k in ("success_rate", "purity", "solutions_found", "behaviour_entropy"):
            out[k].append(float(last[k]))
        first = next((r for r in rows if float(r["success_rate"]) >= 0.5), None)
        out["solutions_at_first_success"].append(
            math.nan if first is None else float(first["solutions_found"])
        )
        reached = next((r for r in rows if float(r["mean_return"]) >= threshold), None)
        out["episodes_to_threshold"].append(
            math.inf if reached is None else float(reached["episodes"])
        )
        out["curve"].append([float(r["solutions_found"]) for r in rows])
        out["episodes"] = [float(r["episodes"]) for r in rows]
    return out


def interval(values: list[float], digits: int = 2, statistic: Any = np.mean) -> str:
    kept = [v for v in values if not math.isnan(v)]
    if not kept:
        return "-"
    point, low, high = bootstrap(kept, statistic)
    if math.isinf(point):
        return "never"
    high_text = "never" if math.isinf(high) else f"{high:.{digits}f}"
    return f"{point:.{digits}f} [{low:.{digits}f}, {high_text}]"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", default="20-39")
    ap.add_argument("--tasks", default=",".join(TASKS))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "versatility")
    add_figures_option(ap)
    args = ap.parse_args()
    seeds = parse_seeds(args.seeds)
    tasks = [t.strip() for t in args.tasks.split(",")]
    if unknown := [t for t in tasks if t not in TASKS]:
        raise SystemExit(f"unknown tasks {unknown}; choose from {', '.join(TASKS)}")
    n = len(seeds)
    header = (
        "| task | algorithm | success | purity | held at end | held at first success | "
        "behaviour entropy | reached threshold | episodes to threshold (median) |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    lines, results, made = [header], {}, {}
    for task in tasks:
        _, _, algorithms, threshold = TASKS[task]
        fig = Figure(figsize=(6, 4))
        ax = fig.subplots()
        for algorithm in algorithms:
            run_dir = run_population(task, algorithm, args.seeds, args.out)
            r = member_results(run_dir, seeds, threshold)
            results[f"{task}/{algorithm}"] = {k: v for k, v in r.items() if k != "curve"}
            k = sum(math.isfinite(e) for e in r["episodes_to_threshold"])
            lo, hi = wilson(k, n)
            lines.append(
                f"| {task} | {algorithm} | {interval(r['success_rate'])} | "
                f"{interval(r['purity'])} | {interval(r['solutions_found'])} | "
                f"{interval(r['solutions_at_first_success'])} | "
                f"{interval(r['behaviour_entropy'])} | {k}/{n} [{lo:.2f}, {hi:.2f}] | "
                f"{interval(r['episodes_to_threshold'], 0, np.median)} |"
            )
            curves = np.asarray(r["curve"])
            mean = curves.mean(0)
            boot = [curves[np.random.default_rng(b).integers(0, n, n)].mean(0) for b in range(1000)]
            low, high = np.percentile(boot, [2.5, 97.5], axis=0)
            ax.plot(r["episodes"], mean, label=algorithm)
            ax.fill_between(r["episodes"], low, high, alpha=0.2)
        ax.set_xlabel("episodes")
        ax.set_ylabel("solutions held")
        ax.set_title(f"{task}: mean over {n} seeds, 95% bootstrap band")
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = args.out / f"solutions_held_{task}.png"
        fig.savefig(path, dpi=110)
        made[path.name] = path
    table = "\n".join(lines)
    print(table)
    (args.out / "results.md").write_text(table + "\n")
    (args.out / "results.json").write_text(json.dumps(results, default=str) + "\n")
    publish(args.figures, made)


if __name__ == "__main__":
    main()
