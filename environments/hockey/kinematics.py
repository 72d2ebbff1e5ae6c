"""The hockey arm's kinematics with pytorch-kinematics: the model, the blade pose, the demo.

The arm is pybullet_data's KUKA LBR iiwa (``kuka_iiwa/model.urdf``, 7 revolute joints) with a
hockey stick added to its flange as two fixed links (``stick``, ``blade``); :func:`arm_urdf`
writes that URDF once, the same text feeds pybullet (the simulation) and pytorch-kinematics
(:class:`ArmKinematics`, forward kinematics, Jacobians and IK), so the two agree to float
precision (tested against pybullet's link poses).

The **demonstration** (:func:`demonstration`) stands in for kinesthetic teach-in: a Cartesian
blade path, a pendulum swing of the blade about a pivot above the control puck (backswing
``backswing`` rad, radius ``swing_radius``; the blade face stays square to the +x shot
direction and the stick along the pendulum's radius), timed ``phi(u) = backswing (1 - u^2)``
for ``u = t / swing_duration``, so it starts at rest and passes the puck at full speed; the
joint trajectory comes from pytorch-kinematics' batched ``PseudoInverseIK`` of the blade poses,
started from the planar posture that puts the blade at the puck. The DMP imitates it; its goal
(the joints when the blade is at the puck) and goal velocity are what the policy adapts.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import hashlib
import math
import os
import tempfile
from dataclasses import dataclass

import torch
from torch import Tensor

from hireps_torch.checks import as_finite_f64, as_float, check_count

__all__ = [
    "ArmGeometry",
    "ArmKinematics",
    "arm_kinematics",
    "arm_urdf",
    "demonstration",
    "require_robot_extra",
]

JOINT_NAMES = tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8))
# Planar posture (joints 2, 4, 6 only) with the blade at the control puck's start spot; found by
# least squares on the forward kinematics, used to start the IK of the demonstration path.
_IK_SEED = (0.0, 0.27, 0.0, -1.43, 0.0, 1.15, 0.0)


def require_robot_extra() -> None:
    """Raise an ImportError naming the ``robot`` extra when pybullet or pytorch-kinematics is
    missing."""
    missing = []
    for name in ("pybullet", "pybullet_data", "pytorch_kinematics"):
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise ImportError(
            f"the robot hockey task needs {', '.join(missing)}: install the robot extra, "
            "pip install 'hireps-torch[robot]' (or pip install -e '.[robot]' in a checkout)"
        )


@dataclass(frozen=True)
class ArmGeometry:
    """The stick on the iiwa flange and the demonstration swing (all SI units).

    Attributes:
        stick_length: shaft length (m); radius ``stick_radius``.
        stick_pitch: the shaft is mounted on the flange pitched by this angle (rad), like the
            bend of a hockey stick, so that the wrist (joint 6) keeps range for the backswing.
        blade_size: (thickness along the shot, width, height) of the box blade (m).
        blade_height: height of the blade centre above the floor at the puck (m).
        puck_x: x of the control puck's start spot (m, on the robot's x axis, y = 0).
        swing_radius: radius of the demo's pendulum swing (m).
        backswing: the demo's backswing angle (rad).
        swing_duration: time from the backswing to the blade at the puck (s).
        demo_points: IK samples along the demo path.
    """

    stick_length: float = 0.55
    stick_radius: float = 0.015
    stick_pitch: float = 0.6
    blade_size: tuple[float, float, float] = (0.02, 0.14, 0.08)
    blade_height: float = 0.04
    puck_x: float = 0.55
    swing_radius: float = 0.6
    backswing: float = math.radians(35.0)
    swing_duration: float = 0.5
    demo_points: int = 26

    def __post_init__(self) -> None:
        positive = (
            "stick_length",
            "stick_radius",
            "blade_height",
            "puck_x",
            "swing_radius",
            "swing_duration",
        )
        for name in positive:
            v = as_float(f"ArmGeometry.{name}", getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ArmGeometry.{name} must be finite and > 0, got {v}")
        for name in ("stick_pitch", "backswing"):
            if not math.isfinite(as_float(f"ArmGeometry.{name}", getattr(self, name))):
                raise ValueError(f"ArmGeometry.{name} must be finite, got {getattr(self, name)}")
        size = self.blade_size
        if not isinstance(size, tuple | list) or len(size) != 3:
            raise ValueError(f"ArmGeometry.blade_size must be 3 numbers, got {size!r}")
        for k, v in enumerate(size):
            if not (math.isfinite(as_float(f"ArmGeometry.blade_size[{k}]", v)) and v > 0):
                raise ValueError(f"ArmGeometry.blade_size must be finite and > 0, got {size}")
        check_count("ArmGeometry.demo_points", self.demo_points, 2)


def _kuka_urdf_path() -> str:
    import pybullet_data

    return os.path.join(pybullet_data.getDataPath(), "kuka_iiwa", "model.urdf")


@functools.lru_cache(maxsize=8)
def arm_urdf(geometry: ArmGeometry = ArmGeometry()) -> tuple[str, str]:
    """The iiwa URDF with the stick links: (urdf text, path of a file holding it).

    Mesh paths are made absolute so the file can live outside pybullet_data. The file is
    ``hireps_iiwa_stick_<hash of the text>.urdf`` in the temp directory, shared by every process
    and left there for the next.
    """
    require_robot_extra()
    src_path = _kuka_urdf_path()
    with open(src_path) as f:
        text = f.read()
    mesh_dir = os.path.join(os.path.dirname(src_path), "meshes")
    text = text.replace('filename="meshes/', f'filename="{mesh_dir}/')
    g = geometry
    L, r = g.stick_length, g.stick_radius
    bx, by, bz = g.blade_size
    stick = f"""
  <joint name="stick_mount" type="fixed">
    <parent link="lbr_iiwa_link_7"/><child link="stick"/>
    <origin rpy="0 {g.stick_pitch} 0" xyz="0 0 0.045"/>
  </joint>
  <link name="stick">
    <inertial><origin xyz="0 0 {L / 2}"/><mass value="0.4"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.0001"/></inertial>
    <visual><origin xyz="0 0 {L / 2}"/><geometry><cylinder radius="{r}" length="{L}"/></geometry>
      <material name="wood"><color rgba="0.6 0.4 0.2 1"/></material></visual>
    <collision><origin xyz="0 0 {L / 2}"/>
      <geometry><cylinder radius="{r}" length="{L}"/></geometry></collision>
  </link>
  <joint name="blade_mount" type="fixed">
    <parent link="stick"/><child link="blade"/>
    <origin rpy="0 0 0" xyz="0 0 {L + bz / 2}"/>
  </joint>
  <link name="blade">
    <inertial><origin xyz="0 0 0"/><mass value="0.1"/>
      <inertia ixx="0.0001" ixy="0" ixz="0" iyy="0.0001" iyz="0" izz="0.0001"/></inertial>
    <visual><geometry><box size="{bx} {by} {bz}"/></geometry>
      <material name="blade_black"><color rgba="0.1 0.1 0.1 1"/></material></visual>
    <collision><geometry><box size="{bx} {by} {bz}"/></geometry></collision>
  </link>
</robot>"""
    text = text.replace("</robot>", stick)
    # one file per text, replaced whole: processes that end without atexit (killed, Ray's
    # workers) leave no copies behind, and a reader never sees a half-written file
    name = f"hireps_iiwa_stick_{hashlib.sha256(text.encode()).hexdigest()[:16]}.urdf"
    path = os.path.join(tempfile.gettempdir(), name)
    fd, part = tempfile.mkstemp(prefix="hireps_iiwa_stick_", suffix=".urdf")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    try:
        os.replace(part, path)
    except OSError:  # another user's file of that name (a shared /tmp): keep ours apart
        path = part
        atexit.register(_remove, part)
    return text, path


def _remove(path: str) -> None:
    with contextlib.suppress(OSError):
        os.remove(path)


def _rot_y(angle: Tensor) -> Tensor:
    """(T,) -> (T, 3, 3) rotations about the world y axis."""
    c, s = torch.cos(angle), torch.sin(angle)
    z, o = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack(
        [torch.stack([c, z, s], -1), torch.stack([z, o, z], -1), torch.stack([-s, z, c], -1)], -2
    )


class ArmKinematics:
    """Forward kinematics of the blade and IK, batched, float64 (pytorch-kinematics).

    Args:
        geometry: the stick and demo geometry.
    """

    def __init__(self, geometry: ArmGeometry = ArmGeometry()) -> None:
        require_robot_extra()
        import pytorch_kinematics as pk

        self.geometry = geometry
        text, _ = arm_urdf(geometry)
        self.chain = pk.build_serial_chain_from_urdf(text.encode(), "blade").to(dtype=torch.float64)
        names = tuple(self.chain.get_joint_parameter_names())
        if names != JOINT_NAMES:  # pragma: no cover - guards a changed pybullet_data model
            raise RuntimeError(f"unexpected joint order in the iiwa model: {names}")
        low, high = self.chain.get_joint_limits()
        self.lower = torch.as_tensor(low, dtype=torch.float64)  # (7,)
        self.upper = torch.as_tensor(high, dtype=torch.float64)  # (7,)

    def blade_pose(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Blade centre position and orientation in the world (base) frame.

        Args:
            q: (..., 7) joint angles (rad).

        Returns:
            position (..., 3) m and rotation (..., 3, 3) (columns: blade x, y, z axes; x is the
            blade face normal, z runs along the shaft away from the flange).
        """
        q = as_finite_f64("joint angles", q)
        if q.shape[-1] != 7:
            raise ValueError(f"joint angles must have shape (..., 7), got {tuple(q.shape)}")
        lead = q.shape[:-1]
        m = self.chain.forward_kinematics(q.reshape(-1, 7)).get_matrix()
        return m[:, :3, 3].reshape(*lead, 3), m[:, :3, :3].reshape(*lead, 3, 3)

    def inverse(self, positions: Tensor, rotations: Tensor, seed: Tensor) -> Tensor:
        """Joint angles putting the blade at the given poses (PseudoInverseIK, batched).

        Args:
            positions: (T, 3) blade centres; rotations: (T, 3, 3).
            seed: (7,) initial configuration for every target.

        Returns:
            (T, 7) joint angles.

        Raises:
            RuntimeError: if a pose is not reached within 1e-5 m / 1e-4 rad.
        """
        import pytorch_kinematics as pk

        T = positions.shape[0]
        mat = torch.eye(4, dtype=torch.float64).repeat(T, 1, 1)
        mat[:, :3, :3] = rotations
        mat[:, :3, 3] = positions
        ik = pk.PseudoInverseIK(
            self.chain,
            retry_configs=seed.reshape(1, 7).to(torch.float64),
            joint_limits=torch.stack([self.lower, self.upper], -1),
            max_iterations=100,
            pos_tolerance=1e-6,
            rot_tolerance=1e-5,
        )
        sol = ik.solve(pk.Transform3d(matrix=mat, dtype=torch.float64))
        if not bool(sol.converged.all()):
            worst = float(sol.err_pos.max())
            raise RuntimeError(f"IK did not reach every blade pose (worst error {worst:.3g} m)")
        return sol.solutions[:, 0]


@functools.lru_cache(maxsize=8)
def arm_kinematics(geometry: ArmGeometry = ArmGeometry()) -> ArmKinematics:
    """One :class:`ArmKinematics` per geometry and process (parsing the chain is not free)."""
    return ArmKinematics(geometry)


@functools.lru_cache(maxsize=8)
def demonstration(geometry: ArmGeometry = ArmGeometry()) -> tuple[Tensor, float]:
    """The demonstrated swing as joint positions: ((T, 7) rad, sample interval dt in s).

    See the module docstring for the path. The result is cached per geometry.
    """
    g = geometry
    T = g.demo_points
    u = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    phi = g.backswing * (1.0 - u**2)  # stick angle from the vertical, blade behind the pivot
    pivot = torch.tensor([g.puck_x, 0.0, g.blade_height + g.swing_radius], dtype=torch.float64)
    offset = torch.stack([-torch.sin(phi), torch.zeros_like(phi), -torch.cos(phi)], -1)
    positions = pivot + g.swing_radius * offset
    # blade square to the shot: x axis -x_world (face normal, symmetric box), z down the shaft
    square = torch.tensor(
        [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64
    )
    rotations = _rot_y(phi) @ square
    kin = arm_kinematics(g)
    q = kin.inverse(positions, rotations, torch.tensor(_IK_SEED, dtype=torch.float64))
    return q, g.swing_duration / (T - 1)
