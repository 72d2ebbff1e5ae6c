"""Pendulum swing-up ablations of the HiREPS paper (Figs 16a, 16b, 17, 18), plus env speed.

1. Speed of the batched pendulum (``PendulumSwingUpBatchEnv.step``, one decision of d = 5
   control steps per call) at 20, 200 and 2000 parallel pendulums, next to gymnasium's own
   ``Pendulum-v1`` stepped in a Python loop, measured in the same run (control steps/s).
2. ``train.py pendulum`` for every configuration of the four figures over ``--seeds`` seeds
   (each unique configuration runs once per seed and is shared between figures), as one sweep
   (:mod:`hireps_torch.experiments.sweep`, one thread per run) in which each configuration's
   seeds run as one population (``--members``: ``train.py pendulum --seeds 0-4``, one batched
   simulation), or with ``--separate`` as separate runs: ``--workers`` at a time (2 by
   default; the slow configurations first), in local processes each held to cores of its own,
   or (``--backend ray``) as Ray tasks, on this machine or a cluster (``--ray-address``).
   ``--resume`` of an interrupted ablation reuses what finished and resumes the rest:

   - 16a: options 1 / 2 / 5 / 10 (d = 5)
   - 16b: d = 1 / 2 / 5 / 10 (5 options)
   - 17:  constant k-means gating with 5 / 20 / 100 options vs learned gating with 5
   - 18:  flat policy on the gating features vs 1 vs 5 options

Writes ``results.json`` (every run's curve and summary), ``results.md`` (mean +- std of the
final average return and the final success rate per configuration, the seeds that end with
success >= 0.9, and per seed the episodes after which the noise-free policy first reached it,
evaluated every 5 iterations) and one PNG per figure (mean
curve with a +-1 std band) to ``--out``; prints the table, the wall time of each standard
run and of the whole ablation.

    python benchmarks/pendulum_ablations.py [--seeds 5] [--out DIR]
    OMP_NUM_THREADS=1 python benchmarks/pendulum_ablations.py --separate [--workers 2]
        [--backend local|ray]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import (  # noqa: E402
    add_figures_option,
    mean_std,
    plot_band,
    publish,
    read_curve,
    start_benchmark,
    write_results,
)
from hireps_torch.envs.pendulum import PendulumSwingUpBatchEnv  # noqa: E402
from hireps_torch.experiments.pendulum import PendulumConfig  # noqa: E402
from hireps_torch.experiments.rundir import atomic_write  # noqa: E402
from hireps_torch.experiments.sweep import SweepRun, plan, run_sweep  # noqa: E402

CONFIGS: dict[str, dict[str, Any]] = {
    "learned-1": {"n_options": 1},
    "learned-2": {"n_options": 2},
    "learned-5": {"n_options": 5},
    "learned-10": {"n_options": 10},
    "d1": {"steps_per_decision": 1},
    "d2": {"steps_per_decision": 2},
    "d10": {"steps_per_decision": 10},
    "constant-5": {"gating": "constant", "n_options": 5},
    "constant-20": {"gating": "constant", "n_options": 20},
    "constant-100": {"gating": "constant", "n_options": 100},
    "flat": {"gating": "flat"},
}
FIGURES: dict[str, list[tuple[str, str]]] = {
    "fig16a_options": [
        ("1 option", "learned-1"),
        ("2 options", "learned-2"),
        ("5 options", "learned-5"),
        ("10 options", "learned-10"),
    ],
    "fig16b_steps_per_decision": [
        ("d = 1", "d1"),
        ("d = 2", "d2"),
        ("d = 5", "learned-5"),
        ("d = 10", "d10"),
    ],
    "fig17_constant_gating": [
        ("constant, 5", "constant-5"),
        ("constant, 20", "constant-20"),
        ("constant, 100", "constant-100"),
        ("learned, 5", "learned-5"),
    ],
    "fig18_flat_policy": [("flat", "flat"), ("1 option", "learned-1"), ("5 options", "learned-5")],
}


def env_speed() -> None:
    """Control steps per second: batched torch pendulum vs gymnasium Pendulum-v1 in a loop."""
    import gymnasium as gym

    print("environment speed (control steps/s, one process, one thread)")
    for B in (20, 200, 2000):
        env = PendulumSwingUpBatchEnv(B, seed=0)
        td = env.reset()
        td["action"] = torch.zeros(B, 1)
        n = 100
        t = time.perf_counter()
        for _ in range(n):
            td = env.step(td)["next"].clone()
            td["action"] = torch.zeros(B, 1)
        dt = time.perf_counter() - t
        steps = n * B * env.params.steps_per_decision
        print(f"  batched torch env, B = {B:>4}: {steps / dt:>12,.0f}")
    genv = gym.make("Pendulum-v1")
    genv.reset(seed=0)
    a = genv.action_space.sample()
    n = 20000
    t = time.perf_counter()
    for _ in range(n):
        genv.step(a)
    dt = time.perf_counter() - t
    print(f"  gymnasium Pendulum-v1 loop : {n / dt:>12,.0f}")


def plot_figure(name: str, lines: list[tuple[str, str]], results: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for label, key in lines:
        curves = [r["curve"] for r in results[key]]
        plot_band(ax, results[key][0]["episodes_axis"], curves, label)
    ax.set_xlabel("episodes")
    ax.set_ylabel("average return (per control step)")
    ax.set_title(f"{name} ({len(results[lines[0][1]])} seeds, mean ± std)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    atomic_write(out / f"{name}.png", lambda p: fig.savefig(p, format="png", dpi=110))
    plt.close(fig)


def _first(summary: dict[str, Any]) -> str:
    """Episodes to the first evaluation with success >= 0.9 ('-': never; evaluations every
    ``eval_every`` iterations of the run)."""
    first = summary.get("episodes_to_success")
    return "-" if first is None else str(first)


# rough run time relative to the standard configuration, to start the slow runs first
SLOWNESS = {"d1": 7.0, "d2": 2.7, "learned-10": 1.4}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--episodes", type=int, default=PendulumConfig.episodes)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "pendulum_ablations")
    add_figures_option(ap)
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS), help="subset to run")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument(
        "--separate",
        action="store_true",
        help="run every seed as its own run instead of each configuration's seeds as one "
        "population (train.py pendulum --seeds)",
    )
    ap.add_argument(
        "--workers",
        type=int,
        default=2,
        help="runs (populations, or with --separate runs) at the same time, one process each",
    )
    ap.add_argument("--backend", choices=["local", "ray"], default="local")
    ap.add_argument("--ray-address", default=None, help="an existing Ray cluster (--backend ray)")
    ap.add_argument(
        "--resume", type=Path, default=None, help="finish the ablation written to this folder"
    )
    args = ap.parse_args()
    if args.workers < 1:
        raise SystemExit(f"--workers must be >= 1, got {args.workers}")
    torch.set_num_threads(1)  # as each run of the sweep computes
    out = args.resume if args.resume is not None else start_benchmark(args.out, args.seeds)
    if not args.skip_speed:
        env_speed()

    configs = list(dict.fromkeys(args.configs))  # each once: runs write to their own dirs
    unknown = [k for k in configs if k not in CONFIGS]
    if unknown:
        raise SystemExit(f"unknown configurations {unknown}; known: {', '.join(CONFIGS)}")
    options = {k: {**CONFIGS[k], "episodes": args.episodes} for k in configs}
    members = 1 if args.separate else args.seeds
    runs = plan("pendulum", options, list(range(args.seeds)), out / "runs", members)
    # the slow configurations first, so that the last runs to finish are short ones
    runs.sort(key=lambda r: -SLOWNESS.get(r.name, 1.0))

    def report(run: SweepRun, summary: dict[str, Any]) -> None:
        print(
            f"  {run.name:<13} seed {run.seed}: final average return "
            f"{summary['final_average_return']:7.1f}, first success after "
            f"{_first(summary):>5} episodes, final success {summary['success_rate']:.2f}, "
            f"{summary['wall_seconds']:.1f} s",
            flush=True,
        )

    t_all = time.perf_counter()
    done = run_sweep(
        runs,
        backend=args.backend,
        workers=args.workers,
        ray_address=args.ray_address,
        progress=False,
        on_result=report,
    )
    for run in (member for r in runs for member in r.members()):
        x, y = read_curve(run.run_dir)
        done[(run.name, run.seed)] = {**done[(run.name, run.seed)], "curve": y, "episodes_axis": x}
    total = time.perf_counter() - t_all
    results = {k: [done[(k, s)] for s in range(args.seeds)] for k in configs}

    lines = [
        "| configuration | final average return | final success rate | seeds ending with "
        "success >= 0.9 | first success >= 0.9 (episodes, per seed) | s/run |",
        "|---|--:|--:|--:|---|--:|",
    ]
    for key, runs in results.items():
        succ = [r["success_rate"] for r in runs]
        lines.append(
            f"| {key} | {mean_std([r['final_average_return'] for r in runs])} | "
            f"{mean_std(succ)} | {sum(s >= 0.9 for s in succ)}/{len(succ)} | "
            f"{', '.join(_first(r) for r in runs)} | "
            f"{statistics.mean(r['wall_seconds'] for r in runs):.1f} |"
        )
    table = "\n".join(lines)
    print(table)
    std_runs = results.get("learned-5", [])
    if std_runs:
        walls = ", ".join(f"{r['wall_seconds']:.1f}" for r in std_runs)
        print(f"standard configuration (5 options, d = 5, {args.episodes} episodes): {walls} s")
    print(f"whole ablation: {total / 60:.1f} min for {sum(map(len, results.values()))} runs")
    drawn = [name for name, lines in FIGURES.items() if all(k in results for _, k in lines)]
    for name in drawn:
        plot_figure(name, FIGURES[name], results, out)
    write_results(out, results, total, table)
    publish(args.figures, {f"{name}.png": out / f"{name}.png" for name in drawn})


if __name__ == "__main__":
    main()
