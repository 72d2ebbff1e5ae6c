"""Feature maps ``x: (..., C) -> (..., F)`` (``F = out_features``), without a constant column
(the policies carry their own bias)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

from hireps_torch._linalg import matmul_each
from hireps_torch.checks import as_float_tensor, check_count, check_finite

__all__ = [
    "ConcatFeatures",
    "FeatureMap",
    "FourierFeatures",
    "IdentityFeatures",
    "QuadraticFeatures",
    "check_feature_map",
]


class FeatureMap(nn.Module):
    """Base of the feature maps: ``(..., in_features) -> (..., out_features)``; a state of
    another width or non-finite raises a ``ValueError``; non-floating states become float64."""

    in_features: int
    out_features: int

    def _input(self, x: Tensor) -> Tensor:
        """x checked (width, finiteness), as a floating tensor."""
        t = x if isinstance(x, Tensor) and x.is_floating_point() else as_float_tensor("x", x)
        if t.dim() < 1 or t.shape[-1] != self.in_features:
            raise ValueError(
                f"{type(self).__name__} takes states of shape (..., {self.in_features}), got "
                f"{tuple(t.shape)}"
            )
        held = next(iter(self._buffers.values()), None)  # a ConcatFeatures: its maps check
        if held is not None and t.device != held.device:
            raise ValueError(
                f"the states given to {type(self).__name__} are on {t.device} but the map on "
                f"{held.device}: move one to the other's device"
            )
        if not t.is_meta:
            check_finite(f"the states given to {type(self).__name__}", t, "")
        return t

    if TYPE_CHECKING:  # nn.Module.__call__ returns Any; a feature map returns a tensor

        def __call__(self, x: Tensor) -> Tensor: ...


def check_feature_map(name: str, value: object) -> FeatureMap | None:
    """``value`` if None or an ``nn.Module`` with int ``in_features`` and ``out_features``."""
    if value is None:
        return None
    widths = (getattr(value, "in_features", None), getattr(value, "out_features", None))
    if not isinstance(value, nn.Module) or not all(
        isinstance(w, int) and not isinstance(w, bool) for w in widths
    ):
        raise TypeError(
            f"{name} must be a feature map (an nn.Module with in_features and out_features, "
            f"e.g. QuadraticFeatures), got {type(value).__name__} {value!r:.60}"
        )
    return value  # type: ignore[return-value]


class IdentityFeatures(FeatureMap):
    """phi(x) = x (linear features). ``in_features = 0`` gives an empty map (no context)."""

    def __init__(self, in_features: int) -> None:
        super().__init__()
        self.in_features = check_count("in_features", in_features, 0)
        self.out_features = self.in_features

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., C) -> (..., C)."""
        return self._input(x)


class QuadraticFeatures(FeatureMap):
    """Squared expansion phi(x) = [z, z_i z_j for i <= j], z = x / scale (per dimension):
    ``(..., C) -> (..., C + C (C + 1) / 2)``."""

    scale: Tensor
    _rows: Tensor
    _cols: Tensor

    def __init__(self, in_features: int, scale: Tensor | None = None) -> None:
        super().__init__()
        self.in_features = in_features = check_count("in_features", in_features, 0)
        self.out_features = in_features + in_features * (in_features + 1) // 2
        if self.out_features > MAX_FOURIER_TERMS:
            raise ValueError(
                f"in_features = {in_features} gives {self.out_features:.3g} quadratic features, "
                f"more than {MAX_FOURIER_TERMS:.0e}: use fewer state dimensions"
            )
        iu = torch.triu_indices(in_features, in_features)
        self.register_buffer("_rows", iu[0], persistent=False)
        self.register_buffer("_cols", iu[1], persistent=False)
        s = torch.ones(in_features) if scale is None else as_float_tensor("scale", scale)
        # named as given, kept as float32 (rounded once, as integers past 2^53 need)
        s32 = s if scale is None else as_float_tensor("scale", scale, torch.float32)
        if s.shape != (in_features,) or not bool((torch.isfinite(s32) & (s32 > 0)).all()):
            raise ValueError(
                f"scale must be positive with shape ({in_features},) and in float32's range, "
                f"got {s}"
            )
        self.register_buffer("scale", s32.clone())

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., C) -> (..., C + C(C+1)/2)."""
        x = self._input(x)
        z = x / self.scale.to(x.dtype)
        quad = z[..., self._rows] * z[..., self._cols]
        return torch.cat([z, quad], dim=-1)


class FourierFeatures(FeatureMap):
    """Fourier basis (Konidaris et al. 2011): with ``u = (x - low) / (high - low)``,

        phi_c(x) = cos(pi c^T u),   c in {0, ..., n_bases - 1}^C,  c != 0,

    ``(..., C) -> (..., out_features)`` (``prod(n_bases) - 1`` with all couplings). Periodic
    dimensions use frequencies 2 pi k / (high - low) and both cos and sin (twice the terms).

    Args:
        low: (C,) lower corner of the state box.
        high: (C,) upper corner, > low.
        n_bases: frequencies per dimension, >= 2; or (C,) counts >= 1 (1: dimension left
            out), at least one >= 2.
        periodic: (C,) bools, or None for none.
        coupling: keep terms with at most this many non-zero frequencies, in 1..C; None: all.
    """

    low: Tensor
    width: Tensor
    coefficients: Tensor

    def __init__(
        self,
        low: Tensor | list[float],
        high: Tensor | list[float],
        n_bases: int | Sequence[int] = 5,
        periodic: list[bool] | None = None,
        coupling: int | None = None,
    ):
        super().__init__()
        lo = as_float_tensor("low", low)
        hi = as_float_tensor("high", high)
        if lo.dim() != 1 or lo.shape != hi.shape:
            raise ValueError(
                f"low and high must both have shape (C,) (C: the state dimension), got "
                f"{tuple(lo.shape)} and {tuple(hi.shape)}"
            )
        width = hi - lo  # finite and not subnormal, or the features are 1 or NaN
        if not bool((torch.isfinite(width) & (width >= torch.finfo(width.dtype).tiny)).all()):
            raise ValueError(
                f"need finite high > low elementwise, with high - low finite and at least "
                f"{torch.finfo(width.dtype).tiny:.3g}, got {lo}, {hi}"
            )
        C = lo.shape[0]
        counts = _bases_per_dimension(n_bases, C)
        per = _periodic_flags(periodic, C)
        if coupling is not None and not 1 <= check_count("coupling", coupling, 1) <= C:
            raise ValueError(f"coupling must be in 1..{C} (or None), got {coupling}")
        terms = math.prod(counts)
        if terms > MAX_FOURIER_TERMS:
            raise ValueError(
                f"n_bases ** state dimension = {n_bases}^{C} = {terms:.3g} frequency vectors "
                f"exceed {MAX_FOURIER_TERMS:.0e}: use fewer bases or fewer state dimensions"
                if isinstance(n_bases, int)
                else f"prod(n_bases) = {terms:.3g} frequency vectors (n_bases = {counts}) exceed "
                f"{MAX_FOURIER_TERMS:.0e}: use fewer bases or fewer state dimensions"
            )
        coeffs = torch.tensor(
            list(itertools.product(*(range(n) for n in counts))), dtype=torch.float64
        )
        if coupling is not None:  # the zero row (constant) stays first
            coeffs = coeffs[(coeffs != 0).sum(dim=1) <= coupling]
        # a periodic dimension doubles its frequency (whole periods on the box)
        coeffs = coeffs * torch.tensor([2.0 if p else 1.0 for p in per], dtype=torch.float64)
        self.in_features = C
        self.with_sin = any(per)
        self.out_features = (coeffs.shape[0] - 1) * (2 if self.with_sin else 1)
        self.register_buffer("low", lo)
        self.register_buffer("width", width)
        self.register_buffer("coefficients", coeffs[1:])

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., C) -> (..., out_features)."""
        x = self._input(x)
        u = (x.to(torch.float64) - self.low) / self.width
        phase = matmul_each(math.pi * u, self.coefficients.T)
        out = torch.cat([phase.cos(), phase.sin()], -1) if self.with_sin else phase.cos()
        return out.to(x.dtype)


MAX_FOURIER_TERMS = 10**6
"""The most frequency vectors :class:`FourierFeatures` enumerates, and the most features
:class:`QuadraticFeatures` builds."""


def _bases_per_dimension(n_bases: object, C: int) -> list[int]:
    """``n_bases`` checked, as a list of C counts."""
    if not isinstance(n_bases, Sequence | np.ndarray | Tensor) or (
        isinstance(n_bases, Tensor) and n_bases.dim() == 0
    ):
        return [check_count("n_bases", n_bases, 2)] * C
    if isinstance(n_bases, str | bytes) or (
        isinstance(n_bases, np.ndarray | Tensor) and n_bases.ndim != 1
    ):
        raise TypeError(
            f"n_bases must be an integer >= 2 or {C} integers >= 1, got "
            f"{type(n_bases).__name__} {n_bases!r:.60}"
        )
    counts = [check_count(f"n_bases[{k}]", n, 1) for k, n in enumerate(n_bases)]
    if len(counts) != C:
        raise ValueError(f"n_bases must have {C} entries (one per dimension), got {n_bases}")
    if max(counts) < 2:
        raise ValueError(f"at least one entry of n_bases must be >= 2, got {n_bases}")
    return counts


def _periodic_flags(periodic: object, C: int) -> list[bool]:
    """``periodic`` (None or C bools) checked, as a list of C bools."""
    if periodic is None:
        return [False] * C
    if isinstance(periodic, str | bytes):
        raise TypeError(f"periodic must be {C} bools (or None), got {periodic!r}")
    try:
        flags = list(periodic)  # type: ignore[call-overload]
    except TypeError:
        raise TypeError(f"periodic must be {C} bools (or None), got {periodic!r}") from None
    if len(flags) != C:
        raise ValueError(f"periodic must have {C} entries, got {periodic}")
    for k, p in enumerate(flags):
        if isinstance(p, Tensor) and p.dim() == 0 and p.dtype == torch.bool:
            continue
        if not isinstance(p, bool | np.bool_):
            raise TypeError(f"periodic[{k}] must be a bool, got {type(p).__name__} {p!r}")
    return [bool(p) for p in flags]


class ConcatFeatures(FeatureMap):
    """The maps' outputs side by side: ``(..., C) -> (..., sum_k F_k)``.

    Args:
        maps: one or more feature maps, all with the same ``in_features``.
    """

    def __init__(self, *maps: FeatureMap) -> None:
        super().__init__()
        if not maps:
            raise ValueError("ConcatFeatures needs at least one feature map")
        for k, m in enumerate(maps):
            check_feature_map(f"maps[{k}]", m)
        dims = sorted({m.in_features for m in maps})
        if len(dims) != 1:
            raise ValueError(f"all maps must share in_features, got {dims}")
        self.maps = nn.ModuleList(maps)
        self.in_features = dims[0]
        self.out_features = sum(m.out_features for m in maps)

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., C) -> (..., sum of the maps' out_features)."""
        x = self._input(x)
        return torch.cat([m(x) for m in self.maps], dim=-1)
