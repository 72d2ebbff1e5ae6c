"""Linear algebra that works on every device, and softmaxes over a short last dimension."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["log_softmax", "logsumexp", "min_norm_lstsq", "softmax"]


def min_norm_lstsq(A: Tensor, B: Tensor) -> Tensor:
    """Minimum-norm least-squares X (..., P, Q) of A (..., M, P) X = B (..., M, Q): gelsd on the
    CPU, elsewhere the pseudo-inverse with gelsd's default cut (same rank on both)."""
    if A.device.type == "cpu":
        x: Tensor = torch.linalg.lstsq(A, B, driver="gelsd").solution
    else:
        cut = torch.finfo(A.dtype).eps * max(A.shape[-2], A.shape[-1])
        x = torch.linalg.pinv(A, rtol=cut) @ B
    return x


# softmaxes over a short last dimension (the gating's O) as elementwise passes (faster on CPU)


def _shifted(x: Tensor) -> tuple[Tensor, Tensor]:
    """(x - m, m), m the max over the last dim (0 for an all -inf row)."""
    m = x.amax(-1, keepdim=True)
    m = torch.where(torch.isneginf(m), 0.0, m)
    return x - m, m


def softmax(x: Tensor) -> Tensor:
    """softmax over the last dimension (NaN rows where every entry is -inf, as torch's)."""
    e = _shifted(x)[0].exp_()
    return e / e.sum(-1, keepdim=True)


def log_softmax(x: Tensor) -> Tensor:
    """log_softmax over the last dimension (NaN rows where every entry is -inf, as torch's)."""
    z, _ = _shifted(x)
    return z - z.exp().sum(-1, keepdim=True).log()


def logsumexp(x: Tensor) -> Tensor:
    """logsumexp over the last dimension, dropped (-inf where every entry is -inf)."""
    z, m = _shifted(x)
    return (z.exp().sum(-1, keepdim=True).log() + m).squeeze(-1)
