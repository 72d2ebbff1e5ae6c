"""Aiming the demonstrated shot at the target puck (pytorch-kinematics).

The demonstration swings the blade square to the +x axis through the control puck's spot, so
its shot sends the control puck (and, on a straight hit, the target puck) along +x from
there. A target at ``(x, y)`` lies at the angle ``phi = atan2(y, x - puck_x)`` seen from that
spot. :func:`aimed_shot` turns the whole swing by ``phi`` about the vertical axis through the
spot: at the goal the blade is where the demo's is (its centre is on the axis), its
orientation turned by ``phi``; the goal posture comes from pytorch-kinematics' IK started at
the demo's goal, and the goal velocity gives the blade the demo's twist turned by ``phi``
(the smallest change of the demo's goal velocity that does, through the Jacobian's
pseudo-inverse; the arm has 7 joints for a 6-D twist). :func:`aim_slopes` linearises the map
from the target's position to the 14 action numbers: the initial slopes of an option that
re-aims from what it observes (the hockey experiments' default; ``--no-aim-slopes`` turns
it off).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hireps_torch.checks import as_finite_f64, as_float
from hireps_torch.envs.hockey.kinematics import ArmGeometry, arm_kinematics
from hireps_torch.features import FeatureMap

__all__ = [
    "AimFeatures",
    "aim_angle",
    "aim_slopes",
    "aimed_shot",
    "blade_twist",
    "rotation_z",
    "turn_derivative",
]

_GEOMETRY = ArmGeometry()  # the default geometry (a frozen dataclass)
MAX_STEP = 0.5
"""The largest finite-difference step (rad) of :func:`turn_derivative` and :func:`aim_slopes`."""


def _angle(name: str, value: object) -> float:
    """A finite angle (rad) as a float; a bool, a non-number or a non-finite value raises
    naming ``name``."""
    if isinstance(value, bool):
        raise TypeError(f"{name} must be a number (rad), got the bool {value!r}")
    a = as_float(name, value)
    if not math.isfinite(a):
        raise ValueError(f"{name} must be finite, got {value}")
    return a


def _joints(name: str, value: Tensor) -> Tensor:
    """(7,) finite float64 joint values; another shape raises naming ``name``."""
    t = as_finite_f64(name, value)
    if t.shape != (7,):
        raise ValueError(f"{name} must have shape (7,), got {tuple(t.shape)}")
    return t


def rotation_z(phi: float) -> Tensor:
    """(3, 3) rotation by ``phi`` rad about the world's vertical (z) axis."""
    phi = _angle("phi", phi)
    c, s = math.cos(phi), math.sin(phi)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def blade_twist(q: Tensor, qdot: Tensor, geometry: ArmGeometry = _GEOMETRY) -> Tensor:
    """(6,) blade twist ``[v, omega]`` (linear velocity of the blade centre, angular velocity,
    world frame) of the arm at joints ``q`` (7,) moving at ``qdot`` (7,)."""
    q, qdot = _joints("q", q), _joints("qdot", qdot)
    J = arm_kinematics(_geometry(geometry)).chain.jacobian(q.reshape(1, 7))[0]
    return J @ qdot


def _geometry(geometry: object) -> ArmGeometry:
    if not isinstance(geometry, ArmGeometry):
        raise TypeError(f"geometry must be an ArmGeometry, got {type(geometry).__name__}")
    return geometry


def aimed_shot(demo: Tensor, phi: float, geometry: ArmGeometry = _GEOMETRY) -> Tensor:
    """The demo shot turned by ``phi`` about the vertical axis through the control puck's spot.

    Args:
        demo: (14,) the demo shot's action ``[goal, goal velocity]`` (see
            :func:`~hireps_torch.envs.hockey.demo_action`).
        phi: the turn (rad, counter-clockwise seen from above; positive aims toward +y).
        geometry: the arm's stick and demo geometry.

    Returns:
        (14,) float64 ``[goal, goal velocity]``: ``phi = 0`` gives ``demo`` back.

    Raises:
        ValueError: for a demo of another shape or a non-finite entry or angle; RuntimeError
            when the IK cannot reach the turned pose (|phi| far beyond the arm's range).
    """
    a = as_finite_f64("demo", demo)
    if a.shape != (14,):
        raise ValueError(f"demo must have shape (14,), got {tuple(a.shape)}")
    turn = _angle("phi", phi)
    if turn == 0.0:
        return a.clone()
    kin = arm_kinematics(_geometry(geometry))
    g0, gd0 = a[:7], a[7:]
    position, rotation = kin.blade_pose(g0)
    Rz = rotation_z(turn)
    # the spot's vertical axis passes through the blade centre: only the orientation turns
    try:
        goal = kin.inverse(position.reshape(1, 3), (Rz @ rotation).reshape(1, 3, 3), g0)[0]
    except RuntimeError as e:
        raise RuntimeError(f"the shot cannot be turned by phi = {turn} rad: {e}") from None
    twist0 = blade_twist(g0, gd0, geometry)
    twist = torch.cat([Rz @ twist0[:3], Rz @ twist0[3:]])
    J = kin.chain.jacobian(goal.reshape(1, 7))[0]
    velocity = gd0 + torch.linalg.pinv(J) @ (twist - J @ gd0)
    return torch.cat([goal, velocity])


def aim_angle(target: Tensor, geometry: ArmGeometry = _GEOMETRY) -> float:
    """The angle (rad) at which a target at ``target`` (2,) = (x, y) m lies, seen from the
    control puck's spot (0 straight out along +x)."""
    t = as_finite_f64("target", target)
    if t.shape != (2,):
        raise ValueError(f"target must have shape (2,), got {tuple(t.shape)}")
    dx = float(t[0]) - _geometry(geometry).puck_x
    if dx <= 0.0:
        raise ValueError(
            f"target ({float(t[0]):.6g}, {float(t[1]):.6g}) is not beyond the control puck's "
            f"spot (x = {geometry.puck_x})"
        )
    return math.atan2(float(t[1]), dx)


def turn_derivative(
    demo: Tensor, phi: float = 0.0, geometry: ArmGeometry = _GEOMETRY, step: float = 0.02
) -> Tensor:
    """(14,) derivative of :func:`aimed_shot` in the turn at ``phi``: central differences
    with ``step`` rad, in (0, 0.5]."""
    phi = _angle("phi", phi)
    h = as_float("step", step)
    if not (math.isfinite(h) and 0 < h <= MAX_STEP):
        raise ValueError(f"step must be in (0, {MAX_STEP}] rad, got {step}")
    return (aimed_shot(demo, phi + h, geometry) - aimed_shot(demo, phi - h, geometry)) / (2 * h)


class AimFeatures(FeatureMap):
    """The target's position as seen from the control puck's spot: ``(x, y) -> (phi, rho)``,
    ``phi = atan2(y, x - puck_x)`` the aim angle and ``rho`` the distance (m); (..., 2) ->
    (..., 2). Options linear in these features turn the shot with the aim angle at any
    distance, where options linear in (x, y) over- or under-turn away from the point their
    slopes were fitted at."""

    def __init__(self, geometry: ArmGeometry = _GEOMETRY) -> None:
        super().__init__()
        self.in_features, self.out_features = 2, 2
        self.puck_x = float(_geometry(geometry).puck_x)

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., 2) target positions -> (..., 2) (angle, distance)."""
        x = self._input(x)
        dx, dy = x[..., 0] - self.puck_x, x[..., 1]
        return torch.stack([torch.atan2(dy, dx), torch.hypot(dx, dy)], dim=-1)


def aim_slopes(
    demo: Tensor,
    target: Tensor,
    geometry: ArmGeometry = _GEOMETRY,
    step: float = 0.02,
) -> Tensor:
    """(14, 2) derivative of ``aimed_shot(demo, aim_angle(p))`` with respect to the target's
    position ``p`` at ``target``: central differences of the shot in ``phi`` (``step`` rad)
    times the angle's gradient ``(-y, x - puck_x) / r^2``."""
    t = as_finite_f64("target", target)
    d_shot = turn_derivative(demo, aim_angle(t, geometry), geometry, step)
    dx, dy = float(t[0]) - geometry.puck_x, float(t[1])
    r2 = dx * dx + dy * dy
    d_phi = torch.tensor([-dy / r2, dx / r2], dtype=torch.float64)
    return d_shot[:, None] * d_phi[None, :]
