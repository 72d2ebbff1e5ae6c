"""Record the dual problems that real runs produce, for :mod:`benchmarks.dual_speed`.

Runs short runs of every experiment (a few seeds each) with the dual wrappers
(``solve_episodic_dual``, ``solve_infinite_horizon_dual``, ``solve_time_indexed_dual``)
wrapped so that every call stores what it hands the generic solver: the checked K-block
inputs ``(R, log_resp, eps, D, c, kappa)`` of :func:`hireps_torch.dual.solver.solve_blocks`,
one problem per population member. Writes them to ``benchmarks/dual_problems.pt`` (a list of
dicts with the experiment's name, the seed and the update).

    OMP_NUM_THREADS=1 python benchmarks/record_duals.py [--out benchmarks/dual_problems.pt]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import hireps_torch.dual.episodic as episodic_dual  # noqa: E402
import hireps_torch.dual.infinite_horizon as infinite_dual  # noqa: E402
import hireps_torch.dual.time_indexed as time_dual  # noqa: E402
from hireps_torch.experiments import EXPERIMENTS  # noqa: E402

# (experiment, seeds, options): short runs that still reach the late, ill-conditioned updates
RUNS: list[tuple[str, tuple[int, ...], dict[str, Any]]] = [
    ("bimodal", (0, 1), {"episodes": 800}),
    ("pendulum", (0,), {"episodes": 1000}),
    ("ball-on-beam", (0, 1, 2), {}),
    ("hockey-sequential", (0, 4, 5), {"episodes": 600}),
    ("hockey-episodic", (0, 4, 5), {"episodes": 600}),
]

_BIG = 100_000  # a problem with more feature entries (N P) than this is kept only ...
_BIG_EVERY = 25  # ... at every 25th update and the last, its features stored in float32

_CURRENT: dict[str, Any] = {}
PROBLEMS: list[dict[str, Any]] = []


def _recording(module: Any) -> None:
    """Wrap ``module.solve_blocks`` (the wrapper's call of the generic solver) to store its
    inputs."""
    inner = module.solve_blocks

    def solve_blocks(R, log_resp, eps, D, c, kappa, *args, **kwargs):  # type: ignore[no-untyped-def]
        for s in range(R.shape[0]):
            PROBLEMS.append(
                {
                    "experiment": _CURRENT["experiment"],
                    "seed": _CURRENT["seed"],
                    "update": sum(
                        p["experiment"] == _CURRENT["experiment"] and p["seed"] == _CURRENT["seed"]
                        for p in PROBLEMS
                    ),
                    "R": R[s].clone(),
                    "log_resp": log_resp[s].clone(),
                    "eps": eps[s].clone(),
                    "D": None if D is None else D[s].clone(),
                    "c": None if c is None else c[s].clone(),
                    "kappa": None if kappa is None else kappa[s].clone(),
                }
            )
        return inner(R, log_resp, eps, D, c, kappa, *args, **kwargs)

    module.solve_blocks = solve_blocks


def compact(problems: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The problems to keep: every small one; of the big ones (the pendulum's 8000 x 53
    features, 3.4 MB each) every ``_BIG_EVERY``-th update and the last of each run, with D
    stored in float32 (solved in float64 like the rest)."""
    last: dict[tuple[str, int], int] = {}
    for p in problems:
        last[p["experiment"], p["seed"]] = p["update"]
    kept = []
    for p in problems:
        D = p["D"]
        if D is not None and D.shape[-2] * D.shape[-1] > _BIG:
            if p["update"] % _BIG_EVERY and p["update"] != last[p["experiment"], p["seed"]]:
                continue
            p = dict(p, D=D.to(torch.float32))
        kept.append(p)
    return kept


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "dual_problems.pt")
    args = parser.parse_args()
    for module in (episodic_dual, infinite_dual, time_dual):
        _recording(module)
    with tempfile.TemporaryDirectory() as tmp:
        for name, seeds, options in RUNS:
            config_cls, run = EXPERIMENTS[name].config, EXPERIMENTS[name].run
            for seed in seeds:
                _CURRENT.update(experiment=name, seed=seed)
                before = len(PROBLEMS)
                cfg = config_cls(
                    seed=seed, run_dir=Path(tmp) / f"{name}-{seed}", progress=False, **options
                )
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    run(cfg)
                print(f"{name} seed {seed}: {len(PROBLEMS) - before} duals", flush=True)
    torch.save(compact(PROBLEMS), args.out)
    print(f"{len(PROBLEMS)} problems written to {args.out}")


if __name__ == "__main__":
    main()
