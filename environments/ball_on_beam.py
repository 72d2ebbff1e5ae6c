"""Ball on a beam held by a robot (HiREPS paper, Section 5.5, Fig 19), simulated.

Spec sheet
==========
Physics (pure, batched: :func:`beam_step`)
    A 1 m beam, pivoting about its centre, is the robot's end effector. A solid ball rolls on
    it without slipping; ``x`` is the ball's position along the beam (m, 0 = centre, +x to the
    right) and ``alpha`` the beam angle (rad, positive raises the right end, so the ball rolls
    toward -x). Rolling-ball dynamics (Lagrange, ball radius small against the beam, rolling
    resistance taken viscous):

        (1 + I / (m r^2)) x'' = x alpha'^2 - g sin(alpha) - c_roll x',   I / (m r^2) = 2/5,

    i.e. ``x'' = 5/7 (x alpha'^2 - g sin alpha - c x')``. The beam is positioned by the robot's
    joint servo, modelled as a first-order lag toward the commanded angle ``alpha_d``:

        alpha' = (alpha_d - alpha) / tau.

    The state ``(x, x', alpha)`` is integrated with one classical Runge-Kutta-4 step per
    control step of ``dt`` (``alpha_d`` held constant over the decision).

Constants and sources
    ==========================  ==========  ==========================================
    beam length                 1 m         paper ("a 1 m beam")
    goals                       +-0.1 m     paper (10 cm left and right of the centre)
    decision interval           0.5 s       paper (new desired beam angle every 0.5 s)
    episode length              20 s        paper (40 decisions)
    control step dt             0.02 s      our choice (50 Hz inside the decision)
    servo time constant tau     0.1 s       our choice
    beam angle limit            0.15 rad    our choice (~8.6 deg; commands are clipped)
    rolling resistance c        0.2 1/s     our choice
    gravity g                   9.81 m/s^2  standard
    start position              +-0.45 m    our choice ("the ball starts at the end"),
                                            at rest, beam level, position noise 0.01 m std
    fall penalty                100         our choice (~16 s at rest at the start, which
                                            costs 0.35^2 = 0.1225 per control step)
    ==========================  ==========  ==========================================

Action (one per decision)
    The desired beam angle ``alpha_d`` (rad). Commands beyond the beam's limit are clipped to
    ``+-max_angle`` (a robot's joint limit would do the same); non-finite commands raise.

Observation
    ``(x, x', alpha)`` (m, m/s, rad), float32 in the adapters; the exact float64 state is in
    ``state`` / ``info["state"]``.

Reward (per decision)
    The sum over the decision's control steps of ``-(d^2 + x'^2)``, evaluated after each
    control step, with ``d = min(|x - 0.1|, |x + 0.1|)`` the distance to the closer goal. If the
    ball leaves the beam (``|x| > 0.5``) the episode terminates: the steps after the fall earn
    nothing and the decision's reward gets ``-fall_penalty`` added.

Start state and episode end
    Episodes alternate between starting near the right end (``x = +0.45``) and near the left
    end (``x = -0.45``), plus N(0, 0.01^2) position noise, at rest with a level beam; a reset
    with a seed starts again on the right. An episode ends after 40 decisions (``truncated``)
    or when the ball falls (``terminated``).

For infinite-horizon HiREPS an episode end is a restart: the restart probability per decision
is ``1 / 40`` (``gamma = 0.975``).

Adapters: :class:`BallOnBeamEnv` (gymnasium, id ``hireps/BallOnBeam-v0``) and
:class:`BallOnBeamBatchEnv` (TorchRL ``EnvBase``, B beams). Both call :func:`beam_step` and
:func:`sample_start` and draw the start noise from one seeded ``torch.Generator`` in the same
order, so the same seed and actions give the same trajectory.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hireps_torch.checks import as_float, check_count, check_generator, check_seed
from hireps_torch.envs._common import (
    BatchedTask,
    ScalarActionBatchEnv,
    ScalarActionGymEnv,
    check_durations,
    check_fields,
    check_params,
    check_scalar_action,
    check_state,
)
from hireps_torch.registration import BALL_ON_BEAM_ID

__all__ = [
    "BallOnBeamBatchEnv",
    "BallOnBeamEnv",
    "BeamEvaluation",
    "BeamParams",
    "beam_step",
    "evaluate_beam",
    "goal_distance",
    "sample_start",
    "step_reward",
]

ENV_ID = BALL_ON_BEAM_ID  # registered by ``import hireps_torch``
MAX_STEPS = 10**7
"""The most control steps per decision and decisions per episode :class:`BeamParams` allows."""


@dataclass(frozen=True)
class BeamParams:
    """Constants of the ball-on-a-beam task (see the module docstring for their sources)."""

    half_length: float = 0.5
    goal: float = 0.1
    decision_seconds: float = 0.5
    episode_seconds: float = 20.0
    dt: float = 0.02
    servo_tau: float = 0.1
    max_angle: float = 0.15
    rolling_resistance: float = 0.2
    gravity: float = 9.81
    start_position: float = 0.45
    start_noise: float = 0.01
    fall_penalty: float = 100.0

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "half_length",
                "decision_seconds",
                "episode_seconds",
                "dt",
                "servo_tau",
                "max_angle",
                "gravity",
            ),
            nonnegative=("goal", "rolling_resistance", "start_noise", "fall_penalty"),
        )
        for name in ("start_position", "goal"):
            if not 0 <= as_float(name, getattr(self, name)) < self.half_length:
                raise ValueError(
                    f"{name} must be in [0, half_length = {self.half_length}), got "
                    f"{getattr(self, name)}"
                )
        if self.steps_per_decision < 1 or self.decisions_per_episode < 1:
            raise ValueError(
                f"need dt <= decision_seconds <= episode_seconds, got dt={self.dt}, "
                f"decision_seconds={self.decision_seconds}, episode_seconds={self.episode_seconds}"
            )
        for name, count, limit in (
            ("decision_seconds / dt", self.steps_per_decision, MAX_STEPS),
            ("episode_seconds / decision_seconds", self.decisions_per_episode, MAX_STEPS),
        ):
            if count > limit:
                raise ValueError(
                    f"{name} = {count:.3g} steps is more than {limit:.0e}: dt={self.dt}, "
                    f"decision_seconds={self.decision_seconds}, "
                    f"episode_seconds={self.episode_seconds}"
                )

    @property
    def steps_per_decision(self) -> int:
        """Control steps per decision (25 by default)."""
        return round(self.decision_seconds / self.dt)

    @property
    def decisions_per_episode(self) -> int:
        """Decisions per episode (40 by default)."""
        return round(self.episode_seconds / self.decision_seconds)

    @property
    def gamma(self) -> float:
        """Discount per decision of the infinite-horizon dual: 1 - 1 / decisions_per_episode."""
        return 1.0 - 1.0 / self.decisions_per_episode


def goal_distance(x: Tensor, params: BeamParams) -> Tensor:
    """Distance of the ball to the closer goal: (...,) -> (...,)."""
    distance: Tensor = _goal_distance(x, params.goal, torch)
    return distance


def _goal_distance(x: Any, goal: float, xp: Any) -> Any:
    """:func:`goal_distance` on torch tensors or numpy arrays (``xp``: the module)."""
    return xp.minimum(abs(x - goal), abs(x + goal))


def step_reward(state: Tensor, params: BeamParams) -> Tensor:
    """Per-control-step reward -(d^2 + x'^2): (..., 3) -> (...)."""
    return -(goal_distance(state[..., 0], params) ** 2 + state[..., 1] ** 2)


def _derivative(x: Any, v: Any, alpha: Any, target: Any, p: BeamParams, xp: Any) -> tuple[Any, ...]:
    """The time derivative (x', x'', alpha') of the state's components, each (B,), as torch
    tensors or numpy arrays (``xp``: the module)."""
    alpha_dot = (target - alpha) / p.servo_tau
    acc = (5.0 / 7.0) * (x * alpha_dot**2 - p.gravity * xp.sin(alpha) - p.rolling_resistance * v)
    return v, acc, alpha_dot


def _rk4(x: Any, v: Any, alpha: Any, target: Any, p: BeamParams, xp: Any) -> tuple[Any, ...]:
    """One RK4 step of ``p.dt`` on the components (x, x', alpha), each (B,), as torch tensors
    or numpy arrays (``xp``: the module): the arithmetic of :func:`control_step` without
    stacking the state (3x fewer operations)."""
    h, half = p.dt, 0.5 * p.dt
    k1 = _derivative(x, v, alpha, target, p, xp)
    k2 = _derivative(x + half * k1[0], v + half * k1[1], alpha + half * k1[2], target, p, xp)
    k3 = _derivative(x + half * k2[0], v + half * k2[1], alpha + half * k2[2], target, p, xp)
    k4 = _derivative(x + h * k3[0], v + h * k3[1], alpha + h * k3[2], target, p, xp)
    sixth = h / 6.0
    return tuple(
        y + sixth * (a + 2.0 * b + 2.0 * c + d)
        for y, a, b, c, d in zip((x, v, alpha), k1, k2, k3, k4, strict=True)
    )


def control_step(state: Tensor, target: Tensor, params: BeamParams) -> Tensor:
    """One RK4 control step of ``dt`` toward the commanded angle: (B, 3), (B,) -> (B, 3)."""
    return torch.stack(
        _rk4(state[..., 0], state[..., 1], state[..., 2], target, params, torch), dim=-1
    )


def beam_step(
    state: Tensor, action: Tensor, params: BeamParams
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One decision: the servo tracks the desired beam angle for the decision's control steps.

    Args:
        state: (B, 3) float64 ``(x, x', alpha)``; every ball must still be on the beam.
        action: (B,) or (B, 1) desired beam angles; clipped to ``+-params.max_angle``.
        params: the task constants.

    Returns:
        next_state (B, 3); reward (B,) summed over the control steps (with the fall penalty);
        fell (B,) bool, the ball left the beam during the decision (the state then stays where
        it left the beam); path (B, steps_per_decision, 3), the state after each control step
        (held after a fall).
    """
    state = check_state(state, 3)
    params = check_params(params, BeamParams, default=False)
    off = state[:, 0].abs() > params.half_length
    if bool(off.any()):
        i = int(off.nonzero()[0, 0])
        raise ValueError(f"ball {i} is already off the beam: x = {state[i, 0].item()}")
    target = check_scalar_action(action, state.shape[0], "beam angle").to(state.dtype)
    target = target.clamp(-params.max_angle, params.max_angle)
    if state.device.type == "cpu":  # numpy's calls on (B,) arrays cost a fraction of torch's
        path, reward, fell = (
            torch.from_numpy(a) for a in _control_steps(state.numpy(), target.numpy(), params, np)
        )
    else:  # no host sync: this may run on a GPU
        path, reward, fell = _control_steps(state, target, params, torch)
    reward = reward - params.fall_penalty * fell.to(state.dtype)
    return path[:, -1].clone(), reward, fell, path  # the state shares no memory with path


def _control_steps(state: Any, target: Any, p: BeamParams, xp: Any) -> tuple[Any, Any, Any]:
    """The control steps of one decision on torch tensors or numpy arrays (``xp``: the module):
    (path (B, steps, 3), reward (B,) without the fall penalty, fell (B,))."""
    x, v, alpha = state[:, 0], state[:, 1], state[:, 2]
    fell = x > math.inf  # all False, of the array kind's bool type
    reward = 0.0 * x
    xs, vs, alphas = [], [], []
    for _ in range(p.steps_per_decision):
        nx, nv, nalpha = _rk4(x, v, alpha, target, p, xp)
        # a fallen ball stays where it left the beam
        x, v, alpha = (xp.where(fell, old, new) for old, new in ((x, nx), (v, nv), (alpha, nalpha)))
        reward = reward + xp.where(fell, 0.0, -(_goal_distance(x, p.goal, xp) ** 2 + v**2))
        fell = fell | (abs(x) > p.half_length)
        xs.append(x)
        vs.append(v)
        alphas.append(alpha)
    path = xp.stack([xp.stack(xs, 1), xp.stack(vs, 1), xp.stack(alphas, 1)], -1)
    return path, reward, fell


def sample_start(sides: Tensor, params: BeamParams, generator: torch.Generator | None) -> Tensor:
    """Start states at the given ends (+1 right, -1 left): (n,) -> (n, 3) float64."""
    side = torch.as_tensor(sides, dtype=torch.float64)
    params = check_params(params, BeamParams, default=False)
    check_generator("generator", generator)
    noise = torch.randn(side.shape[0], generator=generator, dtype=torch.float64)
    x = (side * params.start_position + params.start_noise * noise).clamp(
        -params.start_position - 0.04, params.start_position + 0.04
    )
    zeros = torch.zeros_like(x)
    return torch.stack([x, zeros, zeros], dim=-1)


# --------------------------------------------------------------------------------------------
# adapters


class BeamTask(BatchedTask):
    """B beams for the adapters. Episodes are numbered in the order they start (beams in index
    order when several start together), and episode n starts on the right when n is even, so
    the starts alternate sides: with B = 3, R L R in one iteration, L R L in the next. A start
    drawn again before its beam took a decision (a reset right after a reset, as a collector
    that resets at every iteration does after the end-of-episode reset) keeps its number and
    side, with fresh noise. A seed restarts the numbering.

    ``episodes`` (B,) holds each beam's current episode number (-1 before its first); the next
    number is one past the largest.
    """

    state_dim = 3
    action_name = "beam angle"

    def __init__(
        self, batch: int, params: BeamParams, seed: int = 0, device: str | torch.device = "cpu"
    ) -> None:
        self.params = params
        self.action_limit = params.max_angle
        self.episodes = torch.full((check_count("batch_size", batch, 1),), -1, dtype=torch.long)
        super().__init__(batch, seed, device)

    def seed(self, seed: int | None) -> None:
        super().seed(seed)
        self.episodes.fill_(-1)

    def start_states(self, mask: Tensor) -> Tensor:
        m = mask.reshape(-1).cpu()
        played = self.t.cpu() > 0
        new = m & ((self.episodes < 0) | played)
        following = int(self.episodes.max()) + 1
        numbers = following + torch.cumsum(new.long(), 0) - 1
        self.episodes = torch.where(new, numbers, self.episodes)
        sides = torch.where(self.episodes % 2 == 0, 1.0, -1.0)
        return sample_start(sides, self.params, self.gen)

    def transition(self, state: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return beam_step(state, action, self.params)

    def truncated(self, terminated: Tensor) -> Tensor:
        return (self.t >= self.params.decisions_per_episode) & ~terminated


class BallOnBeamEnv(ScalarActionGymEnv):
    """Gymnasium adapter over :func:`beam_step` (one beam; see the module docstring).

    ``observation_space``: Box([-0.6, -inf, -max_angle], [0.6, inf, max_angle]) float32;
    ``action_space``: Box(-max_angle, max_angle, (1,)) float32. ``info`` holds the float64
    state and the per-control-step path. ``terminated``: the ball fell; ``truncated``: the
    20 s are over.
    """

    def __init__(self, params: BeamParams | None = None):
        self.params = check_params(params, BeamParams)
        p = self.params
        super().__init__(BeamTask(1, p), np.array([p.half_length + 0.1, np.inf, p.max_angle]))


class BallOnBeamBatchEnv(ScalarActionBatchEnv):
    """Batched TorchRL adapter over :func:`beam_step`: B beams stepped together.

    Keys: ``observation`` (B, 3) float32, ``action`` (B, 1) float32 in +-max_angle,
    ``reward`` (B, 1) float32, ``done``/``terminated`` (the ball fell) /``truncated`` (the 20 s
    are over) (B, 1) bool, and ``state`` (B, 3) float64. Episodes alternate sides as described
    in :class:`BeamTask`. Partial resets (``_reset`` mask) restart only the masked beams.

    Args:
        batch_size: B.
        params: task constants.
        seed: seed of the start-noise generator.
        device: torch device of the tensors.
    """

    def __init__(
        self,
        batch_size: int = 3,
        params: BeamParams | None = None,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.params = check_params(params, BeamParams)
        super().__init__(BeamTask(batch_size, self.params, seed, device))


# --------------------------------------------------------------------------------------------
# evaluation


@dataclass(frozen=True)
class BeamEvaluation:
    """Result of :func:`evaluate_beam` (over the evaluation episodes).

    Attributes:
        success_rate: share of episodes in which the ball stays within ``tolerance`` of a goal
            at every control step of the last ``hold_seconds``.
        fell_share: share of episodes in which the ball fell off.
        average_return: mean episode return (with fall penalties).
        positions: (E, T) ball position after each control step (held after a fall).
    """

    success_rate: float
    fell_share: float
    average_return: float
    positions: Tensor


def evaluate_beam(
    act: Any,
    params: BeamParams | None = None,
    *,
    n_episodes: int = 10,
    hold_seconds: float = 5.0,
    tolerance: float = 0.03,
    seed: int | Sequence[int] = 12345,
) -> Any:
    """Run ``n_episodes`` full episodes of a policy, alternating start sides (right first).

    Args:
        act: callable ``states (E, 3) float64 -> desired angles (E,) or (E, 1)``, e.g. the
            noise-free hierarchical policy; for S seeds ``(S, E, 3) -> (S, E[, 1])``.
        params: task constants.
        n_episodes: E, run together.
        hold_seconds: final window in which the ball must stay near a goal for a success.
        tolerance: distance to the closer goal (m) that counts as "at the goal".
        seed: seed of the start noise; a sequence of S seeds evaluates the S members of a
            population at once, member s from the start noise of ``seed[s]``.

    Returns:
        A :class:`BeamEvaluation`, or for S seeds a list of S.
    """
    p = check_params(params, BeamParams)
    n_episodes = check_count("n_episodes", n_episodes, 1)
    check_durations(hold_seconds=hold_seconds, tolerance=tolerance)
    if hold_seconds > p.episode_seconds:
        raise ValueError(
            f"hold_seconds must be <= episode_seconds = {p.episode_seconds}, got {hold_seconds}"
        )
    many = isinstance(seed, Sequence)
    seeds = list(seed) if isinstance(seed, Sequence) else [seed]
    if not seeds:
        raise ValueError("seed must name at least one member")
    sides = torch.where(torch.arange(n_episodes) % 2 == 0, 1.0, -1.0)
    starts = []
    for k, one in enumerate(seeds):
        gen = torch.Generator()
        gen.manual_seed(check_seed(f"seed[{k}]" if many else "seed", one))
        starts.append(sample_start(sides, p, gen))
    policy = act if many else lambda x: act(x[0])[None]
    results = _episodes_of_members(policy, p, torch.stack(starts), hold_seconds, tolerance)
    return results if many else results[0]


def _episodes_of_members(
    act: Any, p: BeamParams, start: Tensor, hold_seconds: float, tolerance: float
) -> list[BeamEvaluation]:
    """Full episodes from (S, E, 3) start states with ``act`` ((S, E, 3) -> (S, E[, 1])) in
    one batched simulation; one :class:`BeamEvaluation` per member."""
    S, E = start.shape[:2]
    state = start.reshape(S * E, 3)
    returns = torch.zeros(S * E, dtype=torch.float64)
    fell = torch.zeros(S * E, dtype=torch.bool)
    paths = []
    with torch.no_grad():
        for _ in range(p.decisions_per_episode):
            safe = torch.where(fell[:, None], torch.zeros_like(state), state)
            action = act(state.reshape(S, E, 3)).reshape(S * E, -1)
            nxt, r, f, path = beam_step(safe, action, p)
            returns += torch.where(fell, 0.0, r)
            path = torch.where(fell[:, None, None], state[:, None, :], path)
            state = torch.where(fell[:, None], state, nxt)
            fell = fell | f
            paths.append(path)
    traj = torch.cat(paths, dim=1)
    hold = max(1, round(hold_seconds / p.dt))
    near = goal_distance(traj[..., 0], p) < tolerance
    success = (near[:, -hold:].all(dim=1) & ~fell).view(S, E)
    fell_m, returns_m, positions = fell.view(S, E), returns.view(S, E), traj[..., 0].view(S, E, -1)
    return [
        BeamEvaluation(
            success_rate=float(success[m].to(torch.float64).mean()),
            fell_share=float(fell_m[m].to(torch.float64).mean()),
            average_return=float(returns_m[m].mean()),
            positions=positions[m],
        )
        for m in range(S)
    ]
