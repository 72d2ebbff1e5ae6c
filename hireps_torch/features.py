"""Feature maps of states / contexts, as ``nn.Module``s.

Every map takes ``x: (..., S)`` and returns ``(..., F)`` with ``F = module.out_features``.
None of them adds a constant column: the policies carry their own bias, and a constant
column would make the dual's value multiplier unidentifiable.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["FeatureMap", "IdentityFeatures", "QuadraticFeatures"]


class FeatureMap(nn.Module):
    """Base of the feature maps: ``(..., in_features) -> (..., out_features)``."""

    in_features: int
    out_features: int


class IdentityFeatures(FeatureMap):
    """phi(x) = x (linear features). ``in_features = 0`` gives an empty map (no context)."""

    def __init__(self, in_features: int) -> None:
        super().__init__()
        if in_features < 0:
            raise ValueError(f"in_features must be >= 0, got {in_features}")
        self.in_features = in_features
        self.out_features = in_features

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., S) -> (..., S)."""
        return x


class QuadraticFeatures(FeatureMap):
    """Squared expansion phi(x) = [x, x_i x_j for i <= j] (the paper's gating features).

    ``(..., S) -> (..., S + S (S + 1) / 2)``. An optional per-dimension ``scale`` divides x
    first so that the quadratic terms are of order one.
    """

    scale: Tensor
    _rows: Tensor
    _cols: Tensor

    def __init__(self, in_features: int, scale: Tensor | None = None) -> None:
        super().__init__()
        if in_features < 0:
            raise ValueError(f"in_features must be >= 0, got {in_features}")
        self.in_features = in_features
        self.out_features = in_features + in_features * (in_features + 1) // 2
        iu = torch.triu_indices(in_features, in_features)
        self.register_buffer("_rows", iu[0], persistent=False)
        self.register_buffer("_cols", iu[1], persistent=False)
        s = (
            torch.ones(in_features)
            if scale is None
            else torch.as_tensor(scale, dtype=torch.float32)
        )
        if s.shape != (in_features,) or bool((s <= 0).any()):
            raise ValueError(f"scale must be positive with shape ({in_features},), got {s}")
        self.register_buffer("scale", s.clone())

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., S) -> (..., S + S(S+1)/2)."""
        z = x / self.scale.to(x.dtype)
        quad = z[..., self._rows] * z[..., self._cols]
        return torch.cat([z, quad], dim=-1)
