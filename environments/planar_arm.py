"""Four-goal planar reaching arm: one task, four equally good solutions.

Spec sheet
==========
Parameters (one vector per episode)
    ``theta`` in R^10: the joint angles (rad) of a planar arm of 10 links of unit length, its
    base at the origin. Joint ``j`` turns link ``j`` against link ``j - 1`` (joint 1 against the
    x axis), so link ``j`` points at ``phi_j = theta_1 + ... + theta_j`` and the end effector is

        x(theta) = sum_j (cos phi_j, sin phi_j).

Reward (one number per episode; no context)
    ``R(theta) = -min_g ||x(theta) - g||^2 - c * sum_{j >= 2} theta_j^2``: the squared distance
    to the closest goal and a posture cost on every joint but the base. Turning the base by
    a multiple of pi/2 carries a posture from one goal to the next at the same cost, so the
    four goals are equally good.

Solution classes (:meth:`PlanarArm.solution_class`)
    ``k`` when the end effector lies within ``tolerance`` of goal ``k`` (0: (7, 0), 1: (0, 7),
    2: (-7, 0), 3: (0, -7)), else -1.

Constants
    ==========================  ================  =====================================
    links                       10, length 1      the VIPS planar reacher (issue 70)
    goals                       (+-7, 0), (0, +-7)  the VIPS four-goal task (issue 70)
    posture cost c              0.01              our choice ("a small cost")
    success tolerance           0.5               our choice (5% of the arm's reach)
    ==========================  ================  =====================================

:class:`PlanarArm` is the pure batched task (``theta ([S,] N, 10)`` -> ``([S,] N)``, on any
device); :class:`PlanarArmEnv` (gymnasium id ``hireps/PlanarArm-v0``) is its one-step episodic
adapter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from hireps_torch.envs._common import EpisodicGymEnv, check_fields

__all__ = ["PlanarArm", "PlanarArmEnv", "end_effector"]


def end_effector(theta: Tensor) -> Tensor:
    """Where the arm's tip is: ``theta ([S,] N, J)`` joint angles -> ``([S,] N, 2)``."""
    phi = theta.cumsum(-1)
    return torch.stack([phi.cos().sum(-1), phi.sin().sum(-1)], -1)


@dataclass(frozen=True)
class PlanarArm:
    """The four-goal planar arm (see the module docstring)."""

    n_links: int = 10
    goal_distance: float = 7.0
    posture_cost: float = 0.01
    tolerance: float = 0.5

    context_dim: int = 0
    n_classes: int = 4

    def __post_init__(self) -> None:
        if isinstance(self.n_links, bool) or not isinstance(self.n_links, int) or self.n_links < 2:
            raise ValueError(f"n_links must be an integer >= 2, got {self.n_links!r}")
        check_fields(self, ("goal_distance", "tolerance"), ("posture_cost",))
        if self.goal_distance >= self.n_links:
            raise ValueError(
                f"goal_distance must be below the arm's reach {self.n_links}, got "
                f"{self.goal_distance}"
            )

    @property
    def param_dim(self) -> int:
        return self.n_links

    def goals(self, dtype: torch.dtype = torch.float64, device: Any = None) -> Tensor:
        """(4, 2): goal k at angle k pi/2, ``goal_distance`` from the base."""
        angle = torch.arange(4, dtype=dtype, device=device) * (math.pi / 2)
        return self.goal_distance * torch.stack([angle.cos(), angle.sin()], -1).round(decimals=12)

    def _distances(self, theta: Tensor) -> Tensor:
        if theta.dim() not in (2, 3) or theta.shape[-1] != self.n_links:
            raise ValueError(
                f"theta must have shape ([S,] N, {self.n_links}), got {tuple(theta.shape)}"
            )
        if not bool(torch.isfinite(theta).all()):
            raise ValueError("theta holds non-finite entries")
        tip = end_effector(theta)
        return (tip[..., None, :] - self.goals(theta.dtype, theta.device)).norm(dim=-1)

    def __call__(self, contexts: Tensor | None, theta: Tensor) -> Tensor:
        """Returns ``([S,] N)`` of ``theta ([S,] N, n_links)`` (``contexts``: None)."""
        d = self._distances(theta).amin(-1)
        return -(d**2) - self.posture_cost * (theta[..., 1:] ** 2).sum(-1)

    def solution_class(self, contexts: Tensor | None, theta: Tensor) -> Tensor:
        """``([S,] N)`` int64: the goal within ``tolerance`` of the tip, else -1."""
        d, goal = self._distances(theta).min(-1)
        return torch.where(d <= self.tolerance, goal, torch.full_like(goal, -1))

    def sample_contexts(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """No context: ``(n, 0)`` (the generator is not drawn from)."""
        return torch.zeros(n, 0, dtype=torch.float64)


class PlanarArmEnv(EpisodicGymEnv):
    """Gymnasium adapter: ``reset()`` gives an empty observation, ``step(theta)`` the reward,
    ``terminated=True`` and ``info["solution_class"]``."""

    def __init__(self, task: PlanarArm | None = None) -> None:
        super().__init__(task or PlanarArm())
