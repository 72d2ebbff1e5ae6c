"""Input checks shared across the package (not public API)."""

from __future__ import annotations

import torch
from torch import Tensor


def as_finite_f64(name: str, value: Tensor | float, shape: tuple[int, ...] | None = None) -> Tensor:
    """``value`` as a float64 tensor, checked for ``shape`` (if given) and finiteness; the
    errors name ``name``, the shapes, and the first non-finite entry."""
    t = torch.as_tensor(value, dtype=torch.float64)
    if shape is not None and tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        bad = (~torch.isfinite(t)).nonzero()[0].tolist()
        where = bad[0] if len(bad) == 1 else bad
        raise ValueError(
            f"{name} contains non-finite values (first at index {where}: {t[tuple(bad)].item()})"
        )
    return t
