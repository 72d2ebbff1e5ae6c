"""Speed of the episodic HiREPS dual: hireps_torch (torch LBFGS) vs scipy L-BFGS-B.

For N in {30, 300, 3000, 30000} and O in {1, 5} the same random problem (returns, 2 context
features, responsibilities; an entropy bound at 0.8 of the mean responsibility entropy when
O = 5) is solved by ``solve_episodic_dual`` and by a scipy L-BFGS-B solve of the same dual
written here in numpy with its analytic gradient (same standardisation, bounds eta > 0,
xi >= 0). Prints the median wall time of each, their ratio and the realised KL of both.

    OMP_NUM_THREADS=1 python benchmarks/dual_speed.py [--repeats 15]
"""

from __future__ import annotations

import argparse
import functools
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import minimize

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hireps_torch.dual import solve_episodic_dual  # noqa: E402


def scipy_dual(R, phi, lr, eps, kappa):
    """Episodic HiREPS dual with analytic gradient; returns (weights, kl, eta)."""
    N, O = lr.shape
    Rs = (R - R.mean()) / R.std()
    Phi = phi - phi.mean(0)
    Phi = Phi / Phi.std(0)
    F = Phi.shape[1]
    use_xi = kappa is not None
    kap = 0.0 if kappa is None else kappa

    def parts(x):
        eta, xi, v = x[0], (x[1] if use_xi else 0.0), x[2 if use_xi else 1 :]
        delta = Rs - Phi @ v
        a = (delta[:, None] + (eta + xi) * lr) / eta
        m = a.max()
        e = np.exp(a - m)
        Z = e.sum()
        P = e / Z
        logZ = m + np.log(Z) - np.log(N)
        return eta, xi, v, delta, P, logZ

    def fg(x):
        eta, xi, v, delta, P, logZ = parts(x)
        g = eta * eps + xi * kap + eta * logZ
        Pl = (P * lr).sum()
        d_eta = eps + logZ - ((P.sum(1) * delta).sum() + xi * Pl) / eta
        grad = [d_eta]
        if use_xi:
            grad.append(kap + Pl)
        grad.extend(-(P.sum(1) @ Phi))
        return g, np.asarray(grad)

    x0 = np.concatenate([[1.0], [0.0] if use_xi else [], np.zeros(F)])
    bounds = [(1e-8, None)] + ([(0.0, None)] if use_xi else []) + [(None, None)] * F
    res = minimize(
        fg,
        x0,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxiter": 300, "gtol": 1e-9, "ftol": 1e-14},
    )
    _, _, _, _, P, _ = parts(res.x)
    kl = float((P * (np.log(np.maximum(P, 1e-300)) - lr + np.log(N))).sum())
    return P, kl


def problem(N, O, seed=0):
    g = np.random.default_rng(seed)
    phi = g.normal(size=(N, 2))
    R = 3.0 * g.normal(size=N) + 2.0 * phi[:, 0]
    logits = 2.0 * g.normal(size=(N, O))
    lr = logits - np.log(np.exp(logits).sum(1, keepdims=True))
    kappa = 0.8 * float(-(np.exp(lr) * lr).sum(1).mean()) if O > 1 else None
    return R, phi, lr, kappa


def median_time(fn, repeats):
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    torch.set_num_threads(1)
    eps = 0.5
    print(
        f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"threads {torch.get_num_threads()}; epsilon = {eps}, F = 2 context features"
    )
    print(
        f"{'N':>6} {'O':>2} {'torch ms':>9} {'scipy ms':>9} {'torch/scipy':>12} "
        f"{'KL torch':>9} {'KL scipy':>9} {'max|dw|':>9}"
    )
    for N in (30, 300, 3000, 30000):
        for O in (1, 5):
            R, phi, lr, kappa = problem(N, O)
            Rt, phit, lrt = (torch.from_numpy(a) for a in (R, phi, lr))
            reps = max(3, args.repeats // (1 if N < 30000 else 3))

            run_torch = functools.partial(
                solve_episodic_dual,
                Rt,
                epsilon=eps,
                log_responsibilities=lrt,
                context_features=phit,
                kappa=kappa,
            )
            run_scipy = functools.partial(scipy_dual, R, phi, lr, eps, kappa)

            tt = median_time(run_torch, reps)
            ts = median_time(run_scipy, reps)
            sol = run_torch()
            P, kl_s = run_scipy()
            dw = float(np.abs(sol.weights.numpy() - P).max())
            print(
                f"{N:>6} {O:>2} {tt * 1e3:>9.2f} {ts * 1e3:>9.2f} {tt / ts:>12.2f} "
                f"{sol.kl:>9.5f} {kl_s:>9.5f} {dw:>9.1e}"
            )


if __name__ == "__main__":
    main()
