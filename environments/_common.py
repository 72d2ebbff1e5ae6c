"""Adapters shared by the tasks with a float64 state and one scalar action per decision.

A task subclasses :class:`BatchedTask` with three hooks (start states, one decision of its pure
physics, truncation); :class:`ScalarActionGymEnv` (one system) and
:class:`ScalarActionBatchEnv` (B systems, TorchRL) are the two thin adapters over it. Both
step the same task code and draw from its one seeded generator in the same order (start states
at a reset; after each decision whatever :meth:`BatchedTask.truncated` draws), so the same seed
and actions give the same trajectory in both.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from typing import Any, TypeVar

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from hireps_torch.checks import (
    as_finite_f64,
    as_float,
    as_float_tensor,
    check_count,
    check_present_device,
    check_seed,
)


def check_fields(obj: object, positive: tuple[str, ...], nonnegative: tuple[str, ...]) -> None:
    """Raise naming the first field of ``obj`` (e.g. a params dataclass) in ``positive`` that
    is not a finite number > 0, then in ``nonnegative`` that is not a finite number >= 0 (NaN
    and inf fail both: an infinite time step or gain gives NaN physics)."""
    for names, ok, rule in ((positive, float.__gt__, "> 0"), (nonnegative, float.__ge__, ">= 0")):
        for name in names:
            value = as_float(name, getattr(obj, name))
            if not (math.isfinite(value) and ok(value, 0.0)):
                raise ValueError(f"{name} must be finite and {rule}, got {getattr(obj, name)}")


def check_durations(**values: float) -> None:
    """Every keyword value a finite number > 0 (seconds, tolerances); the error names it."""
    for name, value in values.items():
        v = as_float(name, value)
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0, got {value}")


P = TypeVar("P")


def check_params(params: object, cls: type[P], default: bool = True) -> P:
    """``params`` if it is a ``cls`` (a task's constants), ``cls()`` for None when
    ``default``; a ``TypeError`` naming the expected class otherwise."""
    if params is None and default:
        return cls()
    if not isinstance(params, cls):
        raise TypeError(
            f"params must be a {cls.__name__}{' (or None: the defaults)' if default else ''}, "
            f"got {type(params).__name__} {params!r:.60}"
        )
    return params


class ResetNeeded(gym.error.ResetNeeded, RuntimeError):
    """``step`` before the first ``reset`` (gymnasium's error, also a ``RuntimeError``)."""


def check_state(state: object, width: int) -> Tensor:
    """A (B, width) state with finite entries (NaN states would give silent NaN physics), as
    a floating tensor (its dtype kept; bool, integer and array states as float64)."""
    s = (
        state
        if isinstance(state, Tensor) and state.is_floating_point()
        else as_float_tensor("state", state)
    )
    if s.dim() != 2 or s.shape[1] != width:
        raise ValueError(f"state must have shape (B, {width}), got {tuple(s.shape)}")
    as_finite_f64("state", s)
    return s


def check_scalar_action(action: object, batch: int, what: str) -> Tensor:
    """Validate a (B,) or (B, 1) action holding one number per system; returns (B,).

    Args:
        action: the action batch (real numbers: a string, None or a complex value raises a
            ``TypeError``).
        batch: B.
        what: what one number is, for the error messages (e.g. "desired angle").
    """
    a = as_float_tensor("action", action)
    if a.dim() == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.shape != (batch,):
        raise ValueError(
            f"action must have shape ({batch},) or ({batch}, 1) (one {what} per system), "
            f"got {tuple(a.shape)}"
        )
    bad = ~torch.isfinite(a)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"action contains a non-finite {what} at index {i}: {a[i].item()}")
    return a


class BatchedTask:
    """B systems of one task: float64 states (B, C), decision counters, one seeded generator.

    Subclasses set ``state_dim``, ``action_limit`` and ``action_name`` and implement
    :meth:`start_states`, :meth:`transition` and :meth:`truncated`.
    """

    state_dim: int
    action_limit: float
    action_name: str
    hold: bool = False
    """Set: the next :meth:`reset` keeps every system as it is and draws nothing (a run
    restored from a checkpoint goes on with its systems where they were)."""

    def __init__(self, batch: int, seed: int = 0, device: str | torch.device = "cpu") -> None:
        self.batch = check_count("batch_size", batch, 1)
        self.device = check_present_device(device)
        self.gen = torch.Generator()
        self.gen.manual_seed(check_seed("seed", seed))
        self.t = torch.zeros(batch, dtype=torch.long, device=self.device)
        self.state = torch.zeros(batch, self.state_dim, dtype=torch.float64, device=self.device)

    # ---- hooks ------------------------------------------------------------------------------
    def start_states(self, mask: Tensor) -> Tensor:
        """(B, C) start states for all systems; only the masked (B,) ones will be used."""
        raise NotImplementedError

    def transition(self, state: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """One decision: (next_state (B, C), reward (B,), terminated (B,), path (B, T, C))."""
        raise NotImplementedError

    def truncated(self, terminated: Tensor) -> Tensor:
        """(B,) bool: which systems' episodes end without a terminal state (after ``t += 1``)."""
        raise NotImplementedError

    # ---- shared -----------------------------------------------------------------------------
    def seed(self, seed: int | None) -> None:
        self.gen.manual_seed(0 if seed is None else check_seed("seed", seed))

    def reset(self, mask: Tensor | None = None) -> None:
        """Restart the masked systems (all when ``mask`` is None; else a bool tensor of B
        entries, (B,) or (B, 1)); a mask of another kind is a ``ValueError`` before anything
        is drawn."""
        if mask is not None and (
            not isinstance(mask, Tensor)
            or mask.dtype != torch.bool
            or mask.is_meta
            or tuple(mask.shape) not in ((self.batch,), (self.batch, 1))
        ):
            what = (
                f"a {mask.dtype} tensor of shape {tuple(mask.shape)} on {mask.device}"
                if isinstance(mask, Tensor)
                else type(mask).__name__
            )
            raise ValueError(
                f"the reset mask must be a bool tensor of {self.batch} entries ((B,) or (B, 1)), "
                f"got {what}; nothing was reset"
            )
        if self.hold:
            self.hold = False
            return
        m = torch.ones(self.batch, dtype=torch.bool) if mask is None else mask.reshape(-1).cpu()
        if not bool(m.any()):  # draws nothing: a seed then starts the same episodes
            return
        fresh = self.start_states(m).to(self.device)
        md = m.to(self.device)
        self.state = torch.where(md[:, None], fresh, self.state)
        self.t = torch.where(md, torch.zeros_like(self.t), self.t)

    def step(self, action: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Advance every system by one decision: (reward, terminated, truncated, path)."""
        self.state, reward, terminated, path = self.transition(self.state, action)
        self.t += 1
        return reward, terminated, self.truncated(terminated), path


class MemberTasks(BatchedTask):
    """The tasks of S members (each of B systems with its own generator, as one seed's run
    holds it) as one task of S B systems, member after member. Starts, restarts and
    truncation of member s's systems draw from its own task (a member whose systems are not
    restarted draws nothing), so its systems do not depend on its companions; one physics
    call steps all of them.

    Args:
        tasks: one task per member, of one kind, batch size, constants and device.
    """

    def __init__(self, tasks: Sequence[BatchedTask]) -> None:
        self.tasks = list(tasks)
        if not self.tasks:
            raise ValueError("MemberTasks needs at least one task")
        first = self.tasks[0]
        for s, task in enumerate(self.tasks[1:], 1):
            if type(task) is not type(first) or (task.batch, task.device) != (
                first.batch,
                first.device,
            ):
                raise ValueError(
                    f"tasks[{s}] is a {type(task).__name__} of {task.batch} systems on "
                    f"{task.device}, tasks[0] a {type(first).__name__} of {first.batch} on "
                    f"{first.device}: members share one kind, size and device"
                )
        self.state_dim, self.action_name = first.state_dim, first.action_name
        self.action_limit = first.action_limit
        self.members, self.per_member = len(self.tasks), first.batch
        self.batch, self.device = self.members * self.per_member, first.device
        self.t = torch.zeros(self.batch, dtype=torch.long, device=self.device)
        self.state = torch.zeros(
            self.batch, self.state_dim, dtype=torch.float64, device=self.device
        )

    def seed(self, seed: int | None) -> None:
        if self.members > 1:
            raise ValueError("the members' tasks are seeded one by one (each its own seed)")
        self.tasks[0].seed(seed)

    def start_states(self, mask: Tensor) -> Tensor:
        hit = mask.view(self.members, -1).any(1).tolist()
        B, parts = self.per_member, []
        for task, m, t, state, h in zip(
            self.tasks,
            torch.split(mask, B),
            torch.split(self.t, B),
            torch.split(self.state, B),
            hit,
            strict=True,
        ):
            if h:
                task.t = t  # the systems that took a decision
                parts.append(task.start_states(m).to(self.device, torch.float64))
            else:
                parts.append(state)
        return torch.cat(parts)

    def transition(self, state: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self.tasks[0].transition(state, action)

    def truncated(self, terminated: Tensor) -> Tensor:
        parts = []
        B = self.per_member
        for task, t, ended in zip(
            self.tasks, torch.split(self.t, B), torch.split(terminated, B), strict=True
        ):
            task.t = t
            parts.append(task.truncated(ended))
        return torch.cat(parts)


class ScalarActionGymEnv(gym.Env):
    """Gymnasium adapter over one system of a :class:`BatchedTask` (built with batch 1).

    ``observation_space``: Box(-obs_high, obs_high) float32; ``action_space``:
    Box(-limit, limit, (1,)) float32. ``info`` holds the float64 state and, after a step, the
    per-control-step path. ``step`` before the first ``reset`` raises :class:`ResetNeeded`;
    ``reset(seed=...)`` takes integers >= 0.
    """

    metadata = {"render_modes": []}

    def __init__(self, task: BatchedTask, obs_high: np.ndarray) -> None:
        self.task = task
        lim = np.float32(task.action_limit)
        self.action_space = gym.spaces.Box(-lim, lim, shape=(1,), dtype=np.float32)
        hi = np.asarray(obs_high, dtype=np.float32)
        self.observation_space = gym.spaces.Box(-hi, hi, dtype=np.float32)
        task.reset(torch.zeros(1, dtype=torch.bool))  # a provisional state, no episode yet
        self._needs_reset = True
        self._ended = False

    def _obs(self) -> np.ndarray:
        return self.task.state[0].numpy().astype(np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is not None:
            seed = check_count("seed", seed, 0)  # gymnasium's np_random takes seeds >= 0
        super().reset(seed=seed)
        if seed is not None:
            self.task.seed(seed)
        self.task.reset()
        self._needs_reset = self._ended = False
        return self._obs(), {"state": self.task.state[0].numpy().copy()}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._needs_reset:
            raise ResetNeeded("call reset() before the first step()")
        a = as_float_tensor("action", action).reshape(-1)
        if a.shape != (1,):
            raise ValueError(
                f"action must hold one {self.task.action_name}, got shape {tuple(a.shape)}"
            )
        if self._ended:  # as gymnasium's own environments say it
            gym.logger.warn(
                "You are calling 'step()' even though this environment has already returned "
                "terminated = True or truncated = True. You should always call 'reset()' once "
                "you receive either; any further steps are undefined behavior."
            )
        reward, term, trunc, path = self.task.step(a)
        self._ended = bool(term[0]) or bool(trunc[0])
        info = {"state": self.task.state[0].numpy().copy(), "path": path[0].numpy()}
        return self._obs(), float(reward[0]), bool(term[0]), bool(trunc[0]), info


class ScalarActionBatchEnv(EnvBase):
    """Batched TorchRL adapter over a :class:`BatchedTask`: its B systems stepped together.

    Keys: ``observation`` (B, C) float32, ``state`` (B, C) float64 (exact), ``action`` (B, 1)
    float32 in ±``action_limit``, ``reward`` (B, 1) float32, ``done`` / ``terminated`` /
    ``truncated`` (B, 1) bool. Partial resets (``_reset`` mask) restart only the masked systems;
    as TorchRL does, ``reset(td)`` returns ``td``'s entries for the other rows (zeros for keys
    ``td`` lacks: pass the whole tensordict, e.g. ``step_mdp``'s). ``step`` before the first
    ``reset`` raises :class:`ResetNeeded`.
    """

    def __init__(self, task: BatchedTask) -> None:
        super().__init__(batch_size=torch.Size([task.batch]), device=task.device)
        self.task = task
        B, C, lim = task.batch, task.state_dim, task.action_limit
        self.observation_spec = Composite(
            observation=Unbounded(shape=(B, C), dtype=torch.float32, device=self.device),
            state=Unbounded(shape=(B, C), dtype=torch.float64, device=self.device),
            shape=(B,),
            device=self.device,
        )
        self.action_spec = Bounded(
            low=-lim, high=lim, shape=(B, 1), dtype=torch.float32, device=self.device
        )
        self.reward_spec = Unbounded(shape=(B, 1), dtype=torch.float32, device=self.device)
        flag = Categorical(2, shape=(B, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=flag.clone(),
            terminated=flag.clone(),
            truncated=flag.clone(),
            shape=(B,),
            device=self.device,
        )
        task.reset(torch.zeros(B, dtype=torch.bool))  # a provisional state, no episode yet
        self._needs_reset = True

    def _td(
        self,
        reward: Tensor | None = None,
        terminated: Tensor | None = None,
        truncated: Tensor | None = None,
    ) -> TensorDictBase:
        false = torch.zeros(self.task.batch, dtype=torch.bool, device=self.device)
        term = false if terminated is None else terminated
        trunc = false if truncated is None else truncated
        state = self.task.state
        out = {
            "observation": state.to(torch.float32),
            "state": state.clone(),
            "done": (term | trunc)[:, None],
            "terminated": term[:, None].clone(),
            "truncated": trunc[:, None].clone(),
        }
        if reward is not None:
            out["reward"] = reward[:, None].to(torch.float32)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None, **kwargs: Any) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        self.task.reset(mask)
        if mask is None or bool(mask.any()):  # an all-False mask restarted nothing
            self._needs_reset = False
        return self._td()

    def maybe_reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """TorchRL's ``maybe_reset``: the systems whose ``done`` / ``terminated`` /
        ``truncated`` (those present) is set restart, the other rows keep their entries; the
        same tensordict as :meth:`~torchrl.envs.EnvBase.maybe_reset` gives, without its generic
        reset machinery.

        Raises:
            ValueError: for a done entry that is not a bool tensor of shape (B, 1) or (B,).
        """
        B, ended = self.task.batch, None
        for key in ("done", "terminated", "truncated"):
            flag = tensordict.get(key, None)
            if flag is None:
                continue
            if not isinstance(flag, Tensor) or flag.dtype != torch.bool or flag.numel() != B:
                what = f"{flag.dtype} {tuple(flag.shape)}" if isinstance(flag, Tensor) else flag
                raise ValueError(
                    f"{key!r} must be a bool tensor of shape ({B}, 1), got {what}; nothing was "
                    "reset"
                )
            flag = flag.reshape(B)
            ended = flag if ended is None else ended | flag
        if ended is None or not bool(ended.any()):
            return tensordict
        self.task.reset(ended)
        self._needs_reset = False
        for key, fresh in self._td().items():
            old = tensordict.get(key, None)
            if old is not None and old.shape == fresh.shape:
                fresh = torch.where(ended.view(B, *[1] * (fresh.dim() - 1)), fresh, old)
            tensordict.set(key, fresh)
        return tensordict

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._needs_reset:
            raise ResetNeeded("call reset() before the first step()")
        action = tensordict.get("action", None)
        if action is None:
            raise ValueError(f"the tensordict holds no 'action' entry: {sorted(tensordict.keys())}")
        action = action.to(torch.float64)  # checked by the task's physics
        reward, term, trunc, _ = self.task.step(action)
        return self._td(reward, term, trunc)

    def set_seed(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        """TorchRL's ``set_seed``, with the seed checked first: TorchRL derives the next seed
        with numpy, which takes seeds >= 0 (a refused seed changes nothing)."""
        checked = None if seed is None else check_count("seed", seed, 0)
        out: int | None = super().set_seed(checked, static_seed)
        return out

    def _set_seed(self, seed: int | None) -> None:
        self.task.seed(seed)


class EpisodicGymEnv(gym.Env):
    """One-step gymnasium adapter over an episodic task (one parameter vector per episode).

    The task has ``param_dim``, ``context_dim``, ``n_classes``, ``sample_contexts(n,
    generator) -> (n, C)``, ``task(contexts, theta) -> returns`` and
    ``task.solution_class(contexts, theta)``. ``reset`` draws the context (observation, float64,
    shape (C,)) from the env's seeded generator; ``step(theta)`` plays the episode: the return,
    ``terminated=True`` and ``info["solution_class"]``.
    """

    def __init__(self, task: Any) -> None:
        self.task = task
        C, D = task.context_dim, task.param_dim
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (C,), np.float64)
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (D,), np.float64)
        self._gen = torch.Generator().manual_seed(0)
        self._context = torch.zeros(1, task.context_dim, dtype=torch.float64)
        self._ready = False  # reset, and not stepped since

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is not None:
            self._gen.manual_seed(check_count("seed", seed, 0))
        super().reset(seed=seed)
        self._context = self.task.sample_contexts(1, self._gen)
        self._ready = True
        return self._context[0].numpy().copy(), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self._ready:
            raise ResetNeeded("call reset() before step(): every episode is one step")
        theta = as_float_tensor("action", action).reshape(1, -1)
        if theta.shape[1] != self.task.param_dim:
            raise ValueError(
                f"action must hold {self.task.param_dim} numbers, got {tuple(theta.shape[1:])}"
            )
        as_finite_f64("action", theta)
        reward = float(self.task(self._context, theta)[0])
        k = int(self.task.solution_class(self._context, theta)[0])
        self._ready = False
        return self._context[0].numpy().copy(), reward, True, False, {"solution_class": k}


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """torch computes on one thread inside the block (or the decorated function), the thread
    count restored after: a task whose simulation amplifies round-off (hockey's contacts) then
    plays the same episodes whatever the process's thread count, worker or backend (torch
    splits large reductions, and MKL its products, by the threads)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
