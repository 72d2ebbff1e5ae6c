"""What the solver promises after LBFGS, whatever it was given.

- The KL bound holds by construction (:func:`enforce_kl`): a block whose realised KL exceeds
  ``epsilon (1 + KL_RTOL)`` gets a larger eta (xi and v held), found by bisection in log eta;
  for fixed xi and v the weights are an exponential tilt of q p~ by h / eta
  (h = delta + xi log p~), and their KL falls monotonically to 0 as eta grows.
- An entropy bound that no distribution within the KL bound meets is found before the solve
  (:func:`reachable_kappa`) and relaxed to what half the KL budget reaches.
- :func:`judge` checks every constraint at the end, with relative tolerances, and says which
  failed and by how much; the solve counts as converged only if none did.

Tolerances (KL and cross-entropy are in nats, dimensionless; the feature residual is measured
in the whitened units of :mod:`~hireps_torch.dual.conditioning`, i.e. in feature spreads):

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
from hireps_torch.dual.solutions import block_cross_entropy, block_kl

__all__ = [
    "ENTROPY_RTOL",
    "FIXED_RTOL",
    "KL_RTOL",
    "Verdict",
    "enforce_kl",
    "entropy_slack",
    "judge",
    "reachable_kappa",
]

KL_RTOL = 1e-6
ENTROPY_RTOL = 1e-6
FIXED_RTOL = 1e-6
_LOG_ETA_CAP = 700.0  # e^700 ~ 1e304: past it every tilt is uniform to float64 precision
_LOG_T_RANGE = (-30.0, 30.0)  # tilt exponents t = xi / eta searched by reachable_kappa


def enforce_kl(prob: DualProblem, eta: Tensor, xi: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """(eta (K,), moved (K,) bool): eta raised, per block and with xi and v held, until the
    realised KL is at most epsilon, where it exceeded epsilon (1 + KL_RTOL); else unchanged.

    Bisection in log eta: the bracket's top is doubled until it keeps the bound, then 80
    halvings leave KL within round-off below epsilon (the feasible end is returned).
    """
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
    """(KL (K,), CE (K,)) of P_k ∝ p~_k^(1 + t_k) / N, t = exp(log_t) (K,)."""
    z = (1.0 + log_t.exp())[:, None, None] * lr
    P = torch.softmax(z.reshape(lr.shape[0], -1), dim=1).reshape(lr.shape)
    return block_kl(P, lr), block_cross_entropy(P, lr)


def _bisect_log_t(lr: Tensor, target: Tensor, use_kl: bool) -> Tensor:
    """(K,) log t where the tilt's KL (rising in t) or CE (falling) meets ``target``."""
    K = lr.shape[0]
    lo = torch.full((K,), _LOG_T_RANGE[0], dtype=torch.float64)
    hi = torch.full((K,), _LOG_T_RANGE[1], dtype=torch.float64)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        kl, ce = _tilt(lr, mid)
        short = kl < target if use_kl else ce > target  # t must grow
        lo = torch.where(short, mid, lo)
        hi = torch.where(short, hi, mid)
    return hi


def reachable_kappa(lr: Tensor, eps: Tensor, kappa: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Whether each entropy bound can be met within its KL bound (features aside).

    The closest distribution to q p~ (in KL) with E[-log p~] <= kappa is the tilt
    P ∝ p~^(1 + t) / N with the smallest t >= 0 that meets kappa (an I-projection onto a linear
    constraint); the bound is reachable iff that tilt's KL is <= epsilon.

    Args:
        lr: (K, N, O) log responsibilities (log 0 floored).
        eps: (K,) KL bounds.
        kappa: (K,) entropy bounds (inf: none).

    Returns:
        (kappa to solve with (K,), unreachable (K,) bool, best (K,)): where unreachable, kappa
        is relaxed to the cross-entropy of the tilt that spends half the KL budget (half of
        what the steepest tilt spends, if less), and ``best`` is the lowest cross-entropy any
        tilt within epsilon reaches.
    """
    K = lr.shape[0]
    zero = torch.full((K,), -math.inf, dtype=torch.float64)
    _, ce0 = _tilt(lr, zero)
    top = torch.full((K,), _LOG_T_RANGE[1], dtype=torch.float64)
    kl_top, ce_top = _tilt(lr, top)
    need = torch.isfinite(kappa) & (ce0 > kappa)
    if not bool(need.any()):
        return kappa, need, ce0
    t_meet = _bisect_log_t(lr, torch.where(need, kappa, 0.0), use_kl=False)
    kl_meet, _ = _tilt(lr, t_meet)
    unreachable = need & ((ce_top > kappa) | (kl_meet > eps))
    budget = torch.minimum(eps, kl_top)
    t_full = _bisect_log_t(lr, budget, use_kl=True)
    _, best = _tilt(lr, t_full)
    t_half = _bisect_log_t(lr, 0.5 * budget, use_kl=True)
    _, ce_half = _tilt(lr, t_half)
    return torch.where(unreachable, ce_half, kappa), unreachable, best


def entropy_slack(kappa: Tensor) -> Tensor:
    """(K,) how far the cross-entropy may exceed kappa: 1e-6 of max(kappa, 1 nat)."""
    return ENTROPY_RTOL * kappa.clamp_min(1.0)


@dataclass(frozen=True)
class Verdict:
    """The end of a solve: converged, and if not, what failed (``parts``) and whether a
    constraint is infeasible (then the warning is an InfeasibleConstraintsWarning)."""

    converged: bool
    infeasible: bool
    parts: tuple[str, ...]


def judge(
    prob: DualProblem,
    P: Tensor,
    kappa: Tensor,
    optimal: bool,
    fixed_residual: float,
    converged_grad: float,
) -> Verdict:
    """Check the KL bound, the entropy bound (the caller's kappa (K,), inf: none), the feature
    constraints and optimality (``optimal``: LBFGS met its gradient tolerance) at weights P."""
    parts: list[str] = []
    infeasible = False
    kl = block_kl(P, prob.lr)
    over = kl > prob.eps * (1.0 + KL_RTOL)
    if bool(over.any()):
        parts.append(
            f"the KL bound is broken: KL = {_fmt(kl[over])} > epsilon {_fmt(prob.eps[over])}"
        )
    ce = block_cross_entropy(P, prob.lr)
    bad_ce = torch.isfinite(kappa) & (ce > kappa + entropy_slack(kappa))
    if prob.multi and bool(bad_ce.any()):
        parts.append(
            f"the entropy bound is violated: cross-entropy {_fmt(ce[bad_ce])} > kappa "
            f"{_fmt(kappa[bad_ce])} (tolerance 1e-6 of max(kappa, 1))"
        )
    if prob.P:
        assert prob.D is not None
        resid = torch.einsum("kn,knp->p", P.sum(-1), prob.D)
        if prob.c is not None:
            resid = resid + prob.c
        worst = float(resid.abs().max())
        if worst > converged_grad:
            parts.append(
                f"the feature constraints are off by {worst:.3g} feature spreads "
                f"(tolerance {converged_grad:g}; see feature_error)"
            )
    if fixed_residual > FIXED_RTOL:
        infeasible = True
        parts.append(
            "the constraint along feature directions without spread in the samples (a constant "
            f"feature) is off by {fixed_residual:.3g} of its terms: no reweighting can meet it "
            "(are the initial features consistent with the samples?)"
        )
    if not optimal and not parts:
        parts.append(
            f"the solver stopped before the optimum (gradient above {converged_grad:g}); "
            f"KL = {_fmt(kl)} against epsilon {_fmt(prob.eps)}"
        )
    return Verdict(not parts and optimal, infeasible, tuple(parts))


def _fmt(x: Tensor) -> str:
    """A short text of a (K,) tensor: one number, or a list."""
    vals = [f"{float(a):.6g}" for a in x.reshape(-1)]
    return vals[0] if len(vals) == 1 else "[" + ", ".join(vals) + "]"
