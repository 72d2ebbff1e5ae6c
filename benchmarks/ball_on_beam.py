"""Ball on a beam (HiREPS paper, Fig 19): learning over seeds, episodes to success, wall time.

Runs ``train.py ball-on-beam`` (30 episodes, 3 per iteration, 5 options) for ``--seeds``
seeds and

- prints, per seed, the number of episodes after which the noise-free policy first succeeded
  (success: at least 90% of 10 evaluation episodes with the ball within 3 cm of a goal for the
  last 5 s; the evaluation runs after every iteration), the final success rate and the run's
  wall time;
- writes ``learning_curve.png`` (average return per episode against episodes, mean and ±1 std
  band over seeds), ``episode.png`` (ball position over time in one noise-free episode from
  each side of the first seed that succeeded, goals and tolerance marked), ``results.json``
  and ``results.md`` to ``--out``.

    OMP_NUM_THREADS=1 python benchmarks/ball_on_beam.py [--seeds 10] [--out DIR]
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
from hireps_torch.envs.ball_on_beam import BeamParams, evaluate_beam  # noqa: E402
from hireps_torch.experiments.ball_on_beam import BallOnBeamConfig, build_ball_on_beam_policy  # noqa: E402
from hireps_torch.experiments.ball_on_beam import run as run_ball_on_beam  # noqa: E402
from hireps_torch.experiments.rundir import atomic_write  # noqa: E402
from hireps_torch.policies import HierarchicalPolicy  # noqa: E402


def plot_curves(results: list[dict[str, Any]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    x = results[0]["episodes_axis"]
    plot_band(axes[0], x, [r["curve"] for r in results], "training (with exploration)")
    plot_band(axes[0], x, [r["eval_curve"] for r in results], "noise-free policy")
    axes[0].set_xlabel("episodes")
    axes[0].set_ylabel("average return per episode")
    axes[0].set_ylim(bottom=max(-400.0, axes[0].get_ylim()[0]))
    axes[0].legend(fontsize=8)
    axes[0].set_title(f"ball on a beam ({len(results)} seeds, mean ± std)")
    plot_band(axes[1], x, [r["success_curve"] for r in results], "success rate")
    axes[1].set_xlabel("episodes")
    axes[1].set_ylabel("evaluation success rate")
    axes[1].set_ylim(-0.05, 1.05)
    fig.tight_layout()
    atomic_write(out / "learning_curve.png", lambda p: fig.savefig(p, format="png", dpi=110))
    plt.close(fig)


def plot_episode(run: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = BeamParams()
    cfg = BallOnBeamConfig(seed=run["seed"])
    policy = HierarchicalPolicy.stack([build_ball_on_beam_policy(cfg)])  # a run of one seed
    ckpt = torch.load(Path(run["run_dir"]) / "checkpoint.pt")
    policy.load_state_dict(ckpt["algorithm"]["policy"])
    policy = policy.member(0)
    ev = evaluate_beam(lambda s: policy.mean_action(s)[0], p, n_episodes=2, seed=0)
    t = p.dt * torch.arange(1, ev.positions.shape[1] + 1)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for i, label in enumerate(("start right", "start left")):
        ax.plot(t.numpy(), ev.positions[i].numpy(), label=label)
    for g in (-p.goal, p.goal):
        ax.axhspan(g - 0.03, g + 0.03, color="green", alpha=0.15)
        ax.axhline(g, color="green", lw=0.8)
    ax.axvspan(p.episode_seconds - 5.0, p.episode_seconds, color="grey", alpha=0.1)
    ax.axhline(p.half_length, color="k", lw=0.8, ls="--")
    ax.axhline(-p.half_length, color="k", lw=0.8, ls="--")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("ball position (m)")
    ax.set_title(
        f"seed {run['seed']}, {run['episodes']} episodes: goals ± 3 cm green, last 5 s grey",
        fontsize=10,
    )
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    atomic_write(out / "episode.png", lambda q: fig.savefig(q, format="png", dpi=110))
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--episodes", type=int, default=BallOnBeamConfig.episodes)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "ball_on_beam_benchmark")
    add_figures_option(ap)
    args = ap.parse_args()
    out = start_benchmark(args.out, args.seeds)

    results: list[dict[str, Any]] = []
    t_all = time.perf_counter()
    for seed in range(args.seeds):
        run_dir = out / "runs" / f"seed{seed}"
        cfg = BallOnBeamConfig(seed=seed, episodes=args.episodes, progress=False, run_dir=run_dir)
        summary = run_ball_on_beam(cfg)
        x, y = read_curve(run_dir)
        _, ev = read_curve(run_dir, "eval_return")
        _, sc = read_curve(run_dir, "eval_success_rate")
        results.append(
            {
                **summary,
                "run_dir": str(run_dir),
                "curve": y,
                "eval_curve": ev,
                "success_curve": sc,
                "episodes_axis": x,
            }
        )
        reached = summary["episodes_to_success"]
        print(
            f"  seed {seed}: first success after "
            f"{'-' if reached is None else reached:>2} episodes, final success "
            f"{summary['success_rate']:.2f}, final eval return "
            f"{summary['final_eval_return']:7.2f}, {summary['wall_seconds']:.1f} s",
            flush=True,
        )
    total = time.perf_counter() - t_all

    reached = [r["episodes_to_success"] for r in results]
    n_ok = sum(e is not None for e in reached)
    walls = [r["wall_seconds"] for r in results]
    table = "\n".join(
        [
            "| seeds | reached success within "
            f"{args.episodes} episodes | episodes to first success (per seed) | final success "
            "rate | final eval return | s/run (mean, max) |",
            "|--:|--:|---|--:|--:|--:|",
            f"| {len(results)} | {n_ok}/{len(results)} | "
            f"{', '.join('-' if e is None else str(e) for e in reached)} | "
            f"{mean_std([r['success_rate'] for r in results])} | "
            f"{mean_std([r['final_eval_return'] for r in results])} | "
            f"{statistics.mean(walls):.1f}, {max(walls):.1f} |",
        ]
    )
    print(table)
    print(f"seeds that reached success within {args.episodes} episodes: {n_ok}/{len(results)}")
    print(
        f"wall time per {args.episodes}-episode run: mean {statistics.mean(walls):.1f} s, "
        f"max {max(walls):.1f} s; all seeds {total:.1f} s"
    )
    plot_curves(results, out)
    shown = next((r for r in results if r["episodes_to_success"] is not None), results[0])
    plot_episode(shown, out)
    write_results(out, results, total, table)
    publish(
        args.figures,
        {
            "fig19_ball_on_beam.png": out / "learning_curve.png",
            "fig19_episode.png": out / "episode.png",
        },
    )


if __name__ == "__main__":
    main()
