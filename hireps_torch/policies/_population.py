"""Helpers for populations: S independent policies stacked along a leading dimension of every
input and output (``stack`` builds one, ``member`` takes one out); each member may sample from
its own generator and then draws what it would alone."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from hireps_torch.checks import check_generator

__all__ = ["Generators", "categorical", "check_members", "check_population_generators", "normal"]

Generators = torch.Generator | Sequence[torch.Generator] | None
"""None, one generator, or (for a population) one generator per member."""


def check_members(name: str, members: object, cls: type) -> list[Any]:
    """``members`` as a non-empty list of ordinary ``cls`` modules on one device."""
    if isinstance(members, torch.nn.Module) or not isinstance(members, Sequence):
        raise TypeError(
            f"{name} must be a sequence of {cls.__name__}s, got {type(members).__name__}"
        )
    items = list(members)
    if not items:
        raise ValueError(f"{name} must hold at least one {cls.__name__}, got none")
    for s, m in enumerate(items):
        if not isinstance(m, cls):
            raise TypeError(f"{name}[{s}] must be a {cls.__name__}, got {type(m).__name__}")
        if getattr(m, "population", None) is not None:
            raise ValueError(f"{name}[{s}] is a population already; stack ordinary modules")
    first = _devices(items[0])
    for s, m in enumerate(items[1:], 1):
        if _devices(m) != first:
            raise ValueError(
                f"{name}[{s}] is on device {sorted(_devices(m))} but {name}[0] on "
                f"{sorted(first)}: move them to one device first (e.g. .to('cpu'))"
            )
    return items


def _devices(module: torch.nn.Module) -> set[str]:
    """The devices of a module's parameters and buffers."""
    return {str(t.device) for t in [*module.parameters(), *module.buffers()]}


def check_population_generators(
    population: int | None, generator: object
) -> torch.Generator | list[torch.Generator] | None:
    """``generator`` checked: None, a ``torch.Generator`` or (population) S generators."""
    if population is None or generator is None or isinstance(generator, torch.Generator):
        return check_generator("generator", generator)
    if not isinstance(generator, Sequence) or isinstance(generator, str | bytes):
        raise TypeError(
            "generator must be a torch.Generator, None or one generator per member, got "
            f"{type(generator).__name__}"
        )
    gens = list(generator)
    if len(gens) != population:
        raise ValueError(
            f"a population of {population} needs one generator per member, got {len(gens)}"
        )
    for s, g in enumerate(gens):
        check_generator(f"generator[{s}]", g)
    return gens


def normal(
    shape: tuple[int, ...],
    generator: torch.Generator | list[torch.Generator] | None,
    dtype: torch.dtype,
    device: torch.device,
) -> Tensor:
    """Standard normal draws of ``shape`` on ``device``, drawn on the generator's device; with
    S generators member s's ``shape[1:]`` come from ``generator[s]``."""
    if isinstance(generator, list):
        draws = [
            torch.randn(shape[1:], generator=g, dtype=dtype, device=g.device) for g in generator
        ]
        return torch.stack(draws).to(device)  # one transfer
    where = device if generator is None else generator.device
    return torch.randn(shape, generator=generator, dtype=dtype, device=where).to(device)


def categorical(probs: Tensor, generator: torch.Generator | list[torch.Generator] | None) -> Tensor:
    """One int64 index per row of ``probs`` (..., O), ``torch.multinomial(p, 1)``'s draw bit
    for bit (argmax of p / q, q ~ Exp(1)); generators as in :func:`normal`."""
    if isinstance(generator, list):
        host = probs.to(generator[0].device)  # one transfer
        pairs = zip(host, generator, strict=True)
        q = torch.stack([torch.empty_like(p).exponential_(1, generator=g) for p, g in pairs])
    else:
        host = probs if generator is None else probs.to(generator.device)
        q = torch.empty_like(host).exponential_(1, generator=generator)
    return (host / q).argmax(-1).to(probs.device)
