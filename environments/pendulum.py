"""Pendulum swing-up with a PD-tracked desired angle (HiREPS paper, Section 5.4, Figs 16-18).

Spec sheet
==========
Physics (pure, batched: :func:`pendulum_step`)
    A point mass ``m`` on a massless rod of length ``l`` with viscous joint friction ``b``:

        m l^2 theta'' = m g l sin(theta) - b theta' + u,     |u| <= u_max,

    ``theta = 0`` is upright, ``theta = +-pi`` hanging down; theta is wrapped to [-pi, pi)
    after every control step. One control step lasts ``dt`` and holds the torque constant;
    it is integrated with one classical Runge-Kutta-4 step (energy drift without friction and
    torque: < 1e-6 relative over 10 s, see the tests).

Constants and sources
    ======================  =========  =============================================
    mass m                  10 kg      paper
    length l                0.5 m      paper
    friction b              0.2 N m s  paper ("friction coefficient 0.2", taken viscous)
    torque limit u_max      30 N m     paper (m g l = 49 N m > 30: a pre-swing is needed)
    control rate            100 Hz     paper (dt = 0.01 s)
    gravity g               9.81 m/s^2 standard
    PD gains kp, kd         60, 10     our choice: kp > m g l so a target of 0 holds the
                                       pendulum up; with b, zeta ~ 0.97 about upright
                                       (0.31 hanging)
    steps per decision d    5          paper's standard setting (a parameter)
    restart prob. 1 - gamma 0.02 / d   paper, per decision
    ======================  =========  =============================================

Action (one per decision)
    A desired joint angle ``theta_d`` (rad), clipped to [-2 pi, 2 pi] (a larger target only
    saturates the torque earlier). For d control steps the PD controller applies
    ``u = clip(kp (theta_d - theta) - kd theta', -u_max, u_max)``. Non-finite actions raise.

Observation
    ``(theta, theta')``: angle in [-pi, pi), angular velocity in rad/s (float32 in the adapters).

Reward (per decision)
    The sum over the decision's d control steps of the per-step reward, evaluated at the state
    after each control step:

        r = 500 - 500 |sin(theta / 2)| - 10 |theta'|

    (the paper's shape: a base value of 500, minus 500 x the deviation from upright, minus
    10 x the speed). The deviation is the distance of the pendulum's tip from its upright
    position, divided by its largest value 2 l: |sin(theta / 2)|, in [0, 1]. 500 is upright at
    rest, 0 hanging at rest. Near upright it falls linearly (250 per rad), so a balance 0.1 rad
    off costs 25 per step; the squared angle (theta / pi)^2 we used first costs 0.5 there and
    made the tilted equilibrium (|theta| ~ 2.48 rad, the saturated torque against gravity)
    worth 188 per step against 27 here, a local optimum that held most runs (benchmarks/README.md
    compares the two).
    "Average return" in the plots is the mean per-control-step reward.

Start state
    Hanging down with a perturbation: ``theta = wrap(pi + 0.1 n1)``, ``theta' = 0.1 n2``,
    n1, n2 ~ N(0, 1) (the perturbation's size is our choice).

Episode end
    The task never terminates. With probability ``1 - gamma`` per decision (the paper's
    ``0.02 / d`` unless ``restart_probability`` is given) the
    system restarts from the start distribution (the infinite-horizon setting of the paper);
    the adapters report that as ``truncated``. ``max_decisions`` (default: none) adds a time
    cap, also reported as ``truncated``.

Adapters: :class:`PendulumSwingUpEnv` (gymnasium, id ``hireps/PendulumSwingUp-v0``) and
:class:`PendulumSwingUpBatchEnv` (TorchRL ``EnvBase`` with batch size B). Both call the same
functions below and draw their randomness from one ``torch.Generator`` seeded by the caller, in
the same order, so the same seed and actions give the same trajectory.
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
from hireps_torch.registration import PENDULUM_ID

__all__ = [
    "PendulumParams",
    "PendulumSwingUpBatchEnv",
    "PendulumSwingUpEnv",
    "SwingUpEvaluation",
    "energy",
    "evaluate_swing_up",
    "mirror_decisions",
    "mirror_states",
    "pd_torque",
    "pendulum_step",
    "sample_start",
    "step_reward",
    "wrap_angle",
]

ENV_ID = PENDULUM_ID  # registered by ``import hireps_torch``


@dataclass(frozen=True)
class PendulumParams:
    """Constants of the swing-up task (see the module docstring for their sources)."""

    mass: float = 10.0
    length: float = 0.5
    friction: float = 0.2
    max_torque: float = 30.0
    dt: float = 0.01
    gravity: float = 9.81
    kp: float = 60.0
    kd: float = 10.0
    steps_per_decision: int = 5
    action_limit: float = 2.0 * math.pi
    start_noise: float = 0.1
    restart_probability: float | None = None  # None: 0.02 / steps_per_decision

    def __post_init__(self) -> None:
        check_count("steps_per_decision", self.steps_per_decision, 1)
        check_fields(
            self,
            positive=("mass", "length", "dt", "action_limit"),
            nonnegative=("friction", "max_torque", "kp", "kd", "start_noise", "gravity"),
        )
        p = self.restart_probability
        if p is not None and not 0.0 <= as_float("restart_probability", p) < 1.0:
            raise ValueError(f"restart_probability must be in [0, 1), got {p}")

    @property
    def restart(self) -> float:
        """Restart probability per decision, 1 - gamma."""
        if self.restart_probability is None:
            return 0.02 / self.steps_per_decision
        return self.restart_probability

    @property
    def gamma(self) -> float:
        """Discount per decision of the infinite-horizon dual."""
        return 1.0 - self.restart

    @property
    def decision_seconds(self) -> float:
        return self.steps_per_decision * self.dt


def wrap_angle(theta: Tensor) -> Tensor:
    """Wrap angles to [-pi, pi)."""
    return torch.remainder(theta + math.pi, 2.0 * math.pi) - math.pi


def energy(state: Tensor, params: PendulumParams) -> Tensor:
    """Mechanical energy (J), zero at the bottom at rest: (B, 2) -> (B,)."""
    m, l, g = params.mass, params.length, params.gravity
    return 0.5 * m * l**2 * state[..., 1] ** 2 + m * g * l * (1.0 + torch.cos(state[..., 0]))


def step_reward(state: Tensor) -> Tensor:
    """Per-control-step reward 500 - 500 |sin(theta/2)| - 10 |theta'|: (..., 2) -> (...).

    |sin(theta/2)| is the tip's distance from upright over 2 l (see the module docstring).
    """
    return 500.0 - 500.0 * torch.sin(0.5 * state[..., 0]).abs() - 10.0 * state[..., 1].abs()


def pd_torque(state: Tensor, target: Tensor, params: PendulumParams) -> Tensor:
    """PD torque toward ``target`` (B,), clipped to the torque limit: (B,)."""
    u = params.kp * (target - state[..., 0]) - params.kd * state[..., 1]
    return u.clamp(-params.max_torque, params.max_torque)


def _accel(theta: Tensor, omega: Tensor, u: Tensor, p: PendulumParams) -> Tensor:
    inertia = p.mass * p.length**2
    return (p.mass * p.gravity * p.length * torch.sin(theta) - p.friction * omega + u) / inertia


def control_step(state: Tensor, torque: Tensor, params: PendulumParams) -> Tensor:
    """One control step (dt, torque held) with RK4: state (B, 2), torque (B,) -> (B, 2)."""
    h = params.dt
    th, om = state[..., 0], state[..., 1]
    # the stages' angle slopes k_i are the stages' velocities, each computed once
    k1t, k1o = om, _accel(th, om, torque, params)
    k2t = om + 0.5 * h * k1o
    k2o = _accel(th + 0.5 * h * k1t, k2t, torque, params)
    k3t = om + 0.5 * h * k2o
    k3o = _accel(th + 0.5 * h * k2t, k3t, torque, params)
    k4t = om + h * k3o
    k4o = _accel(th + h * k3t, k4t, torque, params)
    th = th + h / 6.0 * (k1t + 2.0 * k2t + 2.0 * k3t + k4t)
    om = om + h / 6.0 * (k1o + 2.0 * k2o + 2.0 * k3o + k4o)
    return torch.stack([wrap_angle(th), om], dim=-1)


def pendulum_step(
    state: Tensor, action: Tensor, params: PendulumParams
) -> tuple[Tensor, Tensor, Tensor]:
    """One decision: track the desired angle with the PD controller for d control steps.

    Args:
        state: (B, 2) float64 ``(theta, theta')``.
        action: (B,) or (B, 1) desired angles; clipped to +-``params.action_limit``.
        params: the task constants.

    Returns:
        next_state (B, 2), reward (B,) summed over the d control steps, and the path
        (B, d, 2) of states after each control step.
    """
    state = check_state(state, 2)
    params = check_params(params, PendulumParams, default=False)
    target = check_scalar_action(action, state.shape[0], "desired angle").to(state.dtype)
    target = target.clamp(-params.action_limit, params.action_limit)
    path = []
    s = state
    for _ in range(params.steps_per_decision):
        s = control_step(s, pd_torque(s, target, params), params)
        path.append(s)
    p = torch.stack(path, dim=1)
    return s, step_reward(p).sum(dim=1), p


def mirror_states(state: Tensor) -> Tensor:
    """The mirror image (wrap(-theta), -theta') of states: (..., 2) -> (..., 2).

    The task is symmetric under it: the physics, the PD controller and the reward are unchanged
    when the state and the desired angle change sign (tested), and so is the start distribution.
    """
    return torch.stack([wrap_angle(-state[..., 0]), -state[..., 1]], dim=-1)


def mirror_decisions(
    states: Tensor, actions: Tensor, rewards: Tensor, next_states: Tensor, terminated: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The decisions followed by their mirror images (twice as many, same rewards).

    By the symmetry of :func:`mirror_states`, ``(mirror(s), -a, r, mirror(s'))`` is a decision
    the task could have produced as well; ``train.py pendulum`` adds them to each update
    (``mirror_samples``) so that the policy learns both swing directions.

    Args:
        states: ([S,] N, 2); actions: ([S,] N, 1) desired angles; rewards: ([S,] N);
            next_states: ([S,] N, 2); terminated: ([S,] N) bool (a population's members
            along a leading S).

    Returns:
        The same five arrays with 2N decisions: the originals, then the mirrored ones.
    """
    return (
        torch.cat([states, mirror_states(states)], -2),
        torch.cat([actions, -actions], -2),
        torch.cat([rewards, rewards], -1),
        torch.cat([next_states, mirror_states(next_states)], -2),
        torch.cat([terminated, terminated], -1),
    )


def sample_start(n: int, params: PendulumParams, generator: torch.Generator | None) -> Tensor:
    """n start states hanging down with a perturbation: (n, 2) float64."""
    n = check_count("n", n, 0)
    params = check_params(params, PendulumParams, default=False)
    check_generator("generator", generator)
    noise = torch.randn(n, 2, generator=generator, dtype=torch.float64) * params.start_noise
    return torch.stack([wrap_angle(math.pi + noise[:, 0]), noise[:, 1]], dim=-1)


# --------------------------------------------------------------------------------------------
# adapters


class PendulumTask(BatchedTask):
    """B pendulums for the adapters: restarts at the restart probability, optional time cap."""

    state_dim = 2
    action_name = "desired angle"

    def __init__(
        self,
        batch: int,
        params: PendulumParams,
        max_decisions: int | None = None,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.params = params
        self.action_limit = params.action_limit
        self.max_decisions = (
            None if max_decisions is None else check_count("max_decisions", max_decisions, 1)
        )
        super().__init__(batch, seed, device)

    def start_states(self, mask: Tensor) -> Tensor:
        return sample_start(self.batch, self.params, self.gen)

    def transition(self, state: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        nxt, reward, path = pendulum_step(state, action, self.params)
        return nxt, reward, torch.zeros_like(reward, dtype=torch.bool), path

    def truncated(self, terminated: Tensor) -> Tensor:
        u = torch.rand(self.batch, generator=self.gen, dtype=torch.float64)  # one draw each
        trunc = (u < self.params.restart).to(self.device)  # restarts with probability 1 - gamma
        if self.max_decisions is not None:
            trunc = trunc | (self.t >= self.max_decisions)
        return trunc


class PendulumSwingUpEnv(ScalarActionGymEnv):
    """Gymnasium adapter over :func:`pendulum_step` (one pendulum; see the module docstring).

    ``observation_space``: Box([-pi, -inf], [pi, inf]) float32; ``action_space``:
    Box(-2 pi, 2 pi, (1,)) float32 (the desired angle). ``info`` holds the float64 state and the
    per-control-step path. ``terminated`` is always False; ``truncated`` marks a restart or
    the time cap.
    """

    def __init__(self, params: PendulumParams | None = None, max_decisions: int | None = None):
        self.params = check_params(params, PendulumParams)
        super().__init__(PendulumTask(1, self.params, max_decisions), np.array([math.pi, np.inf]))


class PendulumSwingUpBatchEnv(ScalarActionBatchEnv):
    """Batched TorchRL adapter over :func:`pendulum_step`: B pendulums stepped together.

    Keys: ``observation`` (B, 2) float32, ``action`` (B, 1) float32 in [-2 pi, 2 pi],
    ``reward`` (B, 1) float32, ``done``/``terminated``/``truncated`` (B, 1) bool
    (``terminated`` is always False; ``truncated`` marks a restart or the time cap), and
    ``state`` (B, 2) float64, the exact state. Partial resets (``_reset`` mask) restart only the
    masked pendulums.

    Args:
        batch_size: B.
        params: task constants.
        max_decisions: optional time cap in decisions.
        seed: seed of the environment's generator.
        device: torch device of the tensors.
    """

    def __init__(
        self,
        batch_size: int = 20,
        params: PendulumParams | None = None,
        max_decisions: int | None = None,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.params = check_params(params, PendulumParams)
        super().__init__(PendulumTask(batch_size, self.params, max_decisions, seed, device))


# --------------------------------------------------------------------------------------------
# evaluation


@dataclass(frozen=True)
class SwingUpEvaluation:
    """Result of :func:`evaluate_swing_up` (means over the rollouts).

    Attributes:
        success_rate: share of rollouts within ``angle_tol`` of upright with
            |theta'| < ``velocity_tol`` at every control step of the last ``hold_seconds``.
        time_to_upright: mean time (s) to first reach that region, over the rollouts that
            reach it (nan if none does).
        reached_share: share of rollouts that reach it at all.
        average_return: mean per-control-step reward.
    """

    success_rate: float
    time_to_upright: float
    reached_share: float
    average_return: float


def evaluate_swing_up(
    act: Any,
    params: PendulumParams | None = None,
    *,
    n_rollouts: int = 50,
    seconds: float = 5.0,
    hold_seconds: float = 1.0,
    angle_tol: float = 0.1,
    velocity_tol: float = 1.0,
    seed: int | Sequence[int] = 12345,
) -> Any:
    """Roll a policy out from the standard start distribution, without restarts.

    Args:
        act: callable ``states (B, 2) float64 -> desired angles (B,) or (B, 1)``, e.g. the
            noise-free hierarchical policy; for S seeds ``(S, B, 2) -> (S, B[, 1])``.
        params: task constants (their ``steps_per_decision`` sets how long a decision holds).
        n_rollouts: B, rolled out together.
        seconds: rollout length.
        hold_seconds: the final window that must stay upright for a success.
        angle_tol: |theta| bound for "upright" (rad).
        velocity_tol: |theta'| bound for "upright" (rad/s).
        seed: seed of the start states; a sequence of S seeds evaluates the S members of a
            population at once, member s from the start states of ``seed[s]``.

    Returns:
        A :class:`SwingUpEvaluation`, or for S seeds a list of S.
    """
    p = check_params(params, PendulumParams)
    n_rollouts = check_count("n_rollouts", n_rollouts, 1)
    check_durations(seconds=seconds, hold_seconds=hold_seconds)
    if hold_seconds > seconds:
        raise ValueError(f"hold_seconds must be <= seconds = {seconds}, got {hold_seconds}")
    check_durations(angle_tol=angle_tol, velocity_tol=velocity_tol)
    many = isinstance(seed, Sequence)
    seeds = list(seed) if isinstance(seed, Sequence) else [seed]
    if not seeds:
        raise ValueError("seed must name at least one member")
    starts = []
    for k, one in enumerate(seeds):
        gen = torch.Generator()
        gen.manual_seed(check_seed(f"seed[{k}]" if many else "seed", one))
        starts.append(sample_start(n_rollouts, p, gen))
    policy = act if many else lambda x: act(x[0])[None]
    results = _rollout_members(
        policy, p, torch.stack(starts), seconds, hold_seconds, angle_tol, velocity_tol
    )
    return results if many else results[0]


def _rollout_members(
    act: Any,
    p: PendulumParams,
    state: Tensor,
    seconds: float,
    hold_seconds: float,
    angle_tol: float,
    velocity_tol: float,
) -> list[SwingUpEvaluation]:
    """Roll out (S, B, 2) start states with ``act`` ((S, B, 2) -> (S, B[, 1])) in one
    batched simulation; one :class:`SwingUpEvaluation` per member."""
    S, B = state.shape[:2]
    n_decisions = max(1, round(seconds / p.decision_seconds))
    paths = []
    flat = state.reshape(S * B, 2)
    with torch.no_grad():
        for _ in range(n_decisions):
            action = act(flat.reshape(S, B, 2)).reshape(S * B, -1)
            flat, _, path = pendulum_step(flat, action, p)
            paths.append(path)
    traj = torch.cat(paths, dim=1).reshape(S, B, -1, 2)  # (S, B, T, 2)
    up = (traj[..., 0].abs() < angle_tol) & (traj[..., 1].abs() < velocity_tol)
    hold = max(1, round(hold_seconds / p.dt))
    success = up[..., -hold:].all(dim=-1)
    reached = up.any(dim=-1)
    first = up.to(torch.int64).argmax(dim=-1).to(torch.float64) * p.dt + p.dt
    reward = step_reward(traj.reshape(S * B, -1, 2)).reshape(S, B, -1)
    out = []
    for s in range(S):
        t_up = float(first[s][reached[s]].mean()) if bool(reached[s].any()) else math.nan
        out.append(
            SwingUpEvaluation(
                success_rate=float(success[s].to(torch.float64).mean()),
                time_to_upright=t_up,
                reached_share=float(reached[s].to(torch.float64).mean()),
                average_return=float(reward[s].mean()),
            )
        )
    return out
