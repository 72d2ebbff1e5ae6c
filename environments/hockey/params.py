"""The constants of the hockey task: :class:`HockeyParams` (checked when constructed)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from hireps_torch.checks import as_float, check_count
from hireps_torch.envs.hockey.kinematics import ArmGeometry

__all__ = ["HockeyParams"]


@dataclass(frozen=True)
class HockeyParams:
    """Every constant of the hockey task (SI units; sources in the env's spec sheet).

    Attributes:
        geometry: the stick, the control puck's spot and the demonstration swing.
        puck_radius, puck_height, puck_mass: an ice-hockey puck (76 mm x 25 mm, 170 g).
        floor_friction: puck-floor Coulomb friction (ice-like).
        puck_restitution: restitution coefficient of the pucks and the blade (per body; Bullet
            multiplies the coefficients of the two bodies in contact).
        target_mean: mean (x, y) of the target puck at an episode's start (m).
        target_std: std of the target puck's start in x and in y (m; 0: a fixed start, the
            real robot's setting of Fig 15b).
        flat_pucks: pucks that cannot tip: their inertia about the horizontal axes is 1e4
            times a solid cylinder's, so they slide and spin but stay flat (an idealised
            puck: with the real inertia hard hits tip pucks and fast ones roll on their edge;
            False gives the solid cylinder).
        zones: zone edges by distance from the robot base (m): zones 1 and 2 are
            [zones[k-1], zones[k]), zone 3 is [zones[2], zones[3]] (see ``zone_reward``).
        n_shots: shots per episode.
        sim_dt: pybullet time step (s).
        follow_through: time constant (s) of the exponential joint braking after the DMP ends.
        shot_time_cap: a shot ends at the latest this long (s) after it starts.
        rest_speed: pucks slower than this (m/s) count as stopped.
        motor_force: max joint torque of the position servos (N m, the URDF's effort).
        position_gain, velocity_gain: pybullet position-servo gains.
        joint_margin: goals are clipped this far (rad) inside the joint limits.
        max_goal_velocity: goal velocities are clipped to +- this (rad/s, URDF limit 10).
        min_blade_height: a shot whose DMP takes the blade centre below this height at any
            4th posture of the swing (m; the
            blade's lower edge is 4 cm below its centre) is rejected (not executed).
        dmp_basis: basis functions of the DMP.
    """

    geometry: ArmGeometry = field(default_factory=ArmGeometry)
    puck_radius: float = 0.038
    puck_height: float = 0.025
    puck_mass: float = 0.17
    floor_friction: float = 0.025
    puck_restitution: float = 0.3
    target_mean: tuple[float, float] = (1.1, 0.0)
    target_std: float = 0.1
    zones: tuple[float, float, float, float] = (1.4, 1.8, 2.2, 2.6)
    n_shots: int = 3
    sim_dt: float = 1.0 / 240.0
    follow_through: float = 0.08
    shot_time_cap: float = 6.0
    rest_speed: float = 1e-3
    motor_force: float = 300.0
    position_gain: float = 0.5
    velocity_gain: float = 1.0
    joint_margin: float = 0.05
    max_goal_velocity: float = 10.0
    min_blade_height: float = 0.0
    dmp_basis: int = 15
    flat_pucks: bool = True

    def __post_init__(self) -> None:
        finite = math.isfinite
        rules: list[tuple[tuple[str, ...], Callable[[float], bool], str]] = [
            (
                (
                    "puck_radius",
                    "puck_height",
                    "puck_mass",
                    "sim_dt",
                    "follow_through",
                    "shot_time_cap",
                    "rest_speed",
                    "motor_force",
                    "max_goal_velocity",
                ),
                lambda v: finite(v) and v > 0,
                "must be finite and > 0",
            ),
            (("floor_friction", "target_std"), lambda v: finite(v) and v >= 0, "must be >= 0"),
            (("puck_restitution",), lambda v: 0 <= v <= 1, "must be in [0, 1]"),
            (
                ("position_gain", "velocity_gain"),
                lambda v: finite(v) and 0 < v <= 1,
                "must be in (0, 1]",
            ),
            (("joint_margin",), lambda v: finite(v) and 0 <= v < 1.0, "must be in [0, 1) rad"),
            (("min_blade_height",), finite, "must be finite"),
        ]
        if not isinstance(self.flat_pucks, bool):
            raise TypeError(f"HockeyParams.flat_pucks must be a bool, got {self.flat_pucks!r}")
        if not isinstance(self.geometry, ArmGeometry):
            raise TypeError(
                f"HockeyParams.geometry must be an ArmGeometry, got {type(self.geometry).__name__}"
            )
        for names, ok, rule in rules:
            for name in names:
                if not ok(as_float(f"HockeyParams.{name}", getattr(self, name))):
                    raise ValueError(f"HockeyParams.{name} {rule}, got {getattr(self, name)}")
        mean = _numbers("HockeyParams.target_mean", self.target_mean)
        if not all(math.isfinite(v) for v in mean) or len(mean) != 2:
            raise ValueError(
                f"HockeyParams.target_mean must be 2 finite numbers, got {self.target_mean}"
            )
        check_count("HockeyParams.dmp_basis", self.dmp_basis, 2)
        check_count("HockeyParams.n_shots", self.n_shots, 1)
        zones = _numbers("HockeyParams.zones", self.zones)
        if len(zones) != 4 or not all(math.isfinite(z) for z in zones) or zones != sorted(zones):
            raise ValueError(
                f"HockeyParams.zones must be 4 finite increasing edges, got {self.zones}"
            )

    @property
    def control_start(self) -> tuple[float, float]:
        """(x, y) of the control puck's spot: where the demo's blade meets it."""
        return (self.geometry.puck_x, 0.0)


def _numbers(name: str, value: object) -> list[float]:
    """A sequence of numbers as floats; a ``TypeError`` naming ``name`` (and the entry)."""
    if isinstance(value, str | bytes):
        raise TypeError(f"{name} must be a sequence of numbers, got {value!r}")
    try:
        items = list(value)  # type: ignore[call-overload]
    except TypeError:
        raise TypeError(
            f"{name} must be a sequence of numbers, got {type(value).__name__}"
        ) from None
    return [as_float(f"{name}[{k}]", v) for k, v in enumerate(items)]
