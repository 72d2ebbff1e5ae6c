"""Conditioning of the K-block dual, per problem of S: v = v0 + scale * T u with v0 the
small-epsilon fit (:func:`value_start`), the returns the Bellman errors at v0 centred per block over
their common spread ``scale``, T whitening the features on the directions they identify
(:func:`identified_basis`). The weights are invariant to it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hireps_torch._linalg import min_norm_lstsq

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
    """S K-block duals in standardised units: v = v0 + scale * T u, and the solver sees

        R_s = (R + D v0 - offset) / scale,    D_s = D T,    c_s = T^T c

    (offset: the block means of R + D v0; scale: their common spread).

    Attributes:
        returns: (S, K, N) R_s (zeros where not informative).
        D, c, T: (S, K, N, P) D_s, (S, P) c_s, (S, P, P) T, or None (no features / no c).
        v0: (S, P) value start in the caller's feature units.
        scale: (S,) the common spread.
        informative: (S,) ``scale`` above 1e-13 of the largest |return| (else a projection solve).
        level: (S,) what the centring and c^T v0 took out of the dual value (caller's units).
        fixed_residual: (S,) the constraint residual along feature directions without spread in
            the samples (left out of the solve), relative to its terms.
        reward_spread: (S, K) spread of each block's returns (before v0) over ``scale``.
    """

    returns: Tensor
    D: Tensor | None
    c: Tensor | None
    v0: Tensor
    T: Tensor | None
    scale: Tensor
    informative: Tensor
    level: Tensor
    fixed_residual: Tensor
    reward_spread: Tensor

    def value(self, u: Tensor) -> Tensor:
        """The caller's v (S, P) of the standardised u (S, P)."""
        if self.T is None:
            return u.clone()
        return self.v0 + self.scale[:, None] * torch.einsum("spq,sq->sp", self.T, u)

    def dual_value(self, g: Tensor) -> Tensor:
        """The caller's dual values (S,) of the standardised ones g (S,)."""
        return g * self.scale + self.level


def standardise(R: Tensor, D: Tensor | None, c: Tensor | None, eps: Tensor) -> Standardised:
    """Standardise S duals of returns R (S, K, N), features D (S, K, N, P), linear terms c (S, P)
    and KL bounds eps (S, K) (float64), each on its own; T whitens sum_k Cov(D_k) / eta_k at the
    start."""
    S, K, N = R.shape
    resid = R - R.mean(dim=-1, keepdim=True)
    T = None  # v = v0 + scale * T u (v0 and T in the caller's feature units)
    Ds = cs = None
    P = 0 if D is None else D.shape[-1]
    v0 = R.new_zeros(S, P)
    magnitude = R.abs().amax(dim=(1, 2))
    floor = torch.where(magnitude > 0, _SPREAD_RTOL * magnitude, torch.ones_like(magnitude))
    fixed = R.new_zeros(S)
    if D is not None:
        col = column_scales(D)  # (S, P)
        Dc = (D - D.mean(dim=2, keepdim=True)) / col[:, None, None, :]
        y, svd = _one_block_fit(Dc, resid) if K == 1 and N > P else (None, None)
        if svd is None:
            svd = right_svd(Dc.reshape(S, K * N, P))
        B = identified_basis(Dc, svd)
        Dr = Dc if B is None else Dc @ B[:, None]
        if y is None or B is not None:
            y = value_start(resid, Dr, eps, floor)
        v0 = (y if B is None else torch.einsum("spq,sq->sp", B, y)) / col
        resid = resid + torch.einsum("sknp,sp->skn", D, v0)
        # block weights 1 / eta_k at the start (KL ≈ Var(delta_k) / (2 eta_k^2) = eps_k)
        spread = (resid - resid.mean(dim=-1, keepdim=True)).std(dim=-1)
        spread = torch.maximum(spread, floor[:, None])
        weight = (2.0 * eps).sqrt() / spread
        # one block with every direction kept: whitening's matrix is Dc / sqrt(N), whose SVD
        # is at hand
        same = (svd[0] / math.sqrt(N), svd[1]) if K == 1 and B is None else None
        Tr = whitening(Dr, weight / weight.amax(dim=-1, keepdim=True), same)
        T = (Tr if B is None else B @ Tr) / col[:, :, None]
        Ds = torch.einsum("sknp,spq->sknq", D, T)
        cs = None if c is None else torch.einsum("sp,spq->sq", c, T)
        if B is not None:
            fixed = fixed_residual(D, c, col, B)
    offset = resid.mean(dim=-1, keepdim=True)
    resid = resid - offset
    linear = R.new_zeros(S) if c is None else (c * v0).sum(-1)  # the dual's c^T v at v0
    scale = resid.reshape(S, -1).std(dim=-1)
    informative = scale > _INFORMATIVE_RTOL * magnitude
    r = resid / scale[:, None, None]
    spread_r = R.std(dim=-1)
    return Standardised(
        returns=torch.where(informative[:, None, None], r, torch.zeros_like(r)),
        D=Ds,
        c=cs,
        v0=v0,
        T=T,
        scale=scale,
        informative=informative,
        level=R.mean(dim=-1).sum(-1) + offset.sum(dim=(1, 2)) + linear,
        fixed_residual=fixed,
        reward_spread=torch.where(
            scale[:, None] > 0, spread_r / scale[:, None], torch.zeros_like(spread_r)
        ),
    )


def column_scales(D: Tensor) -> Tensor:
    """(S, P) spread of each feature column of D (S, K, N, P); a column constant to round-off
    (spread below 1e-14 of its magnitude) gets its magnitude (1 if zero)."""
    flat = D.reshape(D.shape[0], -1, D.shape[-1])
    col = flat.std(dim=1)
    mag = flat.abs().amax(dim=1)
    constant = ~(col > _CONSTANT_RTOL * mag)
    return torch.where(constant, torch.where(mag > 0, mag, torch.ones_like(mag)), col)


def identified_basis(Dc: Tensor, svd: tuple[Tensor, Tensor]) -> Tensor | None:
    """(S, P, P) orthonormal bases (as columns, 0 for the rest) of the directions the centred
    unit-column features Dc (S, K, N, P), P >= 1, identify (singular value above 1e-12 of the
    largest and of sqrt(K N)), or None when every problem identifies all P (``svd``:
    :func:`right_svd` of Dc as (S, K N, P))."""
    S, K, N, P = Dc.shape
    sv, Vh = svd
    m = sv.shape[-1]
    top = sv.amax(dim=-1, keepdim=True)
    keep = sv > _RANK_RTOL * top.clamp_min(math.sqrt(K * N))
    if m == P and bool(keep.all()):
        return None
    basis = Dc.new_zeros(S, P, P)
    basis[:, :, :m] = Vh.transpose(1, 2) * keep[:, None, :]
    return basis


def fixed_residual(D: Tensor, c: Tensor | None, col: Tensor, B: Tensor) -> Tensor:
    """(S,) the feature-constraint residual c + sum_k mean_i D_k along the directions outside each
    problem's B (unit-column coordinates y = col * v), relative to the size of its terms; it does
    not depend on the weights (0: met by every distribution)."""
    means = D.mean(dim=2) / col[:, None, :]  # (S, K, P)
    lin = torch.zeros_like(col) if c is None else c / col
    eye = torch.eye(col.shape[-1], dtype=col.dtype, device=col.device)
    null = eye - B @ B.transpose(1, 2)
    resid = torch.einsum("spq,sq->sp", null, lin + means.sum(1))
    size = (lin.abs() + (D.abs().mean(dim=2) / col[:, None, :]).sum(1)).amax(dim=-1)
    worst = resid.abs().amax(dim=-1)
    return torch.where(size > 0, worst / torch.where(size > 0, size, 1.0), 0.0)


def value_start(Rc: Tensor, Dc: Tensor, eps: Tensor, floor: Tensor, rounds: int = 30) -> Tensor:
    """(S, P) small-epsilon value multipliers for returns Rc (S, K, N) and features Dc (S, K, N, P)
    centred per block, KL bounds eps (S, K) and spread floor (S,): the least-squares fit of -Rc on
    Dc with block weights 1 / eta_k, KL_k ≈ Var(delta_k) / (2 eta_k^2) = eps_k, reweighted up to
    ``rounds`` times."""
    S, K, N, P = Dc.shape
    weight = Rc.new_ones(S, K)
    v = Rc.new_zeros(S, P)
    for _ in range(rounds if K > 1 else 1):
        root = weight.sqrt()[..., None]
        A = (root[..., None] * Dc).reshape(S, K * N, P)
        b = (root * Rc).reshape(S, K * N, 1)
        v = -min_norm_lstsq(A, b).squeeze(-1)  # (S, P)
        spread = (Rc + torch.einsum("sknp,sp->skn", Dc, v)).std(dim=-1)
        new = (2.0 * eps).sqrt() / torch.maximum(spread, floor[:, None])
        new = new / new.amax(dim=-1, keepdim=True)
        settled = ((new - weight).abs() <= 1e-3 * weight).all(dim=-1)
        if bool(settled.all()):
            break
        weight = torch.where(settled[:, None], weight, new)
    return v


def _one_block_fit(Dc: Tensor, Rc: Tensor) -> tuple[Tensor, tuple[Tensor, Tensor]]:
    """One block's minimum-norm least-squares fit y (S, P) of -Rc (S, 1, N) on Dc (S, 1, N, P) and
    :func:`right_svd` of Dc, from one QR of [Dc, Rc]."""
    S, _, N, P = Dc.shape
    R = torch.linalg.qr(torch.cat([Dc[:, 0], Rc[:, 0, :, None]], -1), mode="r").R
    U, sv, Vh = torch.linalg.svd(R[:, :P, :P])
    cut = torch.finfo(Dc.dtype).eps * max(N, P) * sv.amax(-1, keepdim=True)
    proj = (U.mT @ R[:, :P, P:])[..., 0]
    inv = torch.where(sv > cut, proj / sv.clamp_min(1e-300), 0.0)
    return -(Vh.mT @ inv[..., None])[..., 0], (sv, Vh)


def whitening(Dc: Tensor, weight: Tensor, svd: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """(S, P, P) maps T with T^T (sum_k weight_k Dc_k^T Dc_k / N) T = I on the identified
    directions, for centred features Dc (S, K, N, P) and block weights (S, K) (``svd``:
    :func:`right_svd` of the weighted (S, K N, P) features over sqrt(N), if at hand). Directions
    without spread keep the largest direction's scale."""
    S, K, N, P = Dc.shape
    eye = torch.eye(P, dtype=Dc.dtype, device=Dc.device).expand(S, P, P).clone()
    if svd is None:
        A = (weight.sqrt()[..., None, None] * Dc).reshape(S, K * N, P) / math.sqrt(N)
        svd = right_svd(A)
    sv, Vh = svd
    m = sv.shape[-1]
    top = sv.amax(dim=-1, keepdim=True)
    flat = ~(top > 0)  # no spread at all (the caller drops such directions first)
    top = torch.where(flat, 1.0, top)
    inv = torch.where(sv > 1e-8 * top, 1.0 / sv.clamp_min(1e-300), 1.0 / top)
    T = eye.clone()
    T[:, :, :m] = Vh.transpose(1, 2) * inv[:, None, :]
    if m < P:  # fewer rows than features: complete the basis
        Q = torch.linalg.qr(torch.cat([Vh.transpose(1, 2), eye], -1)).Q
        T[:, :, m:] = Q[:, :, m:P] / top[:, :, None]
    return torch.where(flat[:, :, None], eye, T)


def right_svd(A: Tensor) -> tuple[Tensor, Tensor]:
    """Singular values and right singular vectors of A (..., m, n), via the QR's triangular factor
    when A is tall."""
    if A.shape[-2] > A.shape[-1]:
        A = torch.linalg.qr(A, mode="r").R
    _, sv, Vh = torch.linalg.svd(A, full_matrices=False)
    return sv, Vh
