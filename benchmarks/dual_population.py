"""Populations of duals: S episodic HiREPS duals solved together (``population=True``, one
LBFGS call per phase) against one of them, against S separate solves and against S scipy
L-BFGS-B solves of the same duals (the reference of ``benchmarks/dual_speed.py``).

For S in {1, 10, 100, 1000} random episodic problems of N = 30 samples and 2 context features,
with one option (REPS) and with 5 options and an entropy bound at 0.8 of the mean
responsibility entropy, prints: the wall time of the population call, its ratio to one
problem alone, the time per problem, scipy's time per problem, and the largest difference
between the population's weights and the separate solves' (with the share of problems whose
solve converged).

Goals (issue 14): 100 problems together cost at most 10x one of them; the time per problem is
at or below scipy's and below MushroomRL's REPS update (0.6-0.9 ms on this machine, see
benchmarks/README.md).

    OMP_NUM_THREADS=1 python benchmarks/dual_population.py [--repeats 5] [--sizes 1,10,100,1000]
"""

from __future__ import annotations

import argparse
import functools
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.dual_speed import problem, scipy_dual  # noqa: E402
from hireps_torch.dual import solve_episodic_dual  # noqa: E402


def population(
    S: int, N: int, O: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float | None]:
    """S problems of ``dual_speed.problem`` (seeds 0..S-1) stacked along a leading S; kappa is
    the first problem's (the bound is one number for the whole population)."""
    parts = [problem(N, O, seed=s) for s in range(S)]
    R = torch.from_numpy(np.stack([p[0] for p in parts]))
    phi = torch.from_numpy(np.stack([p[1] for p in parts]))
    lr = torch.from_numpy(np.stack([p[2] for p in parts]))
    return R, phi, lr, parts[0][3]


def timed(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sizes", default="1,10,100,1000")
    ap.add_argument("--N", type=int, default=30)
    args = ap.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")  # a few random problems warn; the table counts them
    eps, N = 0.5, args.N
    sizes = [int(s) for s in args.sizes.split(",")]
    print(
        f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"threads {torch.get_num_threads()}; N = {N}, epsilon = {eps}, 2 context features"
    )
    print(
        f"{'O':>2} {'S':>5} {'together ms':>12} {'x one':>7} {'ms/problem':>11} "
        f"{'scipy ms/pb':>12} {'/scipy':>7} {'separate ms/pb':>15} {'max|dw|':>9} {'conv':>6}"
    )
    for O in (1, 5):
        R, phi, lr, kappa = population(max(sizes), N, O)
        lrs = lr if O > 1 else None
        t_one = timed(
            functools.partial(solve, R[:1], phi[:1], lrs, eps, kappa, 0), args.repeats * 3
        )
        for S in sizes:
            together = functools.partial(solve, R[:S], phi[:S], lrs, eps, kappa, None)
            t_pop = timed(together, args.repeats)
            pop = together()
            n_ref = min(S, 100)  # separate solves and scipy on at most 100 problems
            t0 = time.perf_counter()
            singles = [solve(R, phi, lrs, eps, kappa, s) for s in range(n_ref)]
            t_sep = (time.perf_counter() - t0) / n_ref
            scipy_dual(R[0].numpy(), phi[0].numpy(), lr[0].numpy(), eps, kappa)  # warm-up
            t0 = time.perf_counter()
            for s in range(n_ref):
                scipy_dual(R[s].numpy(), phi[s].numpy(), lr[s].numpy(), eps, kappa)
            t_scipy = (time.perf_counter() - t0) / n_ref
            dw = max(
                float((pop.weights[s, 0] - singles[s].weights).abs().max()) for s in range(n_ref)
            )
            print(
                f"{O:>2} {S:>5} {t_pop * 1e3:>12.2f} {t_pop / t_one:>7.2f} "
                f"{t_pop / S * 1e3:>11.3f} {t_scipy * 1e3:>12.3f} {t_pop / S / t_scipy:>7.2f} "
                f"{t_sep * 1e3:>15.3f} {dw:>9.1e} {float(pop.converged.double().mean()):>6.2f}"
            )


def solve(R, phi, lr, eps, kappa, s):  # type: ignore[no-untyped-def]
    """Problem s alone (a DualSolution), or all of them as a population when s is None."""
    if s is None:
        return solve_episodic_dual(
            R,
            epsilon=eps,
            kappa=kappa,
            log_responsibilities=None if lr is None else lr[: len(R)],
            context_features=phi,
            population=True,
        )
    return solve_episodic_dual(
        R[s],
        epsilon=eps,
        kappa=kappa,
        log_responsibilities=None if lr is None else lr[s],
        context_features=phi[s],
    )


if __name__ == "__main__":
    main()
