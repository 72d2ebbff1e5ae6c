"""Conditioning of the K-block dual: value start, whitening and scaling.

Before solving, v is written as v0 + scale * T u: v0 is the small-epsilon fit (a least-squares
fit of the returns on the features, block-weighted by 1/eta; a linear term c, which moves the
optimum by O(eta), is left out of it), the returns become the Bellman errors at v0, centred per
block and divided by
their common spread ``scale``, and T whitens the features (per-block centred, block-weighted).
The weights are invariant to all of it; eta, xi and v are mapped back to the caller's units.
Feature directions without spread in the samples (a constant column, all-zero or collinear
features) are left out of u: they cannot move the weights, v is unidentifiable along them, and
the constraints they carry hold for every distribution or for none (``fixed_residual``).
This keeps the problem well conditioned when the features explain most of the returns (a
converging policy) and when they are nearly collinear.

Every quantity is per problem of a population of S independent duals (leading dimension S):
one problem's conditioning never depends on another's.

Why both matter: scaled by the returns, eta is ~1e-5 once the features explain most of them and
the v-curvature ~1/eta, and collinear features (phi = [s, s^2] with s in a narrow range) or
blocks with very different eta make it ill-conditioned besides; LBFGS then stalls or runs off.
"""

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

        R_s = (R + D v0 - offset) / scale,    D_s = D T,    c_s = T^T c.

    Attributes:
        residuals: (S, K, N) Bellman errors at v0, centred per block (R_s times ``scale``).
        D: (S, K, N, P) whitened features D_s, or None without features. Directions a
            problem's samples do not identify are zero columns of its D_s (u is inert along
            them).
        c: (S, P) whitened linear term c_s, or None.
        v0: (S, P) value start in the caller's feature units.
        T: (S, P, P) whitening map, or None without features.
        offset: (S, K, 1) the block means taken out of the Bellman errors.
        scale: (S,) the common spread of each problem's Bellman errors.
        informative: (S,) whether the returns carry information beyond what the features fix
            (``scale`` above 1e-13 of the largest |return|, i.e. above round-off); if not, the
            solver looks for the closest distribution that meets the constraints.
        level: (S,) what the centring and c^T v0 took out of the dual value (caller's units).
        dropped: (S,) feature directions without spread in the samples (a constant column,
            all-zero or collinear features), left out of the solve: v is unidentifiable along
            them.
        fixed_residual: (S,) the constraint residual along the dropped directions, relative to
            the size of its terms; it does not depend on the weights (0: met by every
            distribution).
        reward_spread: (S, K) spread of each block's returns (before v0) over ``scale``: the
            temperature scale of a block whose returns vary, 0 for one whose returns do not.
    """

    residuals: Tensor
    D: Tensor | None
    c: Tensor | None
    v0: Tensor
    T: Tensor | None
    offset: Tensor
    scale: Tensor
    informative: Tensor
    level: Tensor
    dropped: Tensor
    fixed_residual: Tensor
    reward_spread: Tensor

    @property
    def returns(self) -> Tensor:
        """(S, K, N) standardised returns R_s (zeros where the returns carry no
        information)."""
        r = self.residuals / self.scale[:, None, None]
        return torch.where(self.informative[:, None, None], r, torch.zeros_like(r))

    def value(self, u: Tensor) -> Tensor:
        """The caller's v (S, P) of the standardised u (S, P)."""
        if self.T is None:
            return u.clone()
        return self.v0 + self.scale[:, None] * torch.einsum("spq,sq->sp", self.T, u)

    def dual_value(self, g: Tensor) -> Tensor:
        """The caller's dual values (S,) of the standardised ones: every term scales with the
        return scale; the centring adds back the block means."""
        return g * self.scale + self.level


def standardise(R: Tensor, D: Tensor | None, c: Tensor | None, eps: Tensor) -> Standardised:
    """Standardise S duals of returns R (S, K, N), features D (S, K, N, P), linear terms c
    (S, P) and KL bounds eps (S, K) (all float64), each problem on its own.

    The returns are centred per block and divided by one common spread per problem (the
    blocks are coupled through v). v0 is the small-epsilon fit (without c, which the dual
    value's ``level`` then carries as c^T v0; see :func:`value_start`) and T whitens the
    curvature of the dual in v at the start,
    sum_k Cov(D_k) / eta_k, on the directions the centred features identify
    (:func:`identified_basis`; the others are dropped).
    """
    S, K, N = R.shape
    resid = R - R.mean(dim=-1, keepdim=True)
    T = None  # v = v0 + scale * T u (v0 and T in the caller's feature units)
    Ds = cs = None
    P = 0 if D is None else D.shape[-1]
    v0 = R.new_zeros(S, P)
    magnitude = R.abs().amax(dim=(1, 2))
    floor = torch.where(magnitude > 0, _SPREAD_RTOL * magnitude, torch.ones_like(magnitude))
    dropped = torch.zeros(S, dtype=torch.long, device=R.device)
    fixed = R.new_zeros(S)
    if D is not None and P > 0:
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
            dropped = P - (B.abs().amax(dim=1) > 0).sum(-1)
            fixed = fixed_residual(D, c, col, B)
    offset = resid.mean(dim=-1, keepdim=True)
    resid = resid - offset
    linear = R.new_zeros(S) if c is None else (c * v0).sum(-1)  # the dual's c^T v at v0
    scale = resid.reshape(S, -1).std(dim=-1) if K * N > 1 else R.new_ones(S)
    spread_r = R.std(dim=-1)
    return Standardised(
        residuals=resid,
        D=Ds,
        c=cs,
        v0=v0,
        T=T,
        offset=offset,
        scale=scale,
        informative=scale > _INFORMATIVE_RTOL * magnitude,
        level=R.mean(dim=-1).sum(-1) + offset.sum(dim=(1, 2)) + linear,
        dropped=dropped,
        fixed_residual=fixed,
        reward_spread=torch.where(
            scale[:, None] > 0, spread_r / scale[:, None], torch.zeros_like(spread_r)
        ),
    )


def column_scales(D: Tensor) -> Tensor:
    """(S, P) spread of each feature column of D (S, K, N, P) over all blocks and samples; a
    column constant to round-off (spread below 1e-14 of its magnitude, ~45 units in the last
    place: also phi + 1e15 with phi ~ 1, of which float64 keeps 3 bits) gets its magnitude (1
    if zero), so that its centred values stay at round-off level instead of being blown up."""
    flat = D.reshape(D.shape[0], -1, D.shape[-1])
    col = flat.std(dim=1)
    mag = flat.abs().amax(dim=1)
    constant = ~(col > _CONSTANT_RTOL * mag)
    return torch.where(constant, torch.where(mag > 0, mag, torch.ones_like(mag)), col)


def identified_basis(Dc: Tensor, svd: tuple[Tensor, Tensor] | None = None) -> Tensor | None:
    """(S, P, P) orthonormal bases of the directions that each problem's centred, unit-column
    features Dc (S, K, N, P) identify, as columns (the columns of directions not identified
    are 0), or None when every problem identifies all P (``svd``: :func:`right_svd` of Dc as
    (S, K N, P), where the caller has it). A direction counts when its singular
    value exceeds 1e-12 of the largest one and of sqrt(K N), the norm of a unit-spread column
    (so that features that are all round-off identify nothing).

    Along a direction n outside it D_k n is the same for every sample of block k: it does not
    move the weights, v is unidentifiable along it (a constant column next to the
    normalisation), and its constraint holds for every distribution or for none (see
    :func:`fixed_residual`).
    """
    S, K, N, P = Dc.shape
    sv, Vh = right_svd(Dc.reshape(S, K * N, P)) if svd is None else svd
    m = sv.shape[-1]
    top = sv.amax(dim=-1, keepdim=True) if m else sv.new_zeros(S, 1)
    keep = sv > _RANK_RTOL * top.clamp_min(math.sqrt(K * N))
    if m == P and bool(keep.all()):
        return None
    basis = Dc.new_zeros(S, P, P)
    basis[:, :, :m] = Vh.transpose(1, 2) * keep[:, None, :]
    # a problem that identifies every direction gets exactly I (no rotation, no round-off): its
    # solve is then the same whatever its companions identify
    full = keep.all(dim=-1) & (m == P)
    eye = torch.eye(P, dtype=Dc.dtype, device=Dc.device)
    return torch.where(full[:, None, None], eye, basis)


def fixed_residual(D: Tensor, c: Tensor | None, col: Tensor, B: Tensor) -> Tensor:
    """(S,) the feature-constraint residual c + sum_k w_k^T D_k along the directions outside
    each problem's B (in the unit-column coordinates y = col * v), relative to the size of
    its terms.

    Along those directions D_k is constant over samples, so the residual is c + sum_k mean_i
    D_k for every w (weights of a block sum to 1): 0 when the constraint holds trivially (a
    constant feature the data keep), else no reweighting can meet it.
    """
    means = D.mean(dim=2) / col[:, None, :]  # (S, K, P)
    lin = torch.zeros_like(col) if c is None else c / col
    eye = torch.eye(col.shape[-1], dtype=col.dtype, device=col.device)
    null = eye - B @ B.transpose(1, 2)
    resid = torch.einsum("spq,sq->sp", null, lin + means.sum(1))
    size = (lin.abs() + (D.abs().mean(dim=2) / col[:, None, :]).sum(1)).amax(dim=-1)
    worst = resid.abs().amax(dim=-1)
    return torch.where(size > 0, worst / torch.where(size > 0, size, 1.0), 0.0)


def value_start(Rc: Tensor, Dc: Tensor, eps: Tensor, floor: Tensor, rounds: int = 30) -> Tensor:
    """(S, P) small-epsilon value multipliers (the solver's start; exact for small epsilon
    when c = 0, and off by O(eta) otherwise).

    Args:
        Rc: (S, K, N) returns centred per block.
        Dc: (S, K, N, P) features centred per block.
        eps: (S, K) KL bounds.
        floor: (S,) smallest residual spread taken seriously.
        rounds: most reweighting rounds with several blocks.

    For small epsilon w_ki ≈ (1 + (delta_ki - mean_i delta_k) / eta_k) / N, so the feature
    constraint sum_k w_k^T D_k = 0 (met by uniform weights when c = 0) makes v the weighted
    least-squares fit of -R on the centred D with block weights 1 / eta_k, and
    KL_k ≈ Var(delta_k) / (2 eta_k^2) = eps_k ties each eta_k to its block's residual spread.
    One block: plain least squares. Several: iterate the weights (a block that the features fit
    closely gets a small eta and dominates its part of v; an unweighted fit spoils it and leaves
    the optimum far from the start). Each problem stops reweighting when its weights settle.
    """
    S, K, N, P = Dc.shape
    weight = Rc.new_ones(S, K)
    v = Rc.new_zeros(S, P)
    if P == 0:
        return v
    for _ in range(rounds if K > 1 else 1):
        root = weight.sqrt()[..., None]
        A = (root[..., None] * Dc).reshape(S, K * N, P)
        b = (root * Rc).reshape(S, K * N, 1)
        v = -_lstsq(A, b)
        spread = (Rc + torch.einsum("sknp,sp->skn", Dc, v)).std(dim=-1)
        new = (2.0 * eps).sqrt() / torch.maximum(spread, floor[:, None])
        new = new / new.amax(dim=-1, keepdim=True)
        settled = ((new - weight).abs() <= 1e-3 * weight).all(dim=-1)
        if bool(settled.all()):
            break
        weight = torch.where(settled[:, None], weight, new)
    return v


def _one_block_fit(Dc: Tensor, Rc: Tensor) -> tuple[Tensor, tuple[Tensor, Tensor]]:
    """One block's least-squares fit y (S, P) of -Rc (S, 1, N) on Dc (S, 1, N, P) (the
    minimum-norm one, with gelsd's cut at eps max(N, P) of the largest singular value) and
    :func:`right_svd` of Dc, both from one QR of [Dc, Rc]: its triangular factor holds Dc's
    and, in its last column, Q^T Rc."""
    S, _, N, P = Dc.shape
    R = torch.linalg.qr(torch.cat([Dc[:, 0], Rc[:, 0, :, None]], -1), mode="r").R
    U, sv, Vh = torch.linalg.svd(R[:, :P, :P])
    cut = torch.finfo(Dc.dtype).eps * max(N, P) * sv.amax(-1, keepdim=True)
    proj = (U.mT @ R[:, :P, P:])[..., 0]
    inv = torch.where(sv > cut, proj / sv.clamp_min(1e-300), 0.0)
    return -(Vh.mT @ inv[..., None])[..., 0], (sv, Vh)


def _lstsq(A: Tensor, b: Tensor) -> Tensor:
    """(S, P) minimum-norm least-squares solutions of A (S, M, P) x = b (S, M, 1)."""
    return min_norm_lstsq(A, b).squeeze(-1)


def whitening(Dc: Tensor, weight: Tensor, svd: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """(S, P, P) maps T with T^T (sum_k weight_k Dc_k^T Dc_k / N) T = I on the identified
    directions, from (S, K, N, P) centred features and (S, K) block weights (``svd``: the
    :func:`right_svd` of the weighted features stacked as (S, K N, P) over sqrt(N), where the
    caller has it). Directions without spread (a constant feature, collinear columns) keep
    the largest direction's scale."""
    S, K, N, P = Dc.shape
    eye = torch.eye(P, dtype=Dc.dtype, device=Dc.device).expand(S, P, P).clone()
    if P == 0:
        return eye
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
    """Singular values and right singular vectors of A (..., m, n): an SVD of the triangular
    factor of A's QR when A is tall (twice as fast as the SVD of A for the duals' (N, P)
    feature matrices; the left vectors are not needed)."""
    if A.shape[-2] > A.shape[-1]:
        A = torch.linalg.qr(A, mode="r").R
    _, sv, Vh = torch.linalg.svd(A, full_matrices=False)
    return sv, Vh
