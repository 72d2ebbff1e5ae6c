"""Toy multimodal objectives for episodic (contextual) policy search.

Spec sheet
----------
``TwoGaussians`` (the two-Gaussians task of the AISTATS 2012 HiREPS paper):
    parameters  theta in R^2 (unbounded)
    reward      R(theta) = sum_m h_m exp(-||theta - mu_m||^2 / (2 w^2))
    constants   mu_1 = (-2, -2), mu_2 = (2, 2), h = (1, 1), w = 0.5       [choice]
    optimum     R = h_m at theta = mu_m (the bumps are far apart: the cross term is e^-32)
    no context, deterministic; a single Gaussian policy has to pick one mode, a hierarchical
    policy can cover both.
    classes     ``solution_class``: m when theta lies within one bump width w of mu_m (the
                reward there is at least e^-1/2 of the bump's height), else -1      [choice]

``ContextualTwoGaussians`` (contextual variant):
    context     s ~ Uniform[-1, 1] (1-D)
    parameters  theta in R^2
    reward      R(s, theta) = sum_m h_m exp(-||theta - mu_m(s)||^2 / (2 w^2))
    families    mu_1(s) = (-2, -2) + s (1, -1),  mu_2(s) = (2, 2) + s (1, -1)       [choice]
    Both solution families are linear in s, so a linear-Gaussian option can track each one.
    classes     as above, around mu_m(s).

Both objectives are pure batched torch functions; they raise on wrong shapes or non-finite
inputs instead of returning NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from hireps_torch.checks import (
    as_finite_f64,
    as_float,
    as_float_tensor,
    check_count,
    check_generator,
)

__all__ = ["ContextualTwoGaussians", "TwoGaussians", "two_gaussians_reward"]


def two_gaussians_reward(theta: Tensor, modes: Tensor, heights: Tensor, width: float) -> Tensor:
    """Sum of Gaussian bumps.

    Args:
        theta: ([S,] N, 2) parameters (S: a population's members).
        modes: (M, 2) or ([S,] N, M, 2) bump centres (per sample when contextual).
        heights: (M,) bump heights.
        width: bump standard deviation.

    Returns:
        ([S,] N) rewards.
    """
    if theta.dim() not in (2, 3) or theta.shape[-1] != modes.shape[-1]:
        raise ValueError(
            f"theta must have shape ([S,] N, {modes.shape[-1]}), got {tuple(theta.shape)}"
        )
    as_finite_f64("theta", theta)
    d2 = ((theta.unsqueeze(-2) - modes) ** 2).sum(-1)  # ([S,] N, M)
    return (heights * torch.exp(-0.5 * d2 / width**2)).sum(-1)


def nearest_mode(theta: Tensor, modes: Tensor, width: float) -> Tensor:
    """``([S,] N)`` int64: the bump within ``width`` of each theta ``([S,] N, 2)`` (``modes``
    as in :func:`two_gaussians_reward`), else -1."""
    d, m = (theta.unsqueeze(-2) - modes).norm(dim=-1).min(-1)
    return torch.where(d <= width, m, torch.full_like(m, -1))


def _floats(name: str, value: Tensor) -> Tensor:
    """A floating tensor as it is (its dtype kept), anything else (ints, bools) as float64."""
    if isinstance(value, Tensor) and value.is_floating_point():
        return value
    return as_float_tensor(name, value)


def _check_width(width: float) -> None:
    if not (math.isfinite(as_float("width", width)) and width > 0):
        raise ValueError(f"width must be finite and > 0, got {width}")


def _check_table(name: str, value: object, shape: tuple[int | None, ...]) -> int:
    """A finite table of the given shape (None: any size, the same for every None); returns
    the size of the first dimension."""
    t = as_float_tensor(name, value)
    n = t.shape[0] if t.dim() else 0
    want = tuple(n if d is None else d for d in shape)
    if tuple(t.shape) != want or n < 1:
        text = ", ".join("M" if d is None else str(d) for d in shape)
        text = f"({text},)" if len(shape) == 1 else f"({text})"
        rule = " with M >= 1" if None in shape else ""
        raise ValueError(f"{name} must have shape {text}{rule}, got {tuple(t.shape)}")
    as_finite_f64(name, t)
    return n


@dataclass
class TwoGaussians:
    """Bimodal 2-D objective (see the module docstring); ``__call__(theta ([S,] N, 2))`` ->
    ``([S,] N)`` (S: a population's members)."""

    modes: Tensor = field(default_factory=lambda: torch.tensor([[-2.0, -2.0], [2.0, 2.0]]))
    heights: Tensor = field(default_factory=lambda: torch.tensor([1.0, 1.0]))
    width: float = 0.5

    param_dim: int = 2
    context_dim: int = 0

    def __post_init__(self) -> None:
        _check_width(self.width)
        M = _check_table("modes", self.modes, (None, 2))
        _check_table("heights", self.heights, (M,))

    def __call__(self, theta: Tensor) -> Tensor:
        t = _floats("theta", theta)
        return two_gaussians_reward(t, self.modes.to(t.dtype), self.heights.to(t.dtype), self.width)

    @property
    def n_classes(self) -> int:
        return int(self.modes.shape[0])

    def solution_class(self, contexts: Tensor | None, theta: Tensor) -> Tensor:
        """``([S,] N)`` int64: the mode within one bump width of theta, else -1."""
        t = _floats("theta", theta)
        self(t)  # the checks of a reward
        return nearest_mode(t, self.modes.to(t.dtype), self.width)

    @property
    def best_return(self) -> float:
        return float(self.heights.max())


@dataclass
class ContextualTwoGaussians:
    """Contextual bimodal objective; ``__call__(context ([S,] N, 1), theta ([S,] N, 2))`` ->
    ``([S,] N)`` (S: a population's members)."""

    offsets: Tensor = field(default_factory=lambda: torch.tensor([[-2.0, -2.0], [2.0, 2.0]]))
    slope: Tensor = field(default_factory=lambda: torch.tensor([1.0, -1.0]))
    heights: Tensor = field(default_factory=lambda: torch.tensor([1.0, 1.0]))
    width: float = 0.5
    context_low: float = -1.0
    context_high: float = 1.0

    param_dim: int = 2
    context_dim: int = 1

    def modes(self, context: Tensor) -> Tensor:
        """context: ([S,] N, 1) -> bump centres ([S,] N, M, 2)."""
        s = _floats("context", context)
        if s.dim() not in (2, 3) or s.shape[-1] != 1:
            raise ValueError(f"context must have shape ([S,] N, 1), got {tuple(s.shape)}")
        return self.offsets.to(s.dtype) + s[..., None] * self.slope.to(s.dtype)

    def __post_init__(self) -> None:
        _check_width(self.width)
        M = _check_table("offsets", self.offsets, (None, 2))
        _check_table("slope", self.slope, (2,))
        _check_table("heights", self.heights, (M,))
        low = as_float("context_low", self.context_low)
        high = as_float("context_high", self.context_high)
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f"need finite context_low < context_high, got {low}, {high}")

    def sample_contexts(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """(n, 1) contexts uniform in [context_low, context_high]."""
        check_generator("generator", generator)
        u = torch.rand(check_count("n", n, 0), 1, generator=generator, dtype=torch.float64)
        return self.context_low + (self.context_high - self.context_low) * u

    def __call__(self, context: Tensor, theta: Tensor) -> Tensor:
        t = _floats("theta", theta)
        s = as_float_tensor("context", context, t.dtype)
        as_finite_f64("context", s)
        if s.shape[:-1] != t.shape[:-1]:
            raise ValueError(
                f"got contexts of shape {tuple(s.shape)} for parameters of shape "
                f"{tuple(t.shape)} (the same ([S,] N) wanted)"
            )
        return two_gaussians_reward(t, self.modes(s), self.heights.to(t.dtype), self.width)

    @property
    def n_classes(self) -> int:
        return int(self.offsets.shape[0])

    def solution_class(self, contexts: Tensor | None, theta: Tensor) -> Tensor:
        """``([S,] N)`` int64: the mode within one bump width of theta at its context, else -1."""
        if contexts is None:
            raise ValueError("the contextual two Gaussians need contexts ([S,] N, 1)")
        self(contexts, theta)  # the checks of a reward
        t = _floats("theta", theta)
        return nearest_mode(
            t, self.modes(as_float_tensor("context", contexts, t.dtype)), self.width
        )

    @property
    def best_return(self) -> float:
        return float(self.heights.max())
