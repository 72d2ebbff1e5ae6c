"""Robot hockey (HiREPS paper, Fig 14): sequential vs episodic HiREPS, simulation cost, pictures.

1. Simulation cost: ``--timing-episodes`` episodes of the demo shot with exploration noise,
   stepped through the gymnasium env in this process: seconds per shot and per episode.
2. Learning: ``train.py hockey-sequential`` and ``train.py hockey-episodic`` (1500 episodes,
   30 per iteration, 5 options) for ``--seeds`` seeds each; per run the last iteration's
   average reward (mean episode reward over its 30 samples), the final policy's average
   reward on ``--final-eval-episodes`` (200) fresh episodes with its exploration and without
   (noise-free), the share of
   the last iteration's episodes ending in zone 3, and the wall time.
   Also the real robot's setting (Fig 15b, ``train.py hockey-fixed-start``: a fixed start,
   10 episodes per update, 300 episodes) for the same seeds.
3. Writes to ``--out``: ``learning_curve.png`` (average reward per episode against episodes,
   mean and ±1 std band over seeds, both variants), ``fig15b_fixed_start.png``,
   ``episode.png`` (a strip of frames of one noise-free episode of the learned sequential
   policy, seed 0) and ``episode.gif``,
   ``results.json`` and ``results.md``.

    OMP_NUM_THREADS=1 python benchmarks/hockey_learning.py [--seeds 5] [--episodes 1500]
        [--workers 2] [--final-eval-episodes 200] [--backend local|ray]
        [--ray-address ADDR] [--resume DIR]

The runs are one sweep (:mod:`hireps_torch.experiments.sweep`): ``--workers`` at a time, in local
processes or as Ray tasks; ``--resume DIR`` finishes an interrupted benchmark.
"""

from __future__ import annotations

import argparse
import math
import os

os.environ.setdefault("MKL_CBWR", "COMPATIBLE")  # before torch (experiments/workers.py)
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
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
from hireps_torch.envs.hockey import ENV_ID  # noqa: E402
from hireps_torch.experiments.hockey import HockeySequentialConfig  # noqa: E402
from hireps_torch.experiments.rundir import atomic_write  # noqa: E402
from hireps_torch.experiments.saved import LoadedRun, load_run  # noqa: E402
from hireps_torch.experiments.sweep import SweepRun, plan, run_sweep  # noqa: E402


def time_simulation(n_episodes: int) -> dict[str, float]:
    """Seconds per shot and per episode of the gymnasium env (demo shot + noise)."""
    from hireps_torch.envs.hockey import RobotHockeyEnv

    env = RobotHockeyEnv()
    rng = np.random.default_rng(0)
    demo = env.demo_action()
    noise = np.r_[np.full(7, 0.05), np.full(7, 0.3)]
    steps = 0
    t0 = time.perf_counter()
    for ep in range(n_episodes):
        env.reset(seed=ep)
        for _ in range(env.params.n_shots):
            _, _, _, _, info = env.step(demo + noise * rng.standard_normal(14))
            steps += info["sim_steps"]
    dt = time.perf_counter() - t0
    env.close()
    shots = n_episodes * env.params.n_shots
    return {
        "seconds_per_shot": dt / shots,
        "seconds_per_episode": dt / n_episodes,
        "sim_steps_per_shot": steps / shots,
        "sim_steps_per_second": steps / dt,
    }


def plot_curves(
    results: dict[str, list[dict[str, Any]]],
    out: Path,
    name: str = "learning_curve.png",
    paper: tuple[float, str] = (2.3, "paper, sequential (2.3)"),
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for label, runs in results.items():
        plot_band(ax, runs[0]["episodes_axis"], [r["curve"] for r in runs], label)
    ax.axhline(3.0, color="k", lw=0.8, ls="--", label="optimum (3)")
    ax.axhline(paper[0], color="grey", lw=0.8, ls=":", label=paper[1])
    ax.set_xlabel("episodes")
    ax.set_ylabel("average reward per episode")
    n = len(next(iter(results.values())))
    ax.set_title(f"robot hockey, {n} seeds (mean ± std)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    atomic_write(out / name, lambda p: fig.savefig(p, format="png", dpi=110))
    plt.close(fig)


def load_sequential(run_dir: Path) -> LoadedRun:
    """A finished sequential run (its config, and its algorithm: a population of one)."""
    run = load_run(run_dir)
    assert run.experiment == "hockey-sequential", run.experiment
    return run


def describe_strategy(run_dir: Path, n_episodes: int = 10) -> list[list[float]]:
    """The learned sequential policy's shots, noise-free, on ``n_episodes`` fresh starts: per
    episode the target's distance from the robot at the start and after each shot (m)."""
    from hireps_torch.experiments.hockey import _make_env, hockey_params
    from hireps_torch.experiments.workers import play_episodes
    from hireps_torch.rollout import episodes, time_indexed_module

    run = load_sequential(run_dir)
    cfg = run.config
    env = _make_env(ENV_ID, True, hockey_params(cfg))
    try:
        policies = [p.member(0) for p in run.algorithm.policies]
        actor = time_indexed_module(policies, deterministic=True)
        first = 2 * 10**9  # starts that neither training nor the final evaluation used
        batch = play_episodes(env, actor, cfg.seed, range(first, first + n_episodes), 3)
    finally:
        env.close()
    states, _, _, final = episodes(batch, 3)
    dist = torch.cat([states.norm(dim=-1), final.norm(dim=-1)[:, None]], -1)
    return [[round(float(d), 2) for d in row] for row in dist]


def record_episode(run_dir: Path, out: Path, seed: int = 0) -> dict[str, Any]:
    """Play one noise-free episode of a learned sequential policy; write a strip and a GIF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hireps_torch.envs.hockey import RobotHockeyEnv
    from hireps_torch.experiments.hockey import hockey_params

    run = load_sequential(run_dir)  # the run's policy, and its task below
    cfg = run.config
    env = RobotHockeyEnv(hockey_params(cfg), render_mode="rgb_array", frame_every=12)
    obs, _ = env.reset(seed=seed)
    frames, strip, total, zone = [env.render()], [env.render()], 0.0, 0
    for k in range(env.params.n_shots):
        action = run.mean_action(torch.as_tensor(obs[None], dtype=torch.float64), k)[0]
        obs, r, _, _, info = env.step(action.numpy())
        total += r
        zone = info["zone"]
        frames += info["frames"]
        shot_frames = info["frames"] or [env.render()]  # a rejected shot has no frames
        strip += [shot_frames[len(shot_frames) // 5], env.render()]
    env.close()
    fig, axes = plt.subplots(1, len(strip), figsize=(2.6 * len(strip), 2.4))
    titles = ["start"] + [t for k in range(1, 4) for t in (f"shot {k}", f"after shot {k}")]
    for ax, im, title in zip(axes, strip, titles, strict=True):
        ax.imshow(im)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(f"learned sequential policy: episode return {total:.2f}, zone {zone}")
    fig.tight_layout()
    atomic_write(out / "episode.png", lambda p: fig.savefig(p, format="png", dpi=100))
    plt.close(fig)
    from PIL import Image

    images = [Image.fromarray(f) for f in frames[::2]]
    atomic_write(
        out / "episode.gif",
        lambda p: images[0].save(
            p, format="GIF", save_all=True, append_images=images[1:], duration=80, loop=0
        ),
    )
    return {"episode_return": total, "zone": zone}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--episodes", type=int, default=HockeySequentialConfig.episodes)
    ap.add_argument("--timing-episodes", type=int, default=20)
    ap.add_argument(
        "--final-eval-episodes",
        type=int,
        default=200,
        help="fresh episodes the final policy is played on, each way (one episode's reward "
        "spreads over -1.5 .. 3: 30 leave a std of ~0.2 on the mean)",
    )
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "hockey_benchmark")
    add_figures_option(ap)
    ap.add_argument("--workers", type=int, default=1, help="runs at the same time")
    ap.add_argument("--backend", choices=["local", "ray"], default="local")
    ap.add_argument("--ray-address", default=None, help="an existing Ray cluster (--backend ray)")
    ap.add_argument(
        "--resume", type=Path, default=None, help="finish the benchmark written to this folder"
    )
    args = ap.parse_args()
    out = args.resume if args.resume is not None else start_benchmark(args.out, args.seeds)

    timing = time_simulation(args.timing_episodes)
    print(
        f"simulation: {1000 * timing['seconds_per_shot']:.1f} ms per shot "
        f"({timing['sim_steps_per_shot']:.0f} pybullet steps, "
        f"{timing['sim_steps_per_second']:.0f} steps/s), "
        f"{1000 * timing['seconds_per_episode']:.1f} ms per 3-shot episode",
        flush=True,
    )
    final = {"final_eval_episodes": args.final_eval_episodes}
    variants = {
        "sequential": ("hockey-sequential", {"episodes": args.episodes, **final}),
        "episodic": ("hockey-episodic", {"episodes": args.episodes, **final}),
        # Fig 15b: its own 300 episodes, 10 per update
        "fixed-start": ("hockey-fixed-start", final),
    }
    runs = sorted(
        (
            r
            for name, (experiment, options) in variants.items()
            for r in plan(experiment, {name: options}, range(args.seeds), out / "runs")
        ),
        key=lambda r: r.seed,
    )

    def report(run: SweepRun, summary: dict[str, Any]) -> None:
        exploring = summary.get("final_policy_average_reward", math.nan)
        noise_free = summary.get("eval_average_reward", math.nan)
        print(
            f"  {run.name:10s} seed {run.seed}: last iteration "
            f"{summary['final_average_reward']:5.2f}, final policy {exploring:5.2f} "
            f"(noise-free {noise_free:5.2f}), zone 3 share {summary['zone3_share']:.2f}, "
            f"{summary['wall_seconds']:.0f} s",
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
    results: dict[str, list[dict[str, Any]]] = {name: [] for name in variants}
    for run in sorted(runs, key=lambda r: r.seed):
        x, y = read_curve(run.run_dir, "average_reward")
        summary = done[(run.name, run.seed)]
        results[run.name].append(
            {**summary, "run_dir": str(run.run_dir), "curve": y, "episodes_axis": x}
        )
    total = time.perf_counter() - t_all
    lines = [
        "| variant | seeds | last iteration's average reward | final policy, exploring | "
        "final policy, noise-free | zone 3 share (last iteration) | s/run (mean, max) |",
        "|---|--:|--:|--:|--:|--:|--:|",
    ]
    for name, runs in results.items():
        walls = [r["wall_seconds"] for r in runs]
        lines.append(
            f"| {name} | {len(runs)} | "
            f"{mean_std([r['final_average_reward'] for r in runs], 2)} | "
            f"{mean_std([r.get('final_policy_average_reward', math.nan) for r in runs], 2)} | "
            f"{mean_std([r.get('eval_average_reward', math.nan) for r in runs], 2)} | "
            f"{mean_std([r['zone3_share'] for r in runs], 2)} | "
            f"{statistics.mean(walls):.0f}, {max(walls):.0f} |"
        )
    table = "\n".join(lines)
    print(table)
    print(
        f"(final policy: the policy after the last update on {args.final_eval_episodes} fresh "
        "episodes, with its exploration and without)"
    )
    for name, runs in results.items():
        for label, key in (
            ("last iteration", "final_average_reward"),
            ("final policy, exploring", "final_policy_average_reward"),
            ("final policy, noise-free", "eval_average_reward"),
        ):
            values = ", ".join(f"{r.get(key, math.nan):.2f}" for r in runs)
            print(f"{name}: {label} per seed {values}")
    print(f"all runs: {total:.0f} s")
    plot_curves({k: results[k] for k in ("sequential", "episodic")}, out)
    plot_curves(
        {"sequential, fixed start, 10 per update": results["fixed-start"]},
        out,
        "fig15b_fixed_start.png",
        (2.5, "paper, real robot by 300 episodes (2.5)"),
    )
    shown = record_episode(Path(results["sequential"][0]["run_dir"]), out)
    print(f"recorded episode (sequential, seed 0): {shown}")
    strategy = {}
    for r in results["sequential"]:
        strategy[r["seed"]] = describe_strategy(Path(r["run_dir"]))
        print(f"sequential seed {r['seed']}, noise-free, target distance (m) at start / after")
        print(
            "  shot 1 / shot 2 / shot 3: "
            + "; ".join(" / ".join(map(str, row)) for row in strategy[r["seed"]])
        )
    shown = {**shown, "strategy": strategy}
    write_results(out, {"timing": timing, "runs": results, "episode": shown}, total, table)
    publish(
        args.figures,
        {
            "fig14_hockey.png": out / "learning_curve.png",
            "fig15b_fixed_start.png": out / "fig15b_fixed_start.png",
            "hockey_episode.png": out / "episode.png",
        },
    )


if __name__ == "__main__":
    main()
