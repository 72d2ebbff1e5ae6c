"""Conditioning of the K-block dual: value start, whitening and scaling.

Before solving, v is written as v0 + scale * T u: v0 is the small-epsilon solution (a
least-squares fit of the returns on the features, block-weighted by 1/eta; 0 when the dual has a
linear term c), the returns become the Bellman errors at v0, centred per block and divided by
their common spread ``scale``, and T whitens the features (per-block centred, block-weighted).
The weights are invariant to all of it; eta, xi and v are mapped back to the caller's units.
Feature directions without spread in the samples (a constant column, all-zero or collinear
features) are left out of u: they cannot move the weights, v is unidentifiable along them, and
the constraints they carry hold for every distribution or for none (``fixed_residual``).
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

__all__ = [
    "Standardised",
    "column_scales",
    "fixed_residual",
    "identified_basis",
    "standardise",
    "value_start",
    "whitening",
]


# Relative thresholds (the solver pre-scales returns and feature columns by powers of 2, so
# every quantity here is O(1) relative to the caller's magnitudes; none is absolute).
_CONSTANT_RTOL = 1e-14  # a feature column whose spread is below this of its magnitude: constant
_RANK_RTOL = 1e-12  # singular values below this of the unit-column norm sqrt(K N): no direction
_SPREAD_RTOL = 1e-12  # floor of the residual spreads, relative to the return magnitude
_INFORMATIVE_RTOL = 1e-13  # Bellman residual spread below this of the returns: round-off only


@dataclass(frozen=True)
class Standardised:
    """A K-block dual in standardised units: v = v0 + scale * T u, and the solver sees

        R_s = (R + D v0 - offset) / scale,    D_s = D T,    c_s = T^T c.

    Attributes:
        residuals: (K, N) Bellman errors at v0, centred per block (R_s times ``scale``).
        D: (K, N, Q) whitened features D_s (Q <= P identified directions), or None without
            features or when no direction is identified.
        c: (Q,) whitened linear term c_s, or None.
        v0: (P,) value start in the caller's feature units.
        T: (P, Q) whitening map, or None without features.
        offset: (K, 1) the block means taken out of the Bellman errors.
        scale: their common spread.
        informative: whether the returns carry information beyond what the features fix
            (``scale`` above 1e-13 of the largest |return|, i.e. above round-off); if not, the
            solver looks for the closest distribution that meets the constraints.
        level: what the centring took out of the dual value (caller's units).
        dropped: feature directions without spread in the samples (a constant column, all-zero
            or collinear features), left out of the solve: v along them is unidentifiable.
        fixed_residual: the constraint residual along the dropped directions, relative to the
            size of its terms; it does not depend on the weights (0: met by every distribution).
        reward_spread: (K,) spread of each block's returns (before v0) over ``scale``: the
            temperature scale of a block whose returns vary, 0 for one whose returns do not.
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
    dropped: int = 0
    fixed_residual: float = 0.0
    reward_spread: Tensor | None = None

    @property
    def returns(self) -> Tensor:
        """(K, N) standardised returns R_s (zeros when the returns carry no information)."""
        if not self.informative:
            return torch.zeros_like(self.residuals)
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
    whitens the curvature of the dual in v at the start, sum_k Cov(D_k) / eta_k, on the
    directions the centred features identify (:func:`identified_basis`; the others are dropped).
    """
    K, N = R.shape
    resid = R - R.mean(dim=1, keepdim=True)
    T = None  # v = v0 + scale * T u (v0 and T in the caller's feature units)
    Ds = cs = None
    v0 = torch.zeros(0 if D is None else D.shape[-1], dtype=torch.float64)
    magnitude = float(R.abs().max())
    floor = _SPREAD_RTOL * magnitude if magnitude > 0 else 1.0
    dropped, fixed = 0, 0.0
    if D is not None and D.shape[-1] > 0:
        col = column_scales(D)
        Dc = (D - D.mean(dim=1, keepdim=True)) / col  # per-block centred, unit columns
        B = identified_basis(Dc)
        Dr = Dc if B is None else Dc @ B
        if c is None:
            y = value_start(resid, Dr, eps, floor)
            v0 = (y if B is None else B @ y) / col
            resid = resid + D @ v0
        # block weights 1 / eta_k at the start (KL ≈ Var(delta_k) / (2 eta_k^2) = eps_k)
        spread = (resid - resid.mean(dim=1, keepdim=True)).std(dim=1).clamp_min(floor)
        weight = (2.0 * eps).sqrt() / spread
        Tr = whitening(Dr, weight / weight.max())
        T = (Tr if B is None else B @ Tr) / col[:, None]
        if T.shape[1] > 0:
            Ds = D @ T
            cs = None if c is None else T.T @ c
        if B is not None:
            dropped, fixed = D.shape[-1] - B.shape[1], fixed_residual(D, c, col, B)
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
        informative=scale > _INFORMATIVE_RTOL * magnitude,
        level=float(R.mean(dim=1).sum() + offset.sum()),
        dropped=dropped,
        fixed_residual=fixed,
        reward_spread=R.std(dim=1) / scale if scale > 0 else torch.zeros(K, dtype=R.dtype),
    )


def column_scales(D: Tensor) -> Tensor:
    """(P,) spread of each feature column of D (K, N, P) over all blocks and samples; a column
    constant to round-off (spread below 1e-14 of its magnitude, ~45 units in the last place:
    also phi + 1e15 with phi ~ 1, of which float64 keeps 3 bits) gets its magnitude (1 if
    zero), so that its centred values stay at round-off level instead of being blown up."""
    flat = D.reshape(-1, D.shape[-1])
    col = flat.std(dim=0)
    mag = flat.abs().amax(dim=0)
    constant = ~(col > _CONSTANT_RTOL * mag)
    return torch.where(constant, torch.where(mag > 0, mag, torch.ones_like(mag)), col)


def identified_basis(Dc: Tensor) -> Tensor | None:
    """(P, Q) orthonormal basis of the directions that the centred, unit-column features Dc
    (K, N, P) identify, or None when all P are. A direction counts when its singular value
    exceeds 1e-12 of the largest one and of sqrt(K N), the norm of a unit-spread column (so
    that features that are all round-off identify nothing).

    Along a direction n outside it D_k n is the same for every sample of block k: it does not
    move the weights, v is unidentifiable along it (a constant column next to the
    normalisation), and its constraint holds for every distribution or for none (see
    :func:`fixed_residual`).
    """
    K, N, P = Dc.shape
    _, S, Vh = torch.linalg.svd(Dc.reshape(K * N, P), full_matrices=False)
    top = float(S.max()) if S.numel() else 0.0
    keep = S > _RANK_RTOL * max(top, math.sqrt(K * N))
    if int(keep.sum()) == P:
        return None
    basis: Tensor = Vh[keep].T.contiguous()
    return basis


def fixed_residual(D: Tensor, c: Tensor | None, col: Tensor, B: Tensor) -> float:
    """The feature-constraint residual c + sum_k w_k^T D_k along the directions outside B (in
    the unit-column coordinates y = col * v), relative to the size of its terms.

    Along those directions D_k is constant over samples, so the residual is c + sum_k mean_i
    D_k for every w (weights of a block sum to 1): 0 when the constraint holds trivially (a
    constant feature the data keep), else no reweighting can meet it.
    """
    means = D.mean(dim=1) / col  # (K, P)
    lin = torch.zeros_like(col) if c is None else c / col
    null = torch.eye(col.shape[0], dtype=torch.float64) - B @ B.T
    resid = null @ (lin + means.sum(0))
    size = float((lin.abs() + (D.abs().mean(dim=1) / col).sum(0)).max())
    return float(resid.abs().max()) / size if size > 0 else 0.0


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
    if P == 0:
        return v
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
    if P == 0:
        return torch.zeros(0, 0, dtype=torch.float64)
    A = (weight.sqrt()[:, None, None] * Dc).reshape(K * N, P) / math.sqrt(N)
    _, S, Vh = torch.linalg.svd(A, full_matrices=False)
    top = float(S.max()) if S.numel() else 0.0
    if not top > 0:  # no spread at all (the caller drops such directions first)
        return torch.eye(P, dtype=torch.float64)
    inv = torch.where(S > 1e-8 * top, 1.0 / S.clamp_min(1e-300), 1.0 / top)
    T = torch.eye(P, dtype=torch.float64)
    T[:, : S.shape[0]] = Vh.T * inv
    if S.shape[0] < P:  # fewer rows than features: complete the basis
        Q = torch.linalg.qr(torch.cat([Vh.T, torch.eye(P, dtype=torch.float64)], 1)).Q
        T[:, S.shape[0] :] = Q[:, S.shape[0] : P] / top
    return T
