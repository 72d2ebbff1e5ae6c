"""Tetherball, simulated: a ball on a string tied to a pole, hit towards a target behind it.

Spec sheet
==========
Seen from above (no gravity in the plane). A pole of radius ``r`` stands at the origin; a
string of length ``L`` is tied to the pole's surface at the anchor ``A = r (cos a, sin a)``
facing the ball's start. The ball (a point of unit mass) starts at rest at ``(x0, y0)``; the
episode's parameters are the impulse it is given, i.e. its start velocity.

Physics (pure, batched: :func:`simulate`)
    The ball flies straight while the string is slack, slowed by air drag ``v' = -c v``. The
    string wraps around the pole as the ball passes it: with ``w`` the angle of string lying on
    the pole (signed: > 0 wound counter-clockwise, < 0 clockwise, 0 straight from the anchor),
    the free length is ``L - r |w|`` and the free part runs from the tangent point
    ``T = r (cos(a + w), sin(a + w))`` to the ball. When the free part reaches its length the
    string is taut: the catch removes the ball's outward velocity along the string (an
    inelastic jerk), and while it stays taut the string only turns the velocity (speed kept:
    a string wrapping on a fixed pole does no work). A ball that hits the pole (closer than
    ``r + ball_radius`` to its axis) stops there. Symplectic Euler steps of ``dt`` for
    ``duration`` seconds.

Parameters, context, reward
    ``theta`` in R^2: the impulse (m/s). Context ``s = x0`` (m), drawn uniformly from
    ``[-context_range, context_range]``. Reward ``R = -min_t ||p(t) - g||^2 - effort ||theta||^2``
    with ``g`` the target: the paper's closest-approach reward plus a small effort cost.

Solution classes (:meth:`Tetherball.solution_class`)
    The straight line from the start to the target runs through the pole, so the ball reaches
    the target only by passing the pole on one side, which winds the string that way: class 0
    when the ball comes within ``tolerance`` of the target with the string wound
    counter-clockwise (passing the pole on its right, seen from the start), 1 clockwise, -1 when
    it never comes that close.

Constants
    ==========================  ==============  =======================================
    impulse as parameters       2-D             paper (AISTATS 2012)
    context: start x            +-0.3 m         paper (the ball's initial x); range ours
    reward: closest approach    -min d^2        paper
    effort cost                 0.002 s^2/m^2   our choice: without it every impulse that
                                                carries the ball past the target on a taut
                                                string scores the same (a plateau)
    pole radius r               0.1 m           our choice
    ball radius                 0.05 m          our choice
    string length L             0.87 m          our choice: wound around either side, a
                                                taut string carries the ball within 1 cm
                                                of the target (so that every start has
                                                two solution families)
    anchor angle a              -pi/2           our choice (the side facing the start)
    start y0                    -0.9 m          our choice (the string slack at the start)
    target g                    (0, 0.7) m      our choice (behind the pole)
    drag c                      0.5 1/s         our choice
    duration, dt                3 s, 10 ms      our choice (classes agree with 1 ms steps
                                                for 99.5% of random impulses)
    success tolerance           0.1 m           our choice
    ==========================  ==============  =======================================

:class:`Tetherball` is the pure batched task (contexts ``([S,] N, 1)``, theta ``([S,] N, 2)``
-> ``([S,] N)``, on any device); :class:`TetherballEnv` (gymnasium id ``hireps/Tetherball-v0``)
is its one-step episodic adapter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from hireps_torch.checks import check_generator
from hireps_torch.envs._common import EpisodicGymEnv, check_fields

__all__ = ["Flight", "Tetherball", "TetherballEnv", "simulate"]


class Flight(NamedTuple):
    """What :func:`simulate` returns (leading shape ``B``: the batch)."""

    closest: Tensor
    """(B,) the smallest distance to the target (m)."""
    wound: Tensor
    """(B,) the string's wrap angle w at that moment (rad; > 0 counter-clockwise)."""
    path: Tensor | None
    """(T + 1, B, 2) positions, with ``keep_path``."""
    free: Tensor | None
    """(T + 1, B) the string's used length ``r |w| + |free part|``, with ``keep_path``."""
    speed: Tensor | None
    """(T + 1, B) the ball's speed, with ``keep_path``."""


@dataclass(frozen=True)
class Tetherball:
    """The tetherball task (see the module docstring)."""

    pole_radius: float = 0.1
    ball_radius: float = 0.05
    string_length: float = 0.87
    anchor_angle: float = -math.pi / 2
    start_y: float = -0.9
    context_range: float = 0.3
    target_x: float = 0.0
    target_y: float = 0.7
    drag: float = 0.5
    duration: float = 3.0
    dt: float = 0.01
    effort: float = 0.002
    tolerance: float = 0.1

    param_dim: int = 2
    context_dim: int = 1
    n_classes: int = 2

    def __post_init__(self) -> None:
        check_fields(
            self,
            ("pole_radius", "string_length", "duration", "dt", "tolerance"),
            ("ball_radius", "drag", "effort", "context_range"),
        )
        for name in ("anchor_angle", "start_y", "target_x", "target_y"):
            if not math.isfinite(float(getattr(self, name))):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)}")
        if self.string_length <= 2 * math.pi * self.pole_radius:
            raise ValueError("string_length must exceed the pole's circumference")
        ax, ay = (
            self.pole_radius * math.cos(self.anchor_angle),
            self.pole_radius * math.sin(self.anchor_angle),
        )
        far = max(
            math.hypot(x - ax, self.start_y - ay) for x in (-self.context_range, self.context_range)
        )
        if far >= self.string_length:
            raise ValueError(
                f"the ball must start within the string's reach: a start {far:.3f} m from the "
                f"anchor, string_length {self.string_length}"
            )

    @property
    def steps(self) -> int:
        return int(round(self.duration / self.dt))

    def sample_contexts(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """(n, 1) start x, uniform in ``[-context_range, context_range]``."""
        g = check_generator("generator", generator)
        u = torch.rand(n, 1, dtype=torch.float64, generator=g)
        return (2 * u - 1) * self.context_range

    def _checked(self, contexts: Tensor | None, theta: Tensor) -> tuple[Tensor, Tensor]:
        if theta.dim() not in (2, 3) or theta.shape[-1] != 2:
            raise ValueError(f"theta must have shape ([S,] N, 2), got {tuple(theta.shape)}")
        if contexts is None or tuple(contexts.shape) != (*theta.shape[:-1], 1):
            got = None if contexts is None else tuple(contexts.shape)
            raise ValueError(f"contexts must have shape {(*theta.shape[:-1], 1)}, got {got}")
        for name, value in (("theta", theta), ("contexts", contexts)):
            if not bool(torch.isfinite(value).all()):
                raise ValueError(f"{name} holds non-finite entries")
        return contexts.to(torch.float64), theta.to(torch.float64)

    def flight(self, contexts: Tensor | None, theta: Tensor, keep_path: bool = False) -> Flight:
        """:func:`simulate` of the episodes (leading shape ``([S,] N)``)."""
        c, t = self._checked(contexts, theta)
        lead = t.shape[:-1]
        start = torch.stack([c[..., 0], torch.full_like(c[..., 0], self.start_y)], -1)
        out = simulate(self, start.reshape(-1, 2), t.reshape(-1, 2), keep_path)
        return Flight(
            out.closest.reshape(lead),
            out.wound.reshape(lead),
            *(None if x is None else x.reshape(x.shape[0], *lead, *x.shape[2:]) for x in out[2:]),
        )

    def __call__(self, contexts: Tensor | None, theta: Tensor) -> Tensor:
        """Returns ``([S,] N)`` of contexts ``([S,] N, 1)`` and impulses ``([S,] N, 2)``."""
        f = self.flight(contexts, theta)
        return -(f.closest**2) - self.effort * (theta.to(torch.float64) ** 2).sum(-1)

    def solution_class(self, contexts: Tensor | None, theta: Tensor) -> Tensor:
        """``([S,] N)`` int64: 0 wound counter-clockwise, 1 clockwise (within ``tolerance``
        of the target), else -1."""
        f = self.flight(contexts, theta)
        side = torch.where(f.wound > 0, 0, 1)
        return torch.where(f.closest <= self.tolerance, side, torch.full_like(side, -1))


def simulate(task: Tetherball, start: Tensor, velocity: Tensor, keep_path: bool = False) -> Flight:
    """Fly B balls from ``start (B, 2)`` with ``velocity (B, 2)`` (see the module docstring)."""
    r, L, a = task.pole_radius, task.string_length, task.anchor_angle
    dt, hit = task.dt, task.pole_radius + task.ball_radius
    dev = start.device
    anchor = torch.tensor([r * math.cos(a), r * math.sin(a)], dtype=torch.float64, device=dev)
    normal = anchor / r  # outward at the anchor
    tangent = torch.stack([-normal[1], normal[0]])  # counter-clockwise at the anchor
    target = torch.tensor([task.target_x, task.target_y], dtype=torch.float64, device=dev)
    decay = math.exp(-task.drag * dt)
    p, v = start.clone(), velocity.clone()
    B = p.shape[0]
    w = torch.zeros(B, dtype=torch.float64, device=dev)
    alive = torch.ones(B, dtype=torch.bool, device=dev)
    taut = torch.zeros(B, dtype=torch.bool, device=dev)
    closest = (p - target).norm(dim=-1)
    wound = w.clone()
    path, used, speeds = [p.clone()], [(p - anchor).norm(dim=-1)], [v.norm(dim=-1)]
    for _ in range(task.steps):
        v = torch.where(alive[:, None], v * decay, v)
        p = torch.where(alive[:, None], p + dt * v, p)
        rho = p.norm(dim=-1)
        # the wrap angle: where the free part leaves the pole (tangent from the ball)
        straight = w == 0
        begins = straight & (((p - anchor) @ normal) < 0)
        side = torch.where(straight, torch.sign((p - anchor) @ tangent), torch.sign(w))
        beta = torch.atan2(p[:, 1], p[:, 0])
        tau = beta - side * torch.acos((r / rho).clamp(max=1.0))
        lifted = tau - a
        lifted = lifted + 2 * math.pi * torch.round((w - lifted) / (2 * math.pi))
        wrapped = (~straight | begins) & (side * lifted > 0)
        w = torch.where(wrapped, lifted, torch.zeros_like(w))
        # the free part and its length
        corner = torch.stack([r * torch.cos(a + w), r * torch.sin(a + w)], -1)
        base = torch.where(wrapped[:, None], corner, anchor)
        free = p - base
        length = free.norm(dim=-1)
        direction = free / length.clamp_min(1e-12)[:, None]
        room = L - r * w.abs()
        now_taut = alive & (length >= room)
        p = torch.where(now_taut[:, None], base + direction * room[:, None], p)
        outward = (v * direction).sum(-1).clamp_min(0.0)
        turned = v - outward[:, None] * direction
        kept = turned * (v.norm(dim=-1) / turned.norm(dim=-1).clamp_min(1e-300))[:, None]
        # a catch loses the outward velocity; a string already taut only turns it
        v = torch.where((now_taut & taut)[:, None], kept, torch.where(now_taut[:, None], turned, v))
        taut = now_taut
        stopped = alive & (p.norm(dim=-1) < hit)
        v = torch.where(stopped[:, None], torch.zeros_like(v), v)
        alive = alive & ~stopped
        distance = (p - target).norm(dim=-1)
        nearer = distance < closest
        closest = torch.where(nearer, distance, closest)
        wound = torch.where(nearer, w, wound)
        if keep_path:
            path.append(p.clone())
            used.append(r * w.abs() + (p - base).norm(dim=-1))
            speeds.append(v.norm(dim=-1))
    if not keep_path:
        return Flight(closest, wound, None, None, None)
    return Flight(closest, wound, torch.stack(path), torch.stack(used), torch.stack(speeds))


class TetherballEnv(EpisodicGymEnv):
    """Gymnasium adapter: ``reset()`` draws the start x (observation (1,)), ``step(theta)``
    flies the ball: the reward, ``terminated=True`` and ``info["solution_class"]``."""

    def __init__(self, task: Tetherball | None = None) -> None:
        super().__init__(task or Tetherball())
