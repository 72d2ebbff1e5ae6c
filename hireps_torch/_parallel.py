"""A population's members side by side on the cores torch's threads leave idle (same results)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import torch

__all__ = ["MIN_SIZE", "idle_workers", "member_chunks", "side_by_side"]

MIN_SIZE = 2**16
"""Fewest tensor elements one member's work must touch to get a thread (why:
benchmarks/README.md, "Members side by side")."""

T = TypeVar("T")
R = TypeVar("R")


def idle_workers(device: torch.device) -> int:
    """On the CPU, usable cores // torch's intra-op threads; 1 elsewhere."""
    if device.type != "cpu":
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, (cores or 1) // torch.get_num_threads())


def side_by_side(
    fn: Callable[[T], R], items: Sequence[T], device: torch.device, size: int
) -> list[R]:
    """``[fn(item) for item in items]``, in threads on the idle cores when ``size`` >=
    :data:`MIN_SIZE`."""
    workers = min(len(items), idle_workers(device)) if size >= MIN_SIZE else 1
    if workers <= 1:
        return [fn(item) for item in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(fn, items))


def member_chunks(members: int, device: torch.device, size: int) -> list[slice]:
    """Contiguous slices of ``members``, one per idle worker when ``size`` >= :data:`MIN_SIZE`."""
    n = max(1, min(members, idle_workers(device))) if size >= MIN_SIZE else 1
    bounds = [round(i * members / n) for i in range(n + 1)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
