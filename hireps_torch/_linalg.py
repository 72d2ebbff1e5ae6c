"""Linear algebra that works on every device, and softmaxes over a short last dimension."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

__all__ = ["log_softmax", "logsumexp", "matmul_each", "min_norm_lstsq", "reduce_each", "softmax"]


def min_norm_lstsq(A: Tensor, B: Tensor) -> Tensor:
    """Minimum-norm least-squares X (..., P, Q) of A (..., M, P) X = B (..., M, Q): gelsd on the
    CPU, elsewhere the pseudo-inverse with gelsd's default cut (same rank on both)."""
    if A.device.type == "cpu":
        x: Tensor = torch.linalg.lstsq(A, B, driver="gelsd").solution
    else:
        cut = torch.finfo(A.dtype).eps * max(A.shape[-2], A.shape[-1])
        x = torch.linalg.pinv(A, rtol=cut) @ B
    return x


def matmul_each(a: Tensor, b: Tensor) -> Tensor:
    """a @ b member by member on the CPU: a tensor of 3 or more dimensions holds S members along
    its first (1: the same for every member; both such tensors of one rank), a 2-D one is
    shared. Each member's product is the call its own run makes (a population of one, shapes
    (1, ..., M, K)) on a copy of its own: MKL rounds a product's entries by the batch size, the
    rows around them and their memory alignment, so a member's sums round as in its own run.
    Elsewhere (and for one member or none) the product itself."""
    lead = [t.shape[0] for t in (a, b) if t.dim() > 2]
    S = max(lead, default=0)
    if a.device.type != "cpu" or S <= 1 or (a.dim() > 2 and b.dim() > 2 and a.dim() != b.dim()):
        return a @ b
    if any(n not in (1, S) for n in lead):
        raise ValueError(f"matmul_each: member counts {lead} of shapes {a.shape} @ {b.shape}")

    def member(t: Tensor, s: int) -> Tensor:
        return t if t.dim() <= 2 else t[s : s + 1].clone() if t.shape[0] > 1 else t.clone()

    return torch.cat([member(a, s) @ member(b, s) for s in range(S)])


def reduce_each(
    t: Tensor, op: Literal["sum", "mean"], dim: int | tuple[int, ...], keepdim: bool = False
) -> Tensor:
    """``t.sum`` / ``t.mean`` (``op``) over ``dim`` one leading index at a time (the dimensions
    before the first reduced one: a population's members) on the CPU with several torch
    threads: torch splits a reduction of 32768 or more numbers across its threads when it is
    the only output, as in a member's own run, and not when it is one of S."""
    dims = [d % t.dim() for d in ((dim,) if isinstance(dim, int) else dim)]
    first = min(dims)
    lead = t.shape[:first]
    fn = torch.sum if op == "sum" else torch.mean
    if t.device.type != "cpu" or torch.get_num_threads() == 1 or lead.numel() <= 1:
        return fn(t, dim, keepdim=keepdim)
    flat = t.reshape(-1, *t.shape[first:])
    inner = tuple(d - first + 1 for d in dims)
    out = torch.cat([fn(flat[i : i + 1], inner, keepdim=keepdim) for i in range(len(flat))])
    return out.reshape(*lead, *out.shape[1:])


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
