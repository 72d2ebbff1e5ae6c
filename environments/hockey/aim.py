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

from environments.hockey.kinematics import ArmGeometry, arm_kinematics
from hireps_torch.checks import as_finite_f64, as_float

__all__ = ["aim_angle", "aim_slopes", "aimed_shot", "blade_twist", "rotation_z"]

_GEOMETRY = ArmGeometry()  # the default geometry (a frozen dataclass)


def rotation_z(phi: float) -> Tensor:
    """(3, 3) rotation by ``phi`` rad about the world's vertical (z) axis."""
    c, s = math.cos(phi), math.sin(phi)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def blade_twist(q: Tensor, qdot: Tensor, geometry: ArmGeometry = _GEOMETRY) -> Tensor:
    """(6,) blade twist ``[v, omega]`` (linear velocity of the blade centre, angular velocity,
    world frame) of the arm at joints ``q`` (7,) moving at ``qdot`` (7,)."""
    J = arm_kinematics(geometry).chain.jacobian(q.reshape(1, 7))[0]
    return J @ qdot


def aimed_shot(demo: Tensor, phi: float, geometry: ArmGeometry = _GEOMETRY) -> Tensor:
    """The demo shot turned by ``phi`` about the vertical axis through the control puck's spot.

    Args:
        demo: (14,) the demo shot's action ``[goal, goal velocity]`` (see
            :func:`~environments.hockey.demo_action`).
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
    turn = as_float("phi", phi)
    if not math.isfinite(turn):
        raise ValueError(f"phi must be finite, got {phi}")
    if turn == 0.0:
        return a.clone()
    kin = arm_kinematics(geometry)
    g0, gd0 = a[:7], a[7:]
    position, rotation = kin.blade_pose(g0)
    Rz = rotation_z(turn)
    # the spot's vertical axis passes through the blade centre: only the orientation turns
    goal = kin.inverse(position.reshape(1, 3), (Rz @ rotation).reshape(1, 3, 3), g0)[0]
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
    dx = float(t[0]) - geometry.puck_x
    if dx <= 0.0:
        raise ValueError(
            f"target ({float(t[0]):.6g}, {float(t[1]):.6g}) is not beyond the control puck's "
            f"spot (x = {geometry.puck_x})"
        )
    return math.atan2(float(t[1]), dx)


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
    phi = aim_angle(t, geometry)
    h = as_float("step", step)
    if not (math.isfinite(h) and h > 0):
        raise ValueError(f"step must be finite and > 0, got {step}")
    d_shot = (aimed_shot(demo, phi + h, geometry) - aimed_shot(demo, phi - h, geometry)) / (2 * h)
    dx, dy = float(t[0]) - geometry.puck_x, float(t[1])
    r2 = dx * dx + dy * dy
    d_phi = torch.tensor([-dy / r2, dx / r2], dtype=torch.float64)
    return d_shot[:, None] * d_phi[None, :]
