"""Conditioning of the K-block dual: value start, whitening and scaling.

Before solving, v is written as v0 + scale * T u: v0 is the small-epsilon solution (a
least-squares fit of the returns on the features, block-weighted by 1/eta; 0 when the dual has a
linear term c), the returns become the Bellman errors at v0, centred per block and divided by
their common spread ``scale``, and T whitens the features (per-block centred, block-weighted).
The weights are invariant to all of it; eta, xi and v are mapped back to the caller's units.
This keeps the problem well conditioned when the features explain most of the returns (a
converging policy) and when they are nearly collinear.

Why both matter: scaled by the returns, eta is ~1e-5 once the features explain most of them and
the v-curvature ~1/eta, and collinear features (phi = [s, s^2] with s in a narrow range) or
blocks with very different eta make it ill-conditioned besides; LBFGS then stalls or runs off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Standardised", "standardise", "value_start", "whitening"]


@dataclass(frozen=True)
class Standardised:
    """A K-block dual in standardised units: v = v0 + scale * T u, and the solver sees

        R_s = (R + D v0 - offset) / scale,    D_s = D T,    c_s = T^T c.

    Attributes:
        residuals: (K, N) Bellman errors at v0, centred per block (R_s times ``scale``).
        D: (K, N, P) whitened features D_s, or None without features.
        c: (P,) whitened linear term c_s, or None.
        v0: (P,) value start in the caller's feature units.
        T: (P, P) whitening map, or None without features.
        offset: (K, 1) the block means taken out of the Bellman errors.
        scale: their common spread.
        informative: whether the returns carry information beyond what the features fix
            (scale above round-off); if not, the solver keeps the old distribution.
        level: what the centring took out of the dual value (caller's units).
    """

    residuals: Tensor
    D: Tensor | None
    c: Tensor | None
    v0: Tensor
    T: Tensor | None
    offset: Tensor
    scale: float
    informative: bool
    level: float

    @property
    def returns(self) -> Tensor:
        """(K, N) standardised returns R_s."""
        return self.residuals / self.scale

    def value(self, u: Tensor) -> Tensor:
        """The caller's v (P,) of the standardised u."""
        return self.v0 + self.scale * (self.T @ u) if self.T is not None else u.clone()

    def dual_value(self, g: Tensor) -> float:
        """The caller's dual value of the standardised one: every term scales with the return
        scale; the centring adds back the block means."""
        return float(g) * self.scale + self.level


def standardise(R: Tensor, D: Tensor | None, c: Tensor | None, eps: Tensor) -> Standardised:
    """Standardise the dual of returns R (K, N), features D (K, N, P), linear term c (P,) and
    KL bounds eps (K,) (all float64).

    The returns are centred per block and divided by one common spread (the blocks are coupled
    through v). v0 is the small-epsilon solution (without c; see :func:`value_start`) and T
    whitens the curvature of the dual in v at the start, sum_k Cov(D_k) / eta_k.
    """
    K, N = R.shape
    resid = R - R.mean(dim=1, keepdim=True)
    T = None  # v = v0 + scale * T u (v0 and T in the caller's feature units)
    Ds = cs = None
    v0 = torch.zeros(0 if D is None else D.shape[-1], dtype=torch.float64)
    magnitude = max(1.0, float(R.abs().max()))
    floor = 1e-12 * magnitude
    if D is not None and D.shape[-1] > 0:
        col = D.reshape(K * N, -1).std(dim=0)
        col = torch.where(col > 1e-12, col, torch.ones_like(col))
        Dc = (D - D.mean(dim=1, keepdim=True)) / col  # per-block centred, unit columns
        if c is None:
            v0 = value_start(resid, Dc, eps, floor) / col
            resid = resid + D @ v0
        # block weights 1 / eta_k at the start (KL ≈ Var(delta_k) / (2 eta_k^2) = eps_k)
        spread = (resid - resid.mean(dim=1, keepdim=True)).std(dim=1).clamp_min(floor)
        weight = (2.0 * eps).sqrt() / spread
        T = whitening(Dc, weight / weight.max()) / col[:, None]
        Ds = D @ T
        cs = None if c is None else T.T @ c
    offset = resid.mean(dim=1, keepdim=True)
    resid = resid - offset
    scale = float(resid.std()) if resid.numel() > 1 else 1.0
    return Standardised(
        residuals=resid,
        D=Ds,
        c=cs,
        v0=v0,
        T=T,
        offset=offset,
        scale=scale,
        informative=scale > 1e-10 * magnitude,
        level=float(R.mean(dim=1).sum() + offset.sum()),
    )


def value_start(Rc: Tensor, Dc: Tensor, eps: Tensor, floor: float, rounds: int = 30) -> Tensor:
    """Small-epsilon value multipliers (the solver's start when c = 0).

    Args:
        Rc: (K, N) returns centred per block.
        Dc: (K, N, P) features centred per block.
        eps: (K,) KL bounds.
        floor: smallest residual spread taken seriously.
        rounds: most reweighting rounds with several blocks.

    For small epsilon w_ki ≈ (1 + (delta_ki - mean_i delta_k) / eta_k) / N, so the feature
    constraint sum_k w_k^T D_k = 0 (met by uniform weights when c = 0) makes v the weighted
    least-squares fit of -R on the centred D with block weights 1 / eta_k, and
    KL_k ≈ Var(delta_k) / (2 eta_k^2) = eps_k ties each eta_k to its block's residual spread.
    One block: plain least squares. Several: iterate the weights (a block that the features fit
    closely gets a small eta and dominates its part of v; an unweighted fit spoils it and leaves
    the optimum far from the start).
    """
    K, N, P = Dc.shape
    weight = torch.ones(K, dtype=torch.float64)
    v = torch.zeros(P, dtype=torch.float64)
    for _ in range(rounds if K > 1 else 1):
        root = weight.sqrt()[:, None]
        A = (root[:, :, None] * Dc).reshape(K * N, P)
        b = (root * Rc).reshape(K * N, 1)
        v = -torch.linalg.lstsq(A, b, driver="gelsd").solution.squeeze(1)
        spread = (Rc + Dc @ v).std(dim=1).clamp_min(floor)
        new = (2.0 * eps).sqrt() / spread
        new = new / new.max()
        if bool(((new - weight).abs() <= 1e-3 * weight).all()):
            break
        weight = new
    return v


def whitening(Dc: Tensor, weight: Tensor) -> Tensor:
    """(P, P) map T with T^T (sum_k weight_k Dc_k^T Dc_k / N) T = I on the identified
    directions, from (K, N, P) centred features and (K,) block weights. Directions without
    spread (a constant feature, collinear columns) keep the largest direction's scale."""
    K, N, P = Dc.shape
    A = (weight.sqrt()[:, None, None] * Dc).reshape(K * N, P) / math.sqrt(N)
    _, S, Vh = torch.linalg.svd(A, full_matrices=False)
    top = float(S.max()) if S.numel() else 1.0
    inv = torch.where(S > 1e-8 * top, 1.0 / S.clamp_min(1e-300), 1.0 / top)
    T = torch.eye(P, dtype=torch.float64)
    T[:, : S.shape[0]] = Vh.T * inv
    if S.shape[0] < P:  # fewer rows than features: complete the basis
        Q = torch.linalg.qr(torch.cat([Vh.T, torch.eye(P, dtype=torch.float64)], 1)).Q
        T[:, S.shape[0] :] = Q[:, S.shape[0] : P] / top
    return T
