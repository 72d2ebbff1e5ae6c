"""Linear algebra that works on every device."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["min_norm_lstsq"]


def min_norm_lstsq(A: Tensor, B: Tensor) -> Tensor:
    """Minimum-norm least-squares solutions X (..., P, Q) of A (..., M, P) X = B (..., M, Q):
    LAPACK's gelsd on the CPU, elsewhere (CUDA's lstsq solves only full-rank systems) the
    pseudo-inverse with gelsd's default cut (singular values below eps max(M, P) of the
    largest are dropped), so that both devices find the same rank."""
    if A.device.type == "cpu":
        x: Tensor = torch.linalg.lstsq(A, B, driver="gelsd").solution
    else:
        cut = torch.finfo(A.dtype).eps * max(A.shape[-2], A.shape[-1])
        x = torch.linalg.pinv(A, rtol=cut) @ B
    return x
