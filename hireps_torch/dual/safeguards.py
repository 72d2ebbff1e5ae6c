"""What the solver promises after its solve: the KL bound by construction (:func:`enforce_kl`),
unreachable entropy bounds relaxed (:func:`reachable_kappa`), every constraint checked
(:func:`judge`). Tensors lead with (S, K).

Tolerances (KL and cross-entropy in nats; the feature residual in the whitened units of
:mod:`~hireps_torch.dual.conditioning`, i.e. feature spreads):

    KL_k <= epsilon_k (1 + 1e-6)                             always (enforced)
    CE_k <= kappa_k + 1e-6 max(kappa_k, 1 nat)               entropy bound
    |c_s + sum_k w_k^T D_s,k| <= converged_grad (1e-6)       feature constraints
    constraint residual along directions without spread <= 1e-6 of its terms
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hireps_torch.dual.problem import DualProblem
from hireps_torch.dual.solutions import block_cross_entropy, block_kl, feature_error

__all__ = [
    "ENTROPY_RTOL",
    "FIXED_RTOL",
    "KL_RTOL",
    "Verdict",
    "enforce_kl",
    "judge",
    "reachable_kappa",
]

KL_RTOL = 1e-6
ENTROPY_RTOL = 1e-6
FIXED_RTOL = 1e-6
_LOG_ETA_CAP = 700.0  # e^700 ~ 1e304: past it every tilt is uniform to float64 precision
_LOG_T_RANGE = (-30.0, 30.0)  # tilt exponents t = xi / eta searched by reachable_kappa


def enforce_kl(prob: DualProblem, eta: Tensor, xi: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """(eta (S, K), moved (S, K) bool): where the realised KL exceeds epsilon (1 + KL_RTOL), eta
    raised (xi and v held) by bisection in log eta until KL <= epsilon; else unchanged."""
    P, _, _ = prob.weights_at(eta, xi, v)
    moved = block_kl(P, prob.lr) > prob.eps * (1.0 + KL_RTOL)
    if not bool(moved.any()):
        return eta, moved

    def breaks(log_eta: Tensor) -> Tensor:
        W, _, _ = prob.weights_at(log_eta.exp(), xi, v)
        return block_kl(W, prob.lr) > prob.eps

    lo = eta.log()
    hi = lo.clone()
    step = 1.0
    while True:
        hi = torch.where(moved, (lo + step).clamp(max=_LOG_ETA_CAP), hi)
        high = moved & breaks(hi)
        if not bool(high.any()) or step > 2.0 * _LOG_ETA_CAP:
            break
        step *= 2.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        above = breaks(mid)
        lo = torch.where(moved & above, mid, lo)
        hi = torch.where(moved & ~above, mid, hi)
    return torch.where(moved, hi.exp(), eta), moved


def _tilt(lr: Tensor, log_t: Tensor) -> tuple[Tensor, Tensor]:
    """(KL, CE) per block (S, K) of P_k ∝ p~_k^(1 + t_k) / N, t = exp(log_t) (S, K)."""
    z = (1.0 + log_t.exp())[..., None, None] * lr
    flat = z.reshape(*lr.shape[:-2], -1)
    P = torch.softmax(flat, dim=-1).reshape(lr.shape)
    return block_kl(P, lr), block_cross_entropy(P, lr)


def _bisect_log_t(lr: Tensor, target: Tensor) -> Tensor:
    """(S, K) log t where the tilt's KL (rising in t) meets ``target``."""
    lo = torch.full_like(target, _LOG_T_RANGE[0])
    hi = torch.full_like(target, _LOG_T_RANGE[1])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        short = _tilt(lr, mid)[0] < target  # t must grow
        lo = torch.where(short, mid, lo)
        hi = torch.where(short, hi, mid)
    return hi


def _spends_more(lr: Tensor, kappa: Tensor, eps: Tensor, mask: Tensor) -> Tensor:
    """(S, K) where ``mask``: whether the tilt that meets kappa spends more KL than eps (bisection,
    stopped where decided)."""
    lo = torch.full_like(eps, _LOG_T_RANGE[0])
    hi = torch.full_like(eps, _LOG_T_RANGE[1])
    out, decided = torch.zeros_like(mask), ~mask
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        kl, ce = _tilt(lr, mid)
        meets = ce <= kappa
        beyond = ~decided & ~meets & (kl > eps)
        out |= beyond
        decided |= beyond | (meets & (kl <= eps))
        if bool(decided.all()):
            return out
        lo, hi = torch.where(meets, lo, mid), torch.where(meets, mid, hi)
    kl_meet, _ = _tilt(lr, hi)
    return out | (~decided & (kl_meet > eps))


def reachable_kappa(lr: Tensor, eps: Tensor, kappa: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Whether each entropy bound can be met within its KL bound (features aside): the tilt
    P ∝ p~^(1 + t) / N with the smallest t >= 0 that meets kappa must have KL <= epsilon.

    For lr (S, K, N, O), eps and kappa (S, K) (inf: none), returns (kappa to solve with, unreachable
    (bool), best), each (S, K): where unreachable, kappa is relaxed to the cross-entropy of the tilt
    that spends half the KL budget (of the steepest tilt's, if less), and ``best`` is the lowest
    cross-entropy any tilt within epsilon reaches.
    """
    zero = torch.full_like(eps, -math.inf)
    _, ce0 = _tilt(lr, zero)
    top = torch.full_like(eps, _LOG_T_RANGE[1])
    kl_top, ce_top = _tilt(lr, top)
    need = torch.isfinite(kappa) & (ce0 > kappa)
    if not bool(need.any()):
        return kappa, need, ce0
    unreachable = need & ((ce_top > kappa) | _spends_more(lr, kappa, eps, need & (ce_top <= kappa)))
    if not bool(unreachable.any()):  # (``best`` is only read where a bound is unreachable)
        return kappa, unreachable, ce0
    budget = torch.minimum(eps, kl_top)
    t_full = _bisect_log_t(lr, budget)
    _, best = _tilt(lr, t_full)
    t_half = _bisect_log_t(lr, 0.5 * budget)
    _, ce_half = _tilt(lr, t_half)
    return torch.where(unreachable, ce_half, kappa), unreachable, best


@dataclass(frozen=True)
class Verdict:
    """One problem's end: converged, what failed (``parts``), and whether a constraint is
    infeasible."""

    converged: bool
    infeasible: bool
    parts: tuple[str, ...]


def judge(
    prob: DualProblem,
    P: Tensor,
    kappa: Tensor,
    optimal: Tensor,
    fixed_residual: Tensor,
    converged_grad: float,
) -> Verdict:
    """The :class:`Verdict` of one problem's (S = 1) weights P (1, K, N, O): the KL bound, the
    entropy bound (kappa (1, K), inf: none), the feature constraints and ``optimal`` (1,)
    (gradient tolerance met)."""
    kl = block_kl(P, prob.lr)
    over = kl > prob.eps * (1.0 + KL_RTOL)
    ce = block_cross_entropy(P, prob.lr)
    # the cross-entropy may exceed kappa by 1e-6 of max(kappa, 1 nat)
    bad_ce = torch.isfinite(kappa) & (ce > kappa + ENTROPY_RTOL * kappa.clamp_min(1.0)) & prob.multi
    worst = feature_error(P, prob.D, prob.c)
    bad_f = worst > converged_grad
    fixed_bad = fixed_residual > FIXED_RTOL
    if not bool(over.any(-1) | bad_ce.any(-1) | bad_f | fixed_bad | ~optimal):
        return Verdict(True, False, ())
    parts: list[str] = []  # text only where the problem failed
    if bool(over.any()):
        o = over[0]
        parts.append(
            f"the KL bound is broken: KL = {_fmt(kl[0][o])} > epsilon {_fmt(prob.eps[0][o])}"
        )
    if bool(bad_ce.any()):
        b = bad_ce[0]
        parts.append(
            f"the entropy bound is violated: cross-entropy {_fmt(ce[0][b])} > kappa "
            f"{_fmt(kappa[0][b])} (tolerance 1e-6 of max(kappa, 1))"
        )
    if bool(bad_f):
        parts.append(
            f"the feature constraints are off by {float(worst[0]):.3g} feature spreads "
            f"(tolerance {converged_grad:g}; see feature_error)"
        )
    if bool(fixed_bad):
        parts.append(
            "the constraint along feature directions without spread in the samples (a "
            f"constant feature) is off by {float(fixed_residual[0]):.3g} of its terms: no "
            "reweighting can meet it (are the initial features consistent with the samples?)"
        )
    if not bool(optimal) and not parts:
        parts.append(
            f"the solver stopped before the optimum (gradient above {converged_grad:g}); "
            f"KL = {_fmt(kl[0])} against epsilon {_fmt(prob.eps[0])}"
        )
    return Verdict(False, bool(fixed_bad), tuple(parts))


def _fmt(x: Tensor) -> str:
    """A short text of a (K,) tensor: one number, or a list."""
    vals = [f"{float(a):.6g}" for a in x.reshape(-1)]
    return vals[0] if len(vals) == 1 else "[" + ", ".join(vals) + "]"
