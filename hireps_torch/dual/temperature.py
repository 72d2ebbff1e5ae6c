"""Plain episodic REPS (one block, no features, one option column, no entropy bound): the dual of
one temperature, ``g(eta) = eta eps + eta log((1/N) sum_i exp(R_i / eta))``.

:func:`solve_temperature` takes Newton steps in a = log eta (``dg/da = eta (eps - KL)``,
``d2g/da2 = Var_P(R) / eta + dg/da``) until the KL is within ``KL_RTOL`` below epsilon and the
gradient at round-off; it returns None where it cannot conclude, and the general solver
(:mod:`hireps_torch.dual.solver`) takes over. :func:`log_temperatures` runs the same search per
block: the general solver's start for eta.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from hireps_torch.dual.block_solver import _ARMIJO, _FLAT, _LOG_ETA_FLOOR, LbfgsSettings
from hireps_torch.dual.problem import LOG_ETA_MAX
from hireps_torch.dual.safeguards import KL_RTOL
from hireps_torch.dual.solutions import DualSolution

__all__ = ["log_temperatures", "solve_temperature"]

_STEPS = 30  # Newton steps at most
_MAX_LOG_STEP = 2.0  # largest change of log eta in one step (the trust region e^2)
_HALVINGS = 30  # halvings of a step at most
_REFINE_GRAD = 1e-13  # the gradient the steps past the KL tolerance aim at (round-off)
_REFINE_STEPS = 1  # steps past the KL tolerance at most
_SPREAD_RTOL = 1e-13  # returns whose spread is below this of their magnitude carry no information


class _Found(NamedTuple):
    """Where the search ended: log eta ``a`` of the standardised returns ``r`` (largest ``r_max``),
    dual g, KL, steps; returns = (r s + mean) unit."""

    a: float
    g: float
    kl: float
    steps: int
    r: np.ndarray
    r_max: float
    s: float
    mean: float
    unit: float


def _search(Rh: np.ndarray, eps: float) -> _Found | None:
    """Newton steps in log eta on the returns Rh (N,), or None."""
    N = Rh.shape[0]
    lo_r, hi_r = float(np.minimum.reduce(Rh)), float(np.maximum.reduce(Rh))
    m_abs = max(-lo_r, hi_r)
    if m_abs == 0.0:
        return None
    # an exact power of 2 brings the returns to [0.5, 1) (in two factors: neither overflows)
    e = math.frexp(m_abs)[1]
    unit = 2.0 ** (e // 2) * 2.0 ** (e - e // 2)
    f1, f2 = 2.0 ** -(e // 2), 2.0 ** -(e - e // 2)
    Rn = Rh * f1 * f2
    mean = float(np.add.reduce(Rn)) / N
    d = Rn - mean
    s = math.sqrt(float(d @ d) / (N - 1))
    if not s > _SPREAD_RTOL:
        return None
    r = d / s
    powers = np.empty((3, N))
    powers[0], powers[1], powers[2] = 1.0, r, r * r
    # the shift of the exponentials: any value near max r keeps them in range
    log_n, r_max = math.log(N), (hi_r * f1 * f2 - mean) / s

    def parts(a: float) -> tuple[float, float, float, float]:
        """(g, dg/da, d2g/da2, KL) at log eta = a."""
        eta = math.exp(a)
        top = r_max / eta  # the largest r / eta
        s0, s1, s2 = (powers @ np.exp(r * (1.0 / eta) - top)).tolist()
        lse = top + math.log(s0) - log_n
        avg = s1 / s0
        kl = avg / eta - lse
        grad = eta * (eps - kl)
        var = max(s2 / s0 - avg * avg, 0.0)
        return eta * (eps + lse), grad, var / eta + grad, kl

    lo = _LOG_ETA_FLOOR
    a = max(-0.5 * math.log(2.0 * eps), lo + 1.0)  # KL ~ Var / (2 eta^2) = eps
    g, grad, curv, kl = parts(a)
    steps = refined = 0
    while True:
        held = abs(kl - eps) <= KL_RTOL * eps and kl <= eps
        if held and (abs(grad) <= _REFINE_GRAD or refined == _REFINE_STEPS):
            break
        if not held and abs(kl - eps) <= KL_RTOL * eps:  # KL above eps by round-off
            nudged = _nudge(parts, a, eps)
            if nudged is not None:
                a, (g, grad, curv, kl) = nudged
                break
        refined += held  # steps past the tolerance take the gradient to round-off
        if steps == _STEPS or not math.isfinite(g):
            return None
        step = -grad / curv if curv > 0 else math.copysign(_MAX_LOG_STEP, -grad)
        step = max(-_MAX_LOG_STEP, min(_MAX_LOG_STEP, step))
        for _ in range(_HALVINGS):
            if lo <= a + step <= LOG_ETA_MAX:
                trial = parts(a + step)
                flat = trial[0] <= g + _FLAT * (1.0 + abs(g))
                if trial[0] <= g + _ARMIJO * grad * step or (flat and abs(trial[1]) < abs(grad)):
                    a += step
                    g, grad, curv, kl = trial
                    break
            step *= 0.5
        else:
            if held:  # at round-off already
                break
            return None
        steps += 1
    return _Found(a, g, kl, steps, r, r_max, s, mean, unit)


def solve_temperature(R: Tensor, eps: float, settings: LbfgsSettings) -> DualSolution | None:
    """Solve the one-temperature dual of finite float64 returns R (N,), N >= 2, for KL bound eps, or
    None. The solution has S = K = O = 1, no v, xi = 0, and ``KL <= eps (1 + KL_RTOL)``."""
    N = R.shape[0]
    found = _search(R.detach().cpu().numpy(), eps)  # a scalar search: on the host, in numpy
    if found is None:
        return None
    a, g, kl, steps, r, r_max, s, mean, unit = found
    eta = math.exp(a)
    z = np.exp(r * (1.0 / eta) - r_max / eta)
    w = z / float(np.add.reduce(z))
    ess = 1.0 / float(w @ w)
    dual = (g * s + mean) * unit
    eta_s, kl_s, ess_s, zero, dual_s = torch.tensor(
        [[[eta * s * unit]], [[kl]], [[ess]], [[0.0]], [[dual]]], dtype=R.dtype, device=R.device
    ).unbind()  # (S, K) = (1, 1) each
    return DualSolution(
        eta=eta_s,
        xi=zero,
        v=R.new_zeros(1, 0),
        weights=torch.from_numpy(w).to(R.device).view(1, 1, N, 1),
        kl=kl_s,
        cross_entropy=zero,
        effective_sample_size=ess_s,
        feature_error=zero.view(1),
        dual_value=dual_s.view(1),
        converged=torch.ones(1, dtype=torch.bool, device=R.device),
        iterations=torch.full((1,), steps, device=R.device),
        numbers=(eta * s * unit, 0.0, kl, 0.0, ess, 0.0, dual),
    )


def log_temperatures(R: Tensor, eps: Tensor) -> Tensor:
    """(S, K) log eta of each block's one-temperature dual for returns R (S, K, N), KL bounds eps
    (S, K), in R's units; NaN where the search gives up."""
    Rh, eh = R.detach().cpu().numpy(), eps.detach().cpu().numpy()
    out = np.full(eh.shape, math.nan)
    for s, k in np.ndindex(*eh.shape):
        found = _search(Rh[s, k], float(eh[s, k]))
        if found is not None:
            out[s, k] = found.a + math.log(found.s * found.unit)
    return torch.from_numpy(out).to(R.device)


def _nudge(
    parts: Callable[[float], tuple[float, float, float, float]], a: float, eps: float
) -> tuple[float, tuple[float, float, float, float]] | None:
    """The smallest of a few round-off steps up in log eta that bring a KL above eps by round-off to
    at most eps, with its parts; None if none does."""
    unit = math.ulp(max(abs(a), 1.0))
    for k in range(1, 12):
        trial = parts(a + unit * 2.0**k)
        if trial[3] <= eps and abs(trial[3] - eps) <= KL_RTOL * eps:
            return a + unit * 2.0**k, trial
    return None
