"""Robot hockey (HiREPS paper, Section 5.3, Fig 14), simulated in pybullet.

Spec sheet
==========
Scene (:class:`~hireps_torch.envs.hockey.sim.HockeySim`)
    A KUKA LBR iiwa (7 DoF, pybullet_data's ``kuka_iiwa/model.urdf``, base at the origin) holds
    a hockey stick (0.55 m shaft mounted on the flange at 0.6 rad, a 2 x 14 x 8 cm box blade, as
    tall as an ice-hockey blade, centred 4 cm above the floor at the puck).
    On a flat floor lie a blue control puck at (0.55, 0) m, where the demonstrated swing meets
    it, and a red target puck further out along +x. Ice-hockey pucks (radius 38 mm, height
    25 mm, 170 g) that cannot tip (``HockeyParams.flat_pucks``: 1e4 times the horizontal
    inertia, so they slide and spin but stay flat), floor friction 0.025 (ice), restitution
    coefficient 0.3 on the pucks and the blade (per body: Bullet multiplies the two bodies'
    coefficients of a contact, 0.09 for two pucks: a cold rubber puck hardly bounces). The
    stick's links do not collide with the floor (a blade that skims the ice is not stopped by
    it).

    Why these contact constants (they were 0.05, 0.7 and solid cylinders; measured in
    ``benchmarks/README.md``): with restitution 0.7 the final distance jumped along smooth
    changes of the shot (a scan of neighbouring shots: 8-15 of 24 scan points by more
    than 0.2 m; pucks at ~5.4 m/s rolled on their edge for 14 m, an exploit rather than a
    shot), and hard hits tipped pucks (here: 2 of 30 swings up to 2.5x the demo's speed, one
    onto its edge). A fixed-start run (300 episodes,
    10 per update, seeds 0-2) ended at -0.97 +- 1.4 with the old contact and 1.06 +- 0.36 with
    this one (restitution 0.3 alone: 0.78 +- 0.11, flat pucks alone: 0.49 +- 1.4); the 10
    cm-start sequential run (1500 episodes) at -0.25 +- 0.46 and 0.35 +- 0.16.

Action (one per shot): 14 numbers, float64
    ``[g_1..g_7, gdot_1..gdot_7]``: the goal positions (rad) and goal velocities (rad/s) of the
    7 joint DMPs (:class:`hireps_torch.dmp.DMP`, shape learned by imitation of the demo swing,
    0.5 s long); the goal is the posture at which the blade reaches the puck's spot and gdot the
    joint velocity there. Goals are clipped to 0.05 rad inside the joint limits and goal
    velocities to +-10 rad/s (``info["clipped"]`` says when); an action of another shape or
    with a non-finite entry raises a ValueError naming it. The arm starts every shot from the
    demo's start posture at rest; its position servos (300 N m) track the DMP at 240 Hz, then
    brake exponentially (time constant 0.08 s) from the goal velocity (the follow-through).
    pytorch-kinematics maps the DMP's postures to blade poses: a shot that would take the blade
    centre below the floor (height < 0 m, checked at every 4th posture of the swing, i.e. every
    1/60 s) is rejected, not played (``info["rejected"]``); the
    pucks then stay where they are.

Shot
    One environment step is one shot: it ends after the follow-through once the target puck is
    slower than 1 mm/s and the control puck rests or slides away from it (it cannot come back
    on the open floor), or after 6 s. The control puck is then returned to its spot; the target
    puck stays where it stopped.

Observation
    The target puck's (x, y) in m (float64, unbounded), observed after each shot.

Reward
    After every shot ``-(minimum gap between the pucks' rims during the shot)`` in m (0 when the
    control puck touched the target puck). After the last shot, in addition, the zone reward by
    the target puck's distance ``d`` from the robot base (:func:`zone_reward`):
    1 for 1.4 <= d < 1.8, 2 for 1.8 <= d < 2.2, 3 for 2.2 <= d <= 2.6, 0 otherwise. The best
    episode return is 3.

Start state and episode end
    The target puck starts at N((1.1, 0), 0.1^2 I) m (std from the paper, mean our choice: the
    first shot has 0.47 m to cover to reach it, zone 3 is 1.1-1.5 m further). An episode is 3
    shots (``terminated`` after the third); the target puck is reset only between episodes.

Constants and sources
    ================================  ==============  ==================================
    zones 1.4-1.8 / 1.8-2.2 / 2.2-2.6  1 / 2 / 3      paper
    shots per episode                 3               paper
    shot reward -min distance         m               paper (rim gap: our reading)
    action: goal pos + goal vel, 7 J  14              paper
    target start std                  0.1 m           paper
    target start mean                 (1.1, 0) m      our choice
    puck size, mass                   38 x 25 mm, 170 g  our choice (ice-hockey puck)
    floor friction, restitution       0.025, 0.3      our choice (ice; a cold puck)
    pucks cannot tip                  flat_pucks      our choice (see Scene)
    stick, blade, demo swing          see ArmGeometry our choice
    DMP basis functions               15              our choice
    sim step, servo gains, torque     1/240 s, 0.5/1, 300 N m  our choice / URDF effort
    ================================  ==============  ==================================

``RobotHockeyEnv`` (id ``hireps/RobotHockey-v0``) plays one shot per step (the sequential,
time-indexed view); ``RobotHockeyEpisodicEnv`` (id ``hireps/RobotHockeyEpisodic-v0``) takes the
42 numbers of all three shots at once, observes only the start position and returns the episode
return in one step (the episodic view).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import Tensor

from hireps_torch.checks import as_finite_f64, as_float_tensor, check_count
from hireps_torch.envs._common import ResetNeeded, check_params, one_thread
from hireps_torch.envs.hockey.params import HockeyParams
from hireps_torch.envs.hockey.sim import HockeySim, demo_action
from hireps_torch.registration import HOCKEY_EPISODIC_ID, HOCKEY_ID

__all__ = [
    "ENV_ID",
    "EPISODIC_ENV_ID",
    "RobotHockeyEnv",
    "RobotHockeyEpisodicEnv",
    "clip_action",
    "zone_reward",
]

# gymnasium ids, registered by ``import hireps_torch``
ENV_ID = HOCKEY_ID
EPISODIC_ENV_ID = HOCKEY_EPISODIC_ID


def zone_reward(distance: Tensor, zones: tuple[float, float, float, float]) -> Tensor:
    """Zone reward of the target puck's distance from the robot base.

    Args:
        distance: (...) distances in m.
        zones: edges (z0, z1, z2, z3): reward 1 on [z0, z1), 2 on [z1, z2), 3 on [z2, z3],
            0 elsewhere.

    Returns:
        (...) float64 rewards.
    """
    d = torch.as_tensor(distance, dtype=torch.float64)
    z0, z1, z2, z3 = zones
    r = torch.zeros_like(d)
    r = torch.where((d >= z0) & (d < z1), 1.0, r)
    r = torch.where((d >= z1) & (d < z2), 2.0, r)
    return torch.where((d >= z2) & (d <= z3), 3.0, r)


def clip_action(action: Any, low: Tensor, high: Tensor) -> tuple[Tensor, Tensor]:
    """Check a shot action (or all of an episode's shots) and clip it into the arm's range.

    Args:
        action: n numbers, n = 14 per shot: 7 goal positions, then 7 goal velocities.
        low, high: (n,) bounds (the action space's).

    Returns:
        the clipped (n,) float64 action and an (n,) bool mask of the entries that were clipped.

    Raises:
        ValueError: wrong shape or a non-finite entry (named by index and value).
    """
    n = low.shape[0]
    a = as_float_tensor("action", action)
    if a.shape != (n,):
        raise ValueError(
            f"action must have shape ({n},): 7 joint goal positions then 7 goal velocities"
            f"{' per shot' if n != 14 else ''}, got {tuple(a.shape)}"
        )
    a = as_finite_f64("action", a)
    clipped = torch.minimum(torch.maximum(a, low), high)
    return clipped, clipped != a


def _bounds(sim: HockeySim, params: HockeyParams, repeat: int = 1) -> tuple[Tensor, Tensor]:
    """(14 repeat,) lower and upper action bounds: goal positions, then goal velocities."""
    v = torch.full((7,), params.max_goal_velocity, dtype=torch.float64)
    low = torch.cat([sim.goal_low, -v]).repeat(repeat)
    high = torch.cat([sim.goal_high, v]).repeat(repeat)
    return low, high


class RobotHockeyEnv(gym.Env):
    """One shot per step (see the module spec sheet).

    Args:
        params: task constants (:class:`HockeyParams`).
        render_mode: None or ``"rgb_array"`` (``render()`` returns (240, 320, 3) uint8).
        gui: show pybullet's GUI (needs a display).
        frame_every: with ``render_mode="rgb_array"``, put an RGB frame of every this many
            simulation steps of a shot into ``info["frames"]`` (0: none).

    ``info`` after a step: ``shot`` (1..3), ``min_gap`` (m), ``target_distance`` (m from the
    base), ``zone`` (0-3, of the current target position), ``zone_reward`` (only after the last
    shot, else 0), ``clipped``, ``rejected``, ``sim_steps``, ``control_end`` (the control puck's
    position when the shot ended, (2,)).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    @one_thread()  # its episodes the same whatever the process's threads (also reset, play)
    def __init__(
        self,
        params: HockeyParams | None = None,
        render_mode: str | None = None,
        gui: bool = False,
        frame_every: int = 0,
    ) -> None:
        frame_every = check_count("frame_every", frame_every, 0)
        self.frame_every = frame_every if render_mode == "rgb_array" else 0
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.params = check_params(params, HockeyParams)
        self.render_mode = render_mode
        self.sim = HockeySim(self.params, gui=gui, marks=gui or render_mode is not None)
        self._low, self._high = _bounds(self.sim, self.params)
        self.action_space = gym.spaces.Box(self._low.numpy(), self._high.numpy(), dtype=np.float64)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float64)
        self.shot_index = 0
        self._target = np.array(self.params.target_mean, dtype=np.float64)
        self.sim.reset(self._target)
        self.needs_reset = True  # a provisional state until the first reset()

    def demo_action(self) -> np.ndarray:
        """The demonstration's shot as an action: (14,) [goal, goal velocity]."""
        return demo_action(self.sim.dmp)

    @one_thread()
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is not None:
            seed = check_count("seed", seed, 0)  # gymnasium's np_random takes seeds >= 0
        self._check_open()
        super().reset(seed=seed)
        p = self.params
        self._target = np.asarray(p.target_mean) + p.target_std * self.np_random.standard_normal(2)
        if not self.sim.fresh:  # an episode's outcome depends on nothing played before it
            self.sim.new_world()
        self.sim.reset(self._target)
        self.shot_index = 0
        self.needs_reset = False
        return self._target.copy(), {"target_distance": float(np.linalg.norm(self._target))}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self._check_open()
        if self.needs_reset:
            raise ResetNeeded("call reset() before the first step()")
        a, clipped = clip_action(action, self._low, self._high)
        return self.play(a, bool(clipped.any()))

    @one_thread()
    def play(self, action: Tensor, clipped: bool) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One shot of an already checked and clipped (14,) action (what :meth:`step` does
        after :func:`clip_action`); ``clipped`` is reported in ``info``."""
        self._check_open()
        if self.shot_index >= self.params.n_shots:
            raise RuntimeError(f"the episode ended after {self.params.n_shots} shots: call reset()")
        result = self.sim.shot(action[:7], action[7:], frame_every=self.frame_every)
        self.shot_index += 1
        self._target = result.target
        distance = float(np.linalg.norm(result.target))
        zone = float(zone_reward(torch.tensor(distance, dtype=torch.float64), self.params.zones))
        terminated = self.shot_index == self.params.n_shots
        zone_r = zone if terminated else 0.0
        info = {
            "shot": self.shot_index,
            "min_gap": result.min_gap,
            "target_distance": distance,
            "zone": int(zone),
            "zone_reward": zone_r,
            "clipped": clipped,
            "rejected": result.rejected,
            "sim_steps": result.sim_steps,
            "control_end": result.control,
        }
        if self.frame_every:
            info["frames"] = result.frames
        return result.target.copy(), -result.min_gap + zone_r, terminated, False, info

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        self._check_open()
        return self.sim.render()

    def close(self) -> None:
        self.sim.close()

    def _check_open(self) -> None:
        if self.sim.closed:
            raise RuntimeError("the environment was closed: make a new one")


class RobotHockeyEpisodicEnv(gym.Env):
    """All three shots from one 42-number action (the episodic view, one step per episode).

    The observation is the target puck's start position (after the step: where it ended); the
    reward the episode return (sum
    of the shot rewards and the zone reward); every step terminates. ``info`` holds the
    per-shot infos of :class:`RobotHockeyEnv` under ``shots`` and the final ``zone``.
    """

    metadata = RobotHockeyEnv.metadata

    def __init__(
        self, params: HockeyParams | None = None, render_mode: str | None = None, gui: bool = False
    ) -> None:
        self.inner = RobotHockeyEnv(params, render_mode, gui)
        self.params = self.inner.params
        self.render_mode = render_mode
        n = self.params.n_shots
        self._low, self._high = _bounds(self.inner.sim, self.params, repeat=n)
        self.action_space = gym.spaces.Box(self._low.numpy(), self._high.numpy(), dtype=np.float64)
        self.observation_space = self.inner.observation_space

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is not None:
            seed = check_count("seed", seed, 0)
        super().reset(seed=seed)
        return self.inner.reset(seed=seed, options=options)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        n = self.params.n_shots
        self.inner._check_open()
        if self.inner.needs_reset:
            raise ResetNeeded("call reset() before the first step()")
        if self.inner.shot_index != 0:
            raise RuntimeError("the episode already ended: call reset()")
        # the whole action is checked before the first shot is played
        a, clipped = clip_action(action, self._low, self._high)
        total, shots = 0.0, []
        for k in range(n):
            shot = slice(14 * k, 14 * (k + 1))
            _, r, _, _, info = self.inner.play(a[shot], bool(clipped[shot].any()))
            total += r
            shots.append(info)
        info = {
            "shots": shots,
            "zone": shots[-1]["zone"],
            "target_distance": shots[-1]["target_distance"],
        }
        return self.inner._target.copy(), total, True, False, info

    def render(self) -> np.ndarray | None:
        return self.inner.render()

    def close(self) -> None:
        self.inner.close()
