"""How often do HiREPS and REPS end with an option on each mode of the two-Gaussians task?

Runs ``train.py bimodal`` (default config) for HiREPS and REPS over ``--seeds`` seeds, side by
side, and prints the share of runs whose final policy has an option (prior >= 0.05) within
0.25 of each mode, plus the noise-free final return.

    python benchmarks/bimodal_modes.py --seeds 20 [--figures docs/figures]

With ``--figures``, also writes ``two_gaussians_options.png``: the final options of seed 0 on
the reward landscape, HiREPS next to REPS.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._common import add_figures_option, publish  # noqa: E402
from hireps_torch.experiments.bimodal import BimodalConfig  # noqa: E402
from hireps_torch.experiments.bimodal import run as run_bimodal  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--episodes", type=int, default=BimodalConfig.episodes)
    add_figures_option(ap)
    args = ap.parse_args()
    print(f"two-Gaussians, {args.seeds} seeds, {args.episodes} episodes, default config")
    print(f"{'algorithm':<10} {'both modes':>11} {'one mode':>9} {'final return':>13} {'s/run':>6}")
    shown: dict[str, bytes] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for algo in ("hireps", "reps"):
            covered, finals = [], []
            t0 = time.perf_counter()
            for seed in range(args.seeds):
                cfg = BimodalConfig(
                    algorithm=algo,
                    seed=seed,
                    episodes=args.episodes,  # type: ignore[arg-type]
                    run_dir=Path(tmp) / f"{algo}-{seed}",
                    progress=False,
                )
                s = run_bimodal(cfg)
                if seed == 0:
                    shown[algo] = (cfg.run_dir / "options.png").read_bytes()
                covered.append(s["modes_covered"])
                finals.append(s["final_return"])
            dt = (time.perf_counter() - t0) / args.seeds
            both = sum(c == 2 for c in covered) / args.seeds
            one = sum(c == 1 for c in covered) / args.seeds
            print(
                f"{algo:<10} {both:>11.0%} {one:>9.0%} {sum(finals) / len(finals):>13.4f} "
                f"{dt:>6.2f}"
            )
        if args.figures is not None:
            both = Path(tmp) / "two_gaussians_options.png"
            side_by_side(shown, both)
            publish(args.figures, {both.name: both})


def side_by_side(images: dict[str, bytes], path: Path) -> None:
    """The runs' option plots in one figure, titled by algorithm."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(images), figsize=(5 * len(images), 4.6))
    for ax, (algo, png) in zip(axes, images.items(), strict=True):
        ax.imshow(plt.imread(io.BytesIO(png), format="png"))
        ax.set_title(f"{'HiREPS, 10 options' if algo == 'hireps' else 'REPS'}: seed 0, final")
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
