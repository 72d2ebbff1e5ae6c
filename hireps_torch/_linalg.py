"""Linear algebra that works on every device."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["min_norm_lstsq"]


def min_norm_lstsq(A: Tensor, B: Tensor) -> Tensor:
    """Minimum-norm least-squares solutions X (..., P, Q) of A (..., M, P) X = B (..., M, Q):
    LAPACK's gelsd on the CPU, the pseudo-inverse (an SVD, relative cut 1e-12) elsewhere,
    where gelsd is not available (CUDA's lstsq solves only full-rank systems)."""
    if A.device.type == "cpu":
        x: Tensor = torch.linalg.lstsq(A, B, driver="gelsd").solution
    else:
        x = torch.linalg.pinv(A, rtol=1e-12) @ B
    return x
