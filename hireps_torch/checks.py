"""Input checks shared by the library and the environments: one home, one message style.

Every check raises ``ValueError`` (``TypeError`` for something that is not a number at all)
whose message names the argument, the expected and actual shape, or the first bad entry, so a
user can find the bad value without reading torch's internals.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "as_f64",
    "as_finite_f64",
    "check_finite",
    "check_positive",
    "check_positive_float",
    "check_nonnegative_float",
]


def as_f64(name: str, value: Tensor | object) -> Tensor:
    """``value`` as a detached float64 tensor; a ``TypeError`` naming ``name`` if it is not
    a number, a sequence of numbers or a tensor."""
    if not isinstance(value, Tensor):
        try:
            value = torch.as_tensor(value)
        except Exception as exc:
            raise TypeError(f"{name} must be a tensor, got {type(value).__name__}") from exc
    return value.detach().to(torch.float64)


def check_finite(name: str, x: Tensor) -> None:
    """Raise naming ``name``, the number of non-finite entries and the first one's index."""
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{name} contains {int(bad.sum())} non-finite value(s) (first at index {idx}: "
            f"{x[idx].item()}); remove or fix those samples before the update"
        )


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


def check_positive(name: str, value: Tensor) -> None:
    """Every entry of ``value`` finite and > 0."""
    if not bool(torch.isfinite(value).all()) or bool((value <= 0).any()):
        raise ValueError(f"{name} must be finite and > 0, got {value.tolist()}")


def check_positive_float(name: str, value: float) -> float:
    """A finite scalar > 0 (e.g. epsilon), as a float."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value}")
    return v


def check_nonnegative_float(name: str, value: float | None) -> float | None:
    """A finite scalar >= 0 or None (e.g. kappa_rel), as a float."""
    if value is None:
        return None
    v = float(value)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be finite and >= 0 (or None), got {value}")
    return v
