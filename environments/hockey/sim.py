"""The pybullet world of the hockey task: the iiwa with its stick, two pucks, one shot at a time.

:class:`HockeySim` owns one pybullet client (DIRECT by default, GUI optional). A shot
(:meth:`HockeySim.shot`) integrates the batched DMP (:mod:`hireps_torch.dmp`) for the given
joint goals and goal velocities on the simulation grid, lets the arm's position servos track it
(then a follow-through that brakes the joints exponentially from the goal velocity), steps until
both pucks rest, and reports the minimum gap between the pucks. Every physical constant is in
:class:`~hireps_torch.envs.hockey.params.HockeyParams`; the rules (rewards, zones, episode) are in
:mod:`hireps_torch.envs.hockey.env`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from torch import Tensor

from hireps_torch.dmp import DMP
from hireps_torch.envs.hockey.kinematics import (
    arm_kinematics,
    arm_urdf,
    demonstration,
    require_robot_extra,
)
from hireps_torch.envs.hockey.params import HockeyParams

__all__ = ["HockeyParams", "HockeySim", "ShotResult", "demo_action", "shot_dmp"]


def shot_dmp(params: HockeyParams) -> DMP:
    """A DMP imitating the demonstrated swing (a fresh instance; the IK behind it is cached)."""
    demo, dt = demonstration(params.geometry)
    return DMP.from_demonstration(demo, dt, n_basis=params.dmp_basis)


def demo_action(dmp: DMP | HockeyParams | None = None) -> np.ndarray:
    """The demonstration's shot as an action, (14,) [goal, goal velocity], of a shot DMP (or of
    the one :func:`shot_dmp` builds for these params; default params when None)."""
    if not isinstance(dmp, DMP):
        dmp = shot_dmp(dmp or HockeyParams())
    return np.concatenate([dmp.goal.numpy(), dmp.goal_velocity.numpy()])


@dataclass
class ShotResult:
    """What one shot did.

    Attributes:
        min_gap: minimum distance between the pucks' rims during the shot (m, 0 on contact).
        target: (2,) target-puck position after the shot (m).
        control: (2,) control-puck position at the end of the shot (it may still be sliding
            away from the target puck; it is then returned to its spot).
        sim_steps: pybullet steps taken.
        rejected: the DMP would take the blade under the floor, so the arm did not move.
        frames: RGB frames (H, W, 3) uint8 taken during the shot, when requested.
    """

    min_gap: float
    target: np.ndarray
    control: np.ndarray
    sim_steps: int
    rejected: bool
    frames: list[np.ndarray] = field(default_factory=list)


class HockeySim:
    """One pybullet world: the iiwa with its stick, the control puck and the target puck.

    Args:
        params: the task constants.
        gui: open pybullet's GUI instead of the headless DIRECT mode.
        marks: draw the zone edges (visual only, no physics; for pictures).
    """

    def __init__(
        self, params: HockeyParams | None = None, gui: bool = False, marks: bool = True
    ) -> None:
        require_robot_extra()
        import pybullet as pb
        import pybullet_data

        self.pb = pb
        self.params = p = params or HockeyParams()
        n = round(p.geometry.swing_duration / p.sim_dt)
        if abs(n * p.sim_dt - p.geometry.swing_duration) > 1e-9:
            raise ValueError(
                f"sim_dt = {p.sim_dt} must divide the swing duration "
                f"{p.geometry.swing_duration} into whole steps"
            )
        self.client = pb.connect(pb.GUI if gui else pb.DIRECT)
        self._closed = False
        cid = self.client
        pb.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
        self.plane = self.arm = self.control = self.target = -1  # built by new_world()
        self.joints = list(range(7))
        self.kinematics = arm_kinematics(p.geometry)
        self.dmp = shot_dmp(p)
        self.home = self.dmp.start.clone()  # the arm's pose at the start of every shot
        self._swing_steps = n
        lo, hi = self.kinematics.lower + p.joint_margin, self.kinematics.upper - p.joint_margin
        self.goal_low, self.goal_high = lo, hi
        self.marks = marks
        self.fresh = False  # True while the world holds nothing but a new_world() and resets
        self.new_world()

    def new_world(self) -> None:
        """Build the world from nothing (``resetSimulation``): plane, arm, pucks and, with
        ``marks``, the zone marks; the pucks rest at their start spots.

        Called at every episode start (:class:`~hireps_torch.envs.hockey.env.RobotHockeyEnv`
        ``reset``): pybullet keeps state that ``restoreState`` does not restore (contact
        caches of other pairs, deactivation timers, the broadphase's pair cache), so in a
        reused world an episode's outcome depended on the episodes played before it
        (measured: 13 of 450 episodes of a learning run changed when played in another
        order; a fresh world per episode gave none). ~20 ms, against ~90 ms of simulation
        per episode."""
        pb, p, cid = self.pb, self.params, self.client
        pb.resetSimulation(physicsClientId=cid)
        pb.setGravity(0, 0, -9.81, physicsClientId=cid)
        pb.setTimeStep(p.sim_dt, physicsClientId=cid)
        # contact pairs in a fixed order (the results depend on it)
        pb.setPhysicsEngineParameter(deterministicOverlappingPairs=1, physicsClientId=cid)
        self.plane = pb.loadURDF("plane.urdf", physicsClientId=cid)
        pb.changeDynamics(self.plane, -1, lateralFriction=1.0, restitution=0.0, physicsClientId=cid)
        _, path = arm_urdf(p.geometry)
        self.arm = pb.loadURDF(path, useFixedBase=True, physicsClientId=cid)
        self.joints = list(range(7))
        stick, blade = 7, 8
        for link in (stick, blade):  # the blade may skim the floor; the floor does not stop it
            pb.setCollisionFilterPair(self.arm, self.plane, link, -1, 0, physicsClientId=cid)
        pb.changeDynamics(
            self.arm,
            blade,
            restitution=p.puck_restitution,
            lateralFriction=0.3,
            physicsClientId=cid,
        )
        self.control = self._puck([0.1, 0.3, 0.9, 1.0])
        self.target = self._puck([0.9, 0.2, 0.1, 1.0])
        if self.marks:
            self._zone_marks()
        self.reset(np.array(p.target_mean))
        # pybullet keeps contact caches between steps, so the same shot from a teleported start
        # could depend on what came before; every shot starts from this saved state instead
        # (saved after the pucks settled: a state saved without contacts does not clear them).
        for _ in range(24):
            pb.stepSimulation(physicsClientId=cid)
        self._clean_state = pb.saveState(physicsClientId=cid)
        self.fresh = True

    def _puck(self, rgba: list[float]) -> int:
        pb, p, cid = self.pb, self.params, self.client
        col = pb.createCollisionShape(
            pb.GEOM_CYLINDER, radius=p.puck_radius, height=p.puck_height, physicsClientId=cid
        )
        vis = pb.createVisualShape(
            pb.GEOM_CYLINDER,
            radius=p.puck_radius,
            length=p.puck_height,
            rgbaColor=rgba,
            physicsClientId=cid,
        )
        body = pb.createMultiBody(
            p.puck_mass, col, vis, [0, 0, p.puck_height / 2], physicsClientId=cid
        )
        pb.changeDynamics(
            body,
            -1,
            lateralFriction=p.floor_friction,
            restitution=p.puck_restitution,
            rollingFriction=0.0,
            spinningFriction=0.001,
            linearDamping=0.0,
            angularDamping=0.0,
            physicsClientId=cid,
        )
        if p.flat_pucks:  # see HockeyParams.flat_pucks
            r, h, m = p.puck_radius, p.puck_height, p.puck_mass
            tilt = 1e4 * m * (3 * r * r + h * h) / 12
            pb.changeDynamics(
                body, -1, localInertiaDiagonal=[tilt, tilt, m * r * r / 2], physicsClientId=cid
            )
        return body

    def _zone_marks(self) -> None:
        """Visual-only marks (no collision shape, no physics) on the zone edges, for pictures."""
        pb, cid = self.pb, self.client
        colours = ([0.2, 0.7, 0.2, 1], [0.9, 0.8, 0.1, 1], [0.9, 0.5, 0.1, 1], [0.8, 0.1, 0.1, 1])
        for radius, rgba in zip(self.params.zones, colours, strict=True):
            for a in np.linspace(-0.45, 0.45, 24):
                vis = pb.createVisualShape(
                    pb.GEOM_BOX,
                    halfExtents=[0.006, 0.02, 0.001],
                    rgbaColor=rgba,
                    physicsClientId=cid,
                )
                pb.createMultiBody(
                    0,
                    -1,
                    vis,
                    [radius * math.cos(a), radius * math.sin(a), 0.001],
                    pb.getQuaternionFromEuler([0, 0, a]),
                    physicsClientId=cid,
                )

    # ---- state ---------------------------------------------------------------------------------
    def _place(self, body: int, xy: np.ndarray | tuple[float, float]) -> None:
        z = self.params.puck_height / 2
        self.pb.resetBasePositionAndOrientation(
            body, [float(xy[0]), float(xy[1]), z], [0, 0, 0, 1], physicsClientId=self.client
        )
        self.pb.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)

    def reset_arm(self) -> None:
        """Put the arm at the demo's start pose, at rest."""
        for j in self.joints:
            self.pb.resetJointState(
                self.arm, j, float(self.home[j]), 0.0, physicsClientId=self.client
            )

    def reset(self, target_xy: np.ndarray) -> None:
        """Start an episode: target puck at ``target_xy`` (2,), control puck at its spot."""
        self._place(self.target, target_xy)
        self._place(self.control, self.params.control_start)
        self.reset_arm()

    def puck_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """((2,) control, (2,) target) positions in m."""
        gp = self.pb.getBasePositionAndOrientation
        c = gp(self.control, physicsClientId=self.client)[0]
        t = gp(self.target, physicsClientId=self.client)[0]
        return np.array(c[:2]), np.array(t[:2])

    def _gap(self) -> float:
        c, t = self.puck_positions()
        return max(0.0, float(np.linalg.norm(c - t)) - 2 * self.params.puck_radius)

    def _settled(self) -> bool:
        """Nothing more can happen: the target puck rests and the control puck rests or slides
        away from it (on the open floor it cannot turn back)."""
        gv = self.pb.getBaseVelocity
        vc = np.array(gv(self.control, physicsClientId=self.client)[0][:2])
        vt = gv(self.target, physicsClientId=self.client)[0]
        if math.hypot(vt[0], vt[1]) >= self.params.rest_speed:
            return False
        c, t = self.puck_positions()
        return bool(np.linalg.norm(vc) < self.params.rest_speed or vc @ (c - t) > 0)

    # ---- a shot --------------------------------------------------------------------------------
    def plan(self, goal: Tensor, goal_velocity: Tensor) -> tuple[Tensor, Tensor, bool]:
        """The DMP on the simulation grid and whether it keeps the blade above the floor limit.

        Args:
            goal, goal_velocity: (7,) already inside the limits.

        Returns:
            positions (T + 1, 7), velocities (T + 1, 7) for T = swing steps, and ``ok``.
        """
        traj = self.dmp.rollout(goal[None], goal_velocity[None], n_steps=self._swing_steps)
        q, qd = traj.positions[0], traj.velocities[0]
        blade, _ = self.kinematics.blade_pose(q[::4])
        ok = bool(blade[:, 2].min() >= self.params.min_blade_height)
        return q, qd, ok

    def shot(
        self,
        goal: Tensor,
        goal_velocity: Tensor,
        frame_every: int = 0,
        frame_size: tuple[int, int] = (320, 240),
    ) -> ShotResult:
        """Play one shot from the home pose and wait until the pucks rest.

        Args:
            goal: (7,) DMP goal positions (rad), inside ``goal_low``/``goal_high``.
            goal_velocity: (7,) DMP goal velocities (rad/s).
            frame_every: grab an RGB frame every this many steps (0: none).
            frame_size: (width, height) of the frames.

        Returns:
            A :class:`ShotResult`; the control puck is then returned to its spot and the arm
            to its home pose.
        """
        pb, p, cid = self.pb, self.params, self.client
        self.fresh = False
        q, qd, ok = self.plan(goal, goal_velocity)
        frames: list[np.ndarray] = []
        _, target_xy = self.puck_positions()
        pb.restoreState(self._clean_state, physicsClientId=cid)
        self.reset(target_xy)  # same start, same shot: the outcome depends on nothing else
        gap = self._gap()
        steps = 0
        if ok:
            q_np, qd_np = q.numpy(), qd.numpy()
            g, gd = q_np[-1], qd_np[-1]
            lo, hi = self.kinematics.lower.numpy(), self.kinematics.upper.numpy()
            forces = [p.motor_force] * 7
            kp, kd = [p.position_gain] * 7, [p.velocity_gain] * 7
            arm_settled = self._swing_steps + math.ceil(5 * p.follow_through / p.sim_dt)
            cap = math.ceil(p.shot_time_cap / p.sim_dt)
            for k in range(1, cap + 1):
                if k <= arm_settled:
                    if k <= self._swing_steps:
                        qc, vc = q_np[k], qd_np[k]
                    else:
                        e = math.exp(-(k - self._swing_steps) * p.sim_dt / p.follow_through)
                        qc = np.clip(g + gd * p.follow_through * (1 - e), lo, hi)
                        vc = gd * e
                    pb.setJointMotorControlArray(
                        self.arm,
                        self.joints,
                        pb.POSITION_CONTROL,
                        targetPositions=qc,
                        targetVelocities=vc,
                        forces=forces,
                        positionGains=kp,
                        velocityGains=kd,
                        physicsClientId=cid,
                    )
                pb.stepSimulation(physicsClientId=cid)
                steps = k
                gap = min(gap, self._gap())
                if frame_every and k % frame_every == 0:
                    frames.append(self.render(*frame_size))
                if k > arm_settled and k % 8 == 0 and self._settled():
                    break
        control, target = self.puck_positions()
        self._place(self.control, p.control_start)
        self.reset_arm()
        return ShotResult(gap, target, control, steps, not ok, frames)

    # ---- pictures and teardown -------------------------------------------------------------
    def render(self, width: int = 320, height: int = 240) -> np.ndarray:
        """An RGB picture (height, width, 3) uint8 from behind the robot, looking down the rink."""
        pb, cid = self.pb, self.client
        view = pb.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=[1.3, 0.0, 0.0],
            distance=2.0,
            yaw=0.0,
            pitch=-62.0,
            roll=0.0,
            upAxisIndex=2,
            physicsClientId=cid,
        )
        proj = pb.computeProjectionMatrixFOV(
            fov=60.0, aspect=width / height, nearVal=0.05, farVal=10.0, physicsClientId=cid
        )
        img: Any = pb.getCameraImage(
            width, height, view, proj, renderer=pb.ER_TINY_RENDERER, physicsClientId=cid
        )[2]
        return np.asarray(img, dtype=np.uint8).reshape(height, width, 4)[:, :, :3].copy()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` disconnected the pybullet client."""
        return self._closed

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self.pb.disconnect(physicsClientId=self.client)
            except Exception:  # pragma: no cover - already gone at interpreter exit
                pass

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass
