"""Helpers shared by the task modules (not part of their public API)."""

from __future__ import annotations

import torch
from torch import Tensor


def check_scalar_action(action: Tensor, batch: int, what: str) -> Tensor:
    """Validate a (B,) or (B, 1) action holding one number per system; returns (B,).

    Args:
        action: the action batch.
        batch: B.
        what: what one number is, for the error messages (e.g. "desired angle").
    """
    a = torch.as_tensor(action)
    if a.dim() == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.shape != (batch,):
        raise ValueError(
            f"action must have shape ({batch},) or ({batch}, 1) (one {what} per system), "
            f"got {tuple(a.shape)}"
        )
    bad = ~torch.isfinite(a)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"action contains a non-finite {what} at index {i}: {a[i].item()}")
    return a
