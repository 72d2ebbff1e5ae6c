"""TorchRL glue (the only place TensorDicts appear): the policy as a TensorDict module,
collectors and their shutdown. Usage: README.md."""

from __future__ import annotations

import contextlib
import gc
import multiprocessing
import signal
from collections.abc import Callable, Iterator
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, dispatch
from torch import Tensor, nn
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import EnvBase

from hireps_torch.checks import as_float_tensor, check_count, check_seed
from hireps_torch.policies import HierarchicalPolicy

__all__ = [
    "ActorModule",
    "PolicyActor",
    "TimeIndexedActor",
    "episodes",
    "make_collector",
    "policy_module",
    "shutdown_collector",
    "time_indexed_module",
    "member_transitions",
    "transitions",
    "signal_handled",
    "workers_ignore_sigint",
]


class PolicyActor(nn.Module):
    """``observation (B, C) -> action (B, A), option (B,)`` for a :class:`HierarchicalPolicy`.

    Samples (from ``generator``, kept as ``self.generator``: one, or a population's list of S;
    None: the global RNG) or, with ``deterministic``, takes
    :meth:`~HierarchicalPolicy.mean_action`; the action has the observation's dtype (float64
    for integer observations). A population of S takes observations (..., S B, C): the last
    batch dimension holds its members' rows, member after member.
    """

    def __init__(
        self,
        policy: HierarchicalPolicy,
        deterministic: bool = False,
        generator: torch.Generator | list[torch.Generator] | None = None,
    ) -> None:
        super().__init__()
        _check_policies([policy])
        self.policy = policy
        self.deterministic = deterministic
        self.generator = generator

    @torch.no_grad()
    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor]:
        lead, C = observation.shape[:-1], observation.shape[-1]
        s, policy = as_float_tensor("observation", observation), self.policy
        _check_width(observation, policy.context_dim)
        S = policy.population
        if S is not None:  # (..., S B, C) -> (S, ... B, C)
            if not lead or lead[-1] % S:
                raise ValueError(
                    f"a population of {S} takes observations (..., S B, C), its members' rows "
                    f"one after another; got shape {tuple(observation.shape)}"
                )
            s = s.reshape(*lead[:-1], S, lead[-1] // S, C).movedim(-3, 0)
        s = s.reshape(*policy.batch_shape, lead.numel() // (S or 1), C)
        a, o = policy.mean_action(s) if self.deterministic else policy.sample(s, self.generator)
        if S is not None:  # back to (..., S B)
            a = a.reshape(S, *lead[:-1], lead[-1] // S, a.shape[-1]).movedim(0, -3)
            o = o.reshape(S, *lead[:-1], lead[-1] // S).movedim(0, -2)
        dtype = observation.dtype if observation.is_floating_point() else torch.float64
        return a.to(dtype).reshape(*lead, a.shape[-1]), o.reshape(lead)


def _check_width(observation: Tensor, C: int) -> None:
    """A ValueError unless ``observation`` is (..., C), C the policies' state dimension."""
    if observation.shape[-1:] != (C,):
        raise ValueError(
            f"observation must have shape (..., {C}) (the policy's state dimension), got "
            f"{tuple(observation.shape)}"
        )


def _check_policies(policies: object) -> None:
    """``policies`` a list of :class:`HierarchicalPolicy`; a ``TypeError`` otherwise."""
    if not isinstance(policies, list | tuple | nn.ModuleList):
        raise TypeError(f"policies must be a list of HierarchicalPolicy, got {type(policies)}")
    for k, pol in enumerate(policies):
        if not isinstance(pol, HierarchicalPolicy):
            raise TypeError(f"policy {k} must be a HierarchicalPolicy, got {type(pol).__name__}")


class ActorModule(TensorDictModuleBase):
    """An actor (:class:`PolicyActor`, :class:`TimeIndexedActor`) as a TensorDict module: reads
    ``in_keys``, writes the actor's action and option under ``out_keys`` (``action``,
    ``option``) into ``tensordict_out`` (default: the tensordict it is given) and returns it;
    called with keyword tensors (``module(observation=x)``), returns ``(action, option)``.
    A ``TensorDictModule`` over the actor without its generic output conversion and without
    ``set_skip_existing``: entries already present are overwritten."""

    def __init__(self, actor: nn.Module, in_keys: list[str]) -> None:
        super().__init__()
        self.module = actor
        self.in_keys = list(in_keys)
        self.out_keys = ["action", "option"]

    @dispatch(auto_batch_size=False)
    def forward(
        self, tensordict: TensorDictBase, tensordict_out: TensorDictBase | None = None
    ) -> TensorDictBase:
        inputs = [tensordict.get(key, None) for key in self.in_keys]
        if any(x is None for x in inputs):
            missing = [k for k, x in zip(self.in_keys, inputs, strict=True) if x is None]
            raise KeyError(
                f"the actor reads {missing}, which the tensordict does not hold: "
                f"{sorted(map(str, tensordict.keys()))}"
            )
        out = tensordict if tensordict_out is None else tensordict_out
        for key, value in zip(self.out_keys, self.module(*inputs), strict=True):
            out.set(key, value)
        return out


def policy_module(
    policy: HierarchicalPolicy,
    deterministic: bool = False,
    observation_key: str = "observation",
    generator: torch.Generator | list[torch.Generator] | None = None,
) -> ActorModule:
    """Wrap the policy for TorchRL: reads ``observation_key``, writes ``action`` and ``option``
    (sampled from ``generator``, e.g. the algorithm's ``generator``; None: the global RNG, as a
    collector with worker processes needs)."""
    return ActorModule(PolicyActor(policy, deterministic, generator), [observation_key])


class TimeIndexedActor(nn.Module):
    """``observation (B, C), step_count (B, 1) -> action (B, A), option (B,)``: row b acts with
    ``policies[step_count[b]]``, otherwise as :class:`PolicyActor`; the policies of one run
    (not a population)."""

    def __init__(
        self,
        policies: list[HierarchicalPolicy],
        deterministic: bool = False,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        _check_policies(policies)
        dims = {int(p.action_dim) for p in policies}
        if len(policies) < 1 or len(dims) != 1:
            raise ValueError(
                f"need >= 1 policies sharing one action dimension, got dimensions "
                f"{[int(p.action_dim) for p in policies]}"
            )
        if populations := [k for k, p in enumerate(policies) if p.batch_shape]:
            raise ValueError(
                f"time_indexed_module takes the policies of one run; policy {populations[0]} "
                f"holds a population of {policies[populations[0]].batch_shape[0]} (act with "
                "one member's policies)"
            )
        self.policies = nn.ModuleList(policies)
        self.deterministic = deterministic
        self.generator = generator

    @torch.no_grad()
    def forward(self, observation: Tensor, step_count: Tensor) -> tuple[Tensor, Tensor]:
        lead = observation.shape[:-1]
        s = as_float_tensor("observation", observation).reshape(-1, observation.shape[-1])
        _check_width(observation, int(self.policies[0].context_dim))  # type: ignore[arg-type]
        if step_count.is_floating_point() or step_count.is_complex():
            raise ValueError(f"step_count must be an integer tensor, got {step_count.dtype}")
        if step_count.shape not in (lead, (*lead, 1)):
            raise ValueError(
                f"step_count must have shape {tuple(lead)} or {(*lead, 1)} (one per "
                f"observation row), got {tuple(step_count.shape)}"
            )
        k = step_count.reshape(-1).long()
        K = len(self.policies)
        if bool(((k < 0) | (k >= K)).any()):
            raise ValueError(f"step_count must be in [0, {K}), got {torch.unique(k).tolist()}")
        dim = int(self.policies[0].action_dim)  # type: ignore[arg-type]
        a = s.new_zeros(s.shape[0], dim)
        o = torch.zeros(s.shape[0], dtype=torch.long, device=s.device)
        for step in torch.unique(k).tolist():
            rows = k == step
            pol, x = self.policies[step], s[rows]
            out = pol.mean_action(x) if self.deterministic else pol.sample(x, self.generator)
            a[rows], o[rows] = out[0], out[1]
        dtype = observation.dtype if observation.is_floating_point() else torch.float64
        return a.to(dtype).reshape(*lead, a.shape[-1]), o.reshape(lead)


def time_indexed_module(
    policies: list[HierarchicalPolicy],
    deterministic: bool = False,
    observation_key: str = "observation",
    step_key: str = "step_count",
    generator: torch.Generator | None = None,
) -> ActorModule:
    """Wrap per-step policies for TorchRL: reads the observation and ``step_key``, writes
    ``action`` and ``option`` (sampled from ``generator``; None: the global RNG)."""
    return ActorModule(
        TimeIndexedActor(policies, deterministic, generator), [observation_key, step_key]
    )


def make_collector(
    create_env_fn: Callable[[], EnvBase],
    policy: TensorDictModuleBase,
    *,
    frames_per_batch: int,
    total_frames: int = -1,
    num_workers: int = 1,
    reset_at_each_iter: bool = False,
    seed: int | None = None,
) -> Collector | MultiSyncCollector:
    """A TorchRL collector over ``create_env_fn()``.

    ``num_workers = 1``: a :class:`~torchrl.collectors.Collector` using the policy in place,
    without trajectory ids (``("collector", "traj_ids")``: episodes end where ``done`` is set);
    more: a :class:`~torchrl.collectors.MultiSyncCollector` (call
    ``collector.update_policy_weights_()`` after each update, :func:`shutdown_collector` at the
    end, and guard the script with ``if __name__ == "__main__":``). ``reset_at_each_iter``
    restarts every environment at each batch.
    """
    num_workers = check_count("num_workers", num_workers, 1)
    frames_per_batch = check_count("frames_per_batch", frames_per_batch, 1)
    if check_count("total_frames", total_frames, -1) == 0:
        raise ValueError("total_frames must be -1 (no end) or >= 1, got 0")
    if not callable(create_env_fn):
        raise TypeError(
            f"create_env_fn must be a callable that builds the environment, got "
            f"{type(create_env_fn).__name__}"
        )
    seed = None if seed is None else check_seed("seed", seed)
    if num_workers > 1 and getattr(getattr(policy, "module", None), "generator", None) is not None:
        raise ValueError(
            f"the actor samples from its generator, which num_workers = {num_workers} processes "
            "would each copy (the same draws in every worker): build it with generator=None "
            "(each worker then draws from its own global RNG, seeded by seed)"
        )
    common: dict[str, Any] = {
        "frames_per_batch": frames_per_batch,
        "total_frames": total_frames,
        "reset_at_each_iter": reset_at_each_iter,
        "auto_register_policy_transforms": False,
    }
    collector: Collector | MultiSyncCollector
    if num_workers == 1:
        collector = Collector(create_env_fn, policy, track_traj_ids=False, **common)
    else:
        if frames_per_batch % num_workers:
            raise ValueError(
                f"frames_per_batch = {frames_per_batch} must be divisible by num_workers = "
                f"{num_workers}"
            )
        before = set(multiprocessing.active_children())
        built: MultiSyncCollector | None = None
        try:
            with workers_ignore_sigint():
                built = MultiSyncCollector(
                    [create_env_fn] * num_workers, policy, cat_results="stack", **common
                )
        except BaseException:  # a Ctrl-C while the workers start: none of them is left
            if built is not None:
                shutdown_collector(built)
            for proc in set(multiprocessing.active_children()) - before:
                proc.kill()
                proc.join()
            raise
        collector = built
    if seed is not None:
        collector.set_seed(seed)
    return collector


@contextlib.contextmanager
def signal_handled(sig: int, handler: Any) -> Iterator[None]:
    """``handler`` (a function or ``signal.SIG_IGN``) for signal ``sig`` while active, the one
    before after; a no-op outside the main thread."""
    try:
        previous = signal.signal(sig, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(sig, previous)


@contextlib.contextmanager
def workers_ignore_sigint() -> Iterator[None]:
    """SIGINT blocked in this thread while worker processes start: they inherit the block and
    never see a Ctrl-C (a worker that wants it unblocks it), and this process takes one that
    came meanwhile when the block ends."""
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()  # its first start unblocks SIGINT in the caller
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def shutdown_collector(collector: Any) -> None:
    """Shut a collector and its weight-sync schemes down so that the interpreter can exit."""
    try:
        collector.shutdown()
    finally:
        schemes = getattr(collector, "_weight_sync_schemes", None) or {}
        for scheme in list(schemes.values()):
            stop = getattr(scheme, "shutdown", None)
            if callable(stop):
                with contextlib.suppress(Exception):  # best effort at teardown
                    stop()
        gc.collect()


def episodes(
    batch: TensorDictBase, K: int, state_key: str = "observation"
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Cut a batch of N whole K-step episodes (``done`` flags checked) into per-episode arrays.

    Returns:
        states (N, K, C), actions (N, K, A), rewards (N, K) and final states (N, C), float64.
    """
    K = check_count("K", K, 1)
    s, s_next, a, r, done = _entries(batch, state_key, ("next", "done"))
    T = s.shape[0]
    if T % K:
        raise ValueError(f"the batch holds {T} steps, not a whole number of {K}-step episodes")
    done = done.reshape(-1, K)
    if not bool(done[:, -1].all()) or bool(done[:, :-1].any()):
        raise ValueError(f"the batch is not made of whole {K}-step episodes (done flags)")
    N = T // K
    states = s.to(torch.float64).reshape(N, K, -1)
    rewards = r.to(torch.float64).reshape(N, K)
    final = s_next.to(torch.float64).reshape(N, K, -1)[:, -1]
    return states, a.to(torch.float64).reshape(N, K, -1), rewards, final


def _entries(batch: TensorDictBase, state_key: str, extra: Any) -> list[Tensor]:
    """The flattened state, next state, action, reward and ``extra`` entries of a collected
    batch; a ``ValueError`` for an empty batch or one without those entries."""
    if not isinstance(batch, TensorDictBase):
        raise TypeError(f"batch must be a TensorDict of collected steps, got {type(batch)}")
    if batch.batch_size.numel() == 0:
        raise ValueError(f"the batch holds no steps (batch size {tuple(batch.batch_size)})")
    keys = [state_key, ("next", state_key), "action", ("next", "reward"), extra]
    present = batch.keys(include_nested=True)
    if missing := [k for k in keys if k not in present]:
        raise ValueError(
            f"the batch holds no {missing[0]!r} entry (state_key = {state_key!r}); its keys: "
            f"{sorted(map(str, batch.keys(include_nested=True, leaves_only=True)))}"
        )
    flat = batch.reshape(-1)
    return [flat.get(k) for k in keys]


def member_transitions(
    batch: TensorDictBase, members: int, state_key: str = "state"
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """A population's collected batch (its environments member-major, as ``MemberTasks`` lays
    them out) as each member's decisions.

    Returns:
        states (S, N, C), actions (S, N, A), rewards (S, N), next_states (S, N, C) (float64)
        and terminated (S, N) bool, S = ``members``.
    """
    s, a, r, s_next, _ = transitions(batch, state_key)
    terminated = batch["next", "terminated"].reshape(-1)
    s, a, r, s_next, terminated = (
        x.reshape(members, -1, *x.shape[1:]) for x in (s, a, r, s_next, terminated)
    )
    return s, a, r, s_next, terminated


def transitions(
    batch: TensorDictBase, state_key: str = "observation"
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Flatten a collected (..., T) batch into decision samples.

    Returns:
        states (N, C), actions (N, A), rewards (N,), next_states (N, C) (float64; the state
        reached by the decision, before a reset) and options (N,) int64.
    """
    s, s_next, a, r, o = _entries(batch, state_key, "option")
    s, s_next, a, r = (x.to(torch.float64) for x in (s, s_next, a, r))
    return s, a.reshape(s.shape[0], -1), r.reshape(-1), s_next, o.reshape(-1)
