"""A floor on the entropy of the new options' prior: versatility that lasts (beyond the paper).

HiREPS's episodic primal gains one constraint on the options' new masses ``m_o = sum_i P_io``:

    H(m) = -sum_o m_o log m_o >= h.

H is concave, so the constraint is convex. With H's variational form
``H(m) = min_r -sum_o m_o log r_o`` (r on the simplex; equality at r = m) and Sion's minimax
theorem, the multiplier ``lam >= 0`` enters like a reward ``-lam log r_o`` per option, and the
minimum over r is closed-form (``r_o`` proportional to ``B_o^(eta / (eta + lam))``). The dual:

    g(eta, xi, lam, v) = eta eps + xi kappa - lam h
                         + (eta + lam) log sum_o B_o^(eta / (eta + lam)),
    B_o = (1/N) sum_i exp(A_io / eta),   A_io = R_i - v^T (phi_i - phi_hat) + (eta + xi) log p~_io,

and the new distribution tempers each option's total weight:

    m = softmax_o(eta / (eta + lam) log B_o),   P_io = m_o exp(A_io / eta) / (N B_o).

``lam = 0`` is HiREPS's dual exactly. :func:`entropy_floor_solution` keeps the ordinary
solution of every member whose options' prior entropy already meets the floor (``lam = 0``,
bit for bit), and solves the dual above for the others with ``torch.optim.LBFGS`` in float64
(log eta, softplus xi, log lam, v), returns standardised, then raises eta where needed until the
KL bound holds.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor

from hireps_torch.dual.solutions import DualSolution

__all__ = ["entropy_floor_solution", "floor_weights", "prior_entropy"]

_TOL = 1e-6


def prior_entropy(weights: Tensor) -> Tensor:
    """H(m) of the options' masses m_o = sum_i P_io: weights (..., N, O) -> (...)."""
    m = weights.sum(-2)
    out: Tensor = -torch.special.xlogy(m, m).sum(-1)
    return out


def floor_weights(
    R: Tensor, lr: Tensor, D: Tensor | None, eta: Tensor, xi: Tensor, lam: Tensor, v: Tensor | None
) -> tuple[Tensor, Tensor]:
    """The dual's value terms and new weights of one problem.

    Args:
        R: (N,) returns; lr: (N, O) log p~; D: (N, F) centred context features or None.
        eta, xi, lam: 0-d multipliers; v: (F,) or None.

    Returns:
        ``(eta + lam) log sum_o B_o^c`` (0-d) and the weights P (N, O).
    """
    N = R.shape[0]
    adv = R if D is None or v is None else R - D @ v
    A = (adv[:, None] + (eta + xi) * lr) / eta  # (N, O)
    log_B = torch.logsumexp(A, 0) - math.log(N)  # (O,)
    c = eta / (eta + lam)
    log_m = torch.log_softmax(c * log_B, 0)
    value = (eta + lam) * torch.logsumexp(c * log_B, 0)
    finite_B = torch.where(torch.isfinite(log_B), log_B, torch.zeros_like(log_B))
    log_P = log_m + A - math.log(N) - finite_B
    return value, torch.exp(log_P)


def _kl(P: Tensor, lr: Tensor) -> Tensor:
    """KL(P || q p~) of weights (N, O) with log p~ ``lr`` and q = 1 / N."""
    out: Tensor = (torch.special.xlogy(P, P) - P * (lr - math.log(P.shape[0]))).sum()
    return out


@torch.no_grad()
def entropy_floor_solution(
    R: Tensor,
    lr: Tensor,
    eps: Tensor,
    phi: Tensor | None,
    kappa: Tensor | None,
    floor: Tensor,
    start: DualSolution,
) -> tuple[DualSolution, Tensor, Tensor, Tensor]:
    """The episodic solution with the options' prior entropy at least ``floor``.

    Args:
        R: (S, N) returns; lr: (S, N, O) log p~; eps: (S, 1); phi: (S, N, F) or None;
            kappa: (S, 1) or None; floor: (S,) h in nats.
        start: the ordinary (S, 1) solution of the same problems (:func:`episodic_solution`).

    Returns:
        The solution (S, 1) (members whose prior entropy met the floor unchanged), ``lam``
        (S,) (0 there), the realised prior entropy H(m) (S,) and the floor in force (S,): a
        floor no distribution meets within the KL and entropy bounds is lowered towards the
        ordinary solution's entropy until one does.
    """
    S, N = R.shape
    weights = start.weights.clone()
    fields = {
        k: getattr(start, k).clone()
        for k in (
            "eta",
            "xi",
            "v",
            "kl",
            "cross_entropy",
            "effective_sample_size",
            "feature_error",
            "dual_value",
            "converged",
            "iterations",
        )
    }
    lam_all = torch.zeros(S, dtype=torch.float64)
    floors = floor.to(torch.float64).clone()
    for s in range(S):
        H0 = float(prior_entropy(weights[s, 0]))
        if H0 >= float(floor[s]) - _TOL:
            continue
        D = None if phi is None else phi[s] - phi[s].mean(0)
        k = None if kappa is None or not math.isfinite(float(kappa[s, 0])) else float(kappa[s, 0])
        e = float(eps[s, 0])
        eta0 = float(start.eta[s, 0])
        eta0 = eta0 if math.isfinite(eta0) else float(R[s].std()) or 1.0
        xi0 = float(start.xi[s, 0]) if math.isfinite(float(start.xi[s, 0])) else 0.0
        first = (eta0, xi0, None if D is None else start.v[s])
        keep = torch.isfinite(lr[s]).all(0)  # pruned options (-inf) stay empty
        lrs, h = lr[s][:, keep], float(floor[s])
        for _ in range(8):  # a floor out of reach with the other bounds: halve the rise
            out = _member(R[s], lrs, D, e, k, h, first)
            if out is not None:
                break
            h = (h + H0) / 2
        if out is None:  # keep the ordinary solution
            floors[s] = H0
            continue
        Pk, eta, xi, lam, v, value, ok, its = out
        P = torch.zeros_like(lr[s])
        P[:, keep] = Pk
        w = P.sum(-1)
        weights[s, 0] = P
        fields["eta"][s, 0], fields["xi"][s, 0] = eta, xi
        if v is not None:
            fields["v"][s] = v
        fields["kl"][s, 0], fields["cross_entropy"][s, 0] = _kl(Pk, lrs), -(Pk * lrs).sum()
        fields["effective_sample_size"][s, 0] = 1.0 / (w**2).sum()
        fields["feature_error"][s] = 0.0 if D is None else (w @ D).abs().max()
        fields["dual_value"][s] = value
        fields["converged"][s] = ok
        fields["iterations"][s] = fields["iterations"][s] + its
        lam_all[s], floors[s] = lam, h
    sol = replace(start, weights=weights, numbers=None, **fields)
    return sol, lam_all, prior_entropy(weights[:, 0]), floors


def _member(
    R: Tensor,
    lr: Tensor,
    D: Tensor | None,
    eps: float,
    kappa: float | None,
    h: float,
    start: tuple[float, float, Tensor | None],
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None, Tensor, bool, int] | None:
    """One member's floored solution: weights (N, O), eta, xi, lam, v, the dual's value,
    whether every bound holds and the solver converged, iterations; None where the solve
    diverged or the floor was missed (out of reach with the other bounds)."""
    # LBFGS on (log eta, softplus^-1 xi, log lam, v), the returns standardised
    with torch.enable_grad():
        scale = float(R.std()) or 1.0
        Rs = (R - R.mean()) / scale
        eta0, xi0, v0 = start
        a = torch.tensor(math.log(max(eta0 / scale, 1e-8)), dtype=torch.float64, requires_grad=True)
        b = torch.tensor(
            math.log(math.expm1(max(xi0 / scale, 1e-6))),
            dtype=torch.float64,
            requires_grad=kappa is not None,
        )
        c = torch.tensor(
            math.log(max(0.1 * eta0 / scale, 1e-6)), dtype=torch.float64, requires_grad=True
        )
        v = (
            None
            if D is None
            else (torch.zeros(D.shape[1], dtype=torch.float64) if v0 is None else v0 / scale)
            .clone()
            .requires_grad_(True)
        )
        params = [p for p in (a, b, c, v) if p is not None and p.requires_grad]
        opt = torch.optim.LBFGS(
            params,
            max_iter=500,
            tolerance_grad=1e-9,
            tolerance_change=1e-14,
            history_size=20,
            line_search_fn="strong_wolfe",
        )

        def dual() -> Tensor:
            eta, lam = a.exp(), c.exp()
            xi = F.softplus(b) if kappa is not None else torch.zeros((), dtype=torch.float64)
            value, _ = floor_weights(Rs, lr, D, eta, xi, lam, v)
            return eta * eps + xi * (kappa or 0.0) - lam * h + value

        def closure() -> Tensor:
            opt.zero_grad()
            g = dual()
            g.backward()  # type: ignore[no-untyped-call,unused-ignore]  # untyped in torch
            return g

        opt.step(closure)  # type: ignore[no-untyped-call,unused-ignore]  # untyped in torch
        state = opt.state[opt._params[0]]
        iterations = int(state.get("n_iter", 0))
        grad = torch.cat([p.grad.reshape(-1) for p in params if p.grad is not None])
        met = bool(grad.abs().max() <= 1e-6)
        with torch.no_grad():
            eta = a.exp() * scale
            xi = (
                F.softplus(b) if kappa is not None else torch.zeros((), dtype=torch.float64)
            ) * scale
            lam = c.exp() * scale
            vv = None if v is None else v.detach() * scale
        v = vv
    if not all(math.isfinite(float(x)) for x in (eta, xi, lam)):
        return None
    P = floor_weights(R, lr, D, eta, xi, lam, v)[1]
    for _ in range(60):  # the KL bound must hold: raise eta (P moves towards q p~)
        if float(_kl(P, lr)) <= eps * (1 + _TOL):
            break
        eta = eta * 1.25
        P = floor_weights(R, lr, D, eta, xi, lam, v)[1]
    P = P / P.sum()
    if not bool(torch.isfinite(P).all()) or float(prior_entropy(P)) < h - 1e-3:
        return None
    value = eps * eta + xi * (kappa or 0.0) - lam * h + floor_weights(R, lr, D, eta, xi, lam, v)[0]
    ok = met and float(_kl(P, lr)) <= eps * (1 + _TOL) and float(prior_entropy(P)) >= h - 1e-4
    if kappa is not None:
        ok = ok and float(-(P * lr).sum()) <= kappa + 1e-6 * max(kappa, 1.0)
    return P, eta, xi, lam, v, value, ok, iterations
