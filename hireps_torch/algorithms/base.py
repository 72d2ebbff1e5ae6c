"""Shared by every HiREPS variant: :class:`Algorithm`, :class:`Experience`, :class:`HiREPSBase`."""

from __future__ import annotations

import copy
import numbers
import operator
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Protocol, Self, TypedDict, Unpack, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from hireps_torch.checks import (
    as_finite_f64,
    as_float_tensor,
    check_count,
    check_finite,
    check_nonnegative_float,
    check_positive_float,
    check_present_device,
    check_prune_threshold,
    check_seed,
)
from hireps_torch.features import FeatureMap, QuadraticFeatures
from hireps_torch.policies import HierarchicalPolicy

__all__ = [
    "Algorithm",
    "Experience",
    "HiREPSBase",
    "PolicyKwargs",
    "check_epsilons",
    "check_step",
    "check_saved_values",
    "checked_states",
    "member_policies",
    "population_seeds",
    "stream_seed",
]


@dataclass(frozen=True)
class Experience:
    """One iteration's N samples of K decision steps each (a population: leading S).

    Attributes:
        states: (N, K, C) contexts (episodic, K = 1, C = 0 without context) or states.
        actions: (N, K, D) drawn with :meth:`Algorithm.sample`.
        rewards: (N, K) returns / per-step rewards; higher is better.
        next_states: (N, K, C) where the decisions led: infinite horizon only.
        terminated: (N, K) bool, ended in a terminal state: infinite horizon only, optional.
    """

    states: Tensor
    actions: Tensor
    rewards: Tensor
    next_states: Tensor | None = None
    terminated: Tensor | None = None


@runtime_checkable
class Algorithm(Protocol):
    """The interface every HiREPS variant implements.

    Attributes:
        iteration: number of updates so far.
        population: S (every shape gains a leading S), or None for one run.
    """

    iteration: int
    population: int | None

    @property
    def policies(self) -> Sequence[HierarchicalPolicy]:
        """One policy per decision step (one, except for the time-indexed variant)."""
        ...

    def sample(self, states: Tensor, step: int = 0) -> Tensor:
        """Exploring actions (N, D) for states (N, C) at ``step``, from the seeded generator."""
        ...

    def mean_action(self, states: Tensor, step: int = 0) -> Tensor:
        """Noise-free actions (N, D): the mean of the most probable option."""
        ...

    def learn(self, experience: Experience) -> dict[str, Any]:
        """One update from samples of the current policies; diagnostics. Raising changes nothing."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the run bit-for-bit, as a copy (later updates leave it
        as it is)."""
        ...

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; one that does not fit raises, changing nothing."""
        ...


class PolicyKwargs(TypedDict, total=False):
    """Keyword options of the ``create`` methods' policies (:meth:`HierarchicalPolicy.create`).

    Attributes:
        init_std: initial option standard deviation, float or (D,) (1.0).
        spread: spread of the initial option means in units of ``init_std`` (1.0).
        gating_features: the gating's features (default: squared expansion of the state).
        policy_features: the options' features (default: the state: linear options).
        min_variance: option variance floor, float or (D,) (1e-8).
        covariance_prior, mean_prior: prior pseudo-samples (0.0; see
            :class:`~hireps_torch.policies.LinearGaussian`).
    """

    init_std: float | Tensor
    spread: float
    gating_features: FeatureMap | None
    policy_features: FeatureMap | None
    min_variance: float | Tensor
    covariance_prior: float
    mean_prior: float


def population_seeds(seed: object, population: int | None) -> tuple[list[int], bool]:
    """The members' distinct seeds (default 0 .. S-1) and True, or without a population
    ``[seed]`` (default 0) and False."""
    if population is not None:
        population = check_count("population", population, 1)
    if shape := tuple(getattr(seed, "shape", ())):  # an array or tensor of seeds
        raise TypeError(
            f"seed must be an integer or a list of integers (one per member), got a "
            f"{type(seed).__name__} of shape {shape}: pass seed.tolist()"
        )
    if not isinstance(seed, Sequence) or isinstance(seed, str | bytes):
        if population is None:
            return [0 if seed is None else check_seed("seed", seed)], False
        if seed is not None:
            raise ValueError(
                f"a population of {population} takes one seed per member (e.g. seed="
                f"{list(range(population))}), got the single seed {seed!r}"
            )
        return list(range(population)), True
    seeds = [check_seed(f"seed[{s}]", x) for s, x in enumerate(seed)]
    if not seeds:
        raise ValueError("a population needs at least one seed, got an empty sequence")
    if population is not None and len(seeds) != population:
        raise ValueError(
            f"population = {population} does not match the {len(seeds)} seeds given ({seeds})"
        )
    seen: dict[int, int] = {}  # torch seeds modulo 2**64 -> the seed given
    for x in seeds:
        y = seen.get(x % 2**64)
        if y is not None:  # the same seed again, or one equal to torch
            same = (
                f"seed {x} is repeated in {seeds}"
                if y == x
                else f"seeds {y} and {x} in {seeds} are one seed to torch (equal modulo 2**64)"
            )
            raise ValueError(f"{same}: members with one seed would be copies")
        seen[x % 2**64] = x
    return seeds, True


STREAMS = ("policy", "sampling", "env", "eval", "contexts")
"""The named random streams of a run, each seeded by :func:`stream_seed`."""


def stream_seed(seed: int, stream: str, *index: int) -> int:
    """The seed in [0, 2**32) of stream ``stream`` (one of :data:`STREAMS`) of the run with
    ``seed``, or of its part ``index`` (e.g. an iteration's draws): numpy's ``SeedSequence``
    of ``(seed mod 2**64, stream index, *index)``, so streams and parts are unrelated."""
    entropy = (seed % 2**64, STREAMS.index(stream), *index)
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def member_policies(
    seed: int | Sequence[int] | None,
    population: int | None,
    means: Sequence[Tensor | None],
    n_options: int,
    state_dim: int,
    action_dim: int,
    **policy_kwargs: Unpack[PolicyKwargs],
) -> tuple[list[HierarchicalPolicy], int | list[int] | None, list[int] | None]:
    """One fresh softmax-gated mixture of linear-Gaussian options per entry of ``means``
    (stacked over a population's members), the sampling seed(s) and a population's seeds.

    Args:
        seed: one seed (None: 0) or S (see :func:`population_seeds`): a member's seed seeds one
            generator for all its policies' initial option means; its ``"sampling"``
            :func:`stream_seed` is returned.
        population: S, or None.
        means: each policy's ``init_mean``: (D,), (O, D) or None (zeros).
        n_options: options per policy.
        state_dim: C (0: no context).
        action_dim: D.
        **policy_kwargs: see :class:`PolicyKwargs`.
    """
    seeds, many = population_seeds(seed, population)
    kwargs = policy_kwargs.copy()
    if kwargs.get("gating_features") is None and state_dim > 0:
        kwargs["gating_features"] = QuadraticFeatures(state_dim)
    create = partial(HierarchicalPolicy.create, n_options, state_dim, action_dim, **kwargs)
    gens = [torch.Generator().manual_seed(s) for s in seeds]
    members = [[create(init_mean=m, generator=g) for m in means] for g in gens]
    sampling = [stream_seed(s, "sampling") for s in seeds]
    if not many:
        return members[0], sampling[0], None
    stacked = [HierarchicalPolicy.stack([m[k] for m in members]) for k in range(len(means))]
    return stacked, sampling, seeds


def check_step(step: int, n_steps: int) -> int:
    """``step`` as an int in [0, n_steps); a ValueError naming the range otherwise."""
    try:
        if isinstance(step, bool):
            raise TypeError
        k = operator.index(step)
    except TypeError:
        if shape := tuple(getattr(step, "shape", ())):  # states in the step's place?
            raise ValueError(
                f"step must be an integer in [0, {n_steps}), got a {type(step).__name__} of "
                f"shape {shape} (sample and mean_action take (states, step); a time-indexed "
                "algorithm's ask, act and value take (step, contexts))"
            ) from None
        raise ValueError(f"step must be an integer in [0, {n_steps}), got {step!r}") from None
    if not 0 <= k < n_steps:
        raise ValueError(f"step must be in [0, {n_steps}) (K = {n_steps} decision steps), got {k}")
    return k


def checked_states(
    value: object,
    name: str,
    lead: tuple[int, ...],
    C: int,
    device: torch.device,
    *,
    noun: str = "state",
    hint: str = "",
    squeeze: bool = False,
) -> Tensor:
    """``value`` as finite float64 states ([S,] N, C) on ``device``, N >= 1 (``lead``: (S,) or
    ()); ``squeeze``: (N,) is read as (N, 1) when C = 1 without S. A ValueError naming ``name``
    (``hint`` ends the shape error, ``noun`` names a row)."""
    s = as_float_tensor(name, value, device=device)
    if squeeze and not lead and s.dim() == 1 and C == 1:
        s = s[:, None]
    if s.dim() != 2 + len(lead) or s.shape[:-2] != lead or s.shape[-1] != C:
        names, sizes = ("(S, N, C) = ", f"{lead[0]}, ") if lead else ("", "")
        raise ValueError(
            f"{name} must have shape {names}({sizes}N, {C}), got {tuple(s.shape)}{hint}"
        )
    if s.shape[-2] < 1:
        raise ValueError(f"{name} must hold at least one {noun}, got {tuple(s.shape)}")
    as_finite_f64(name, s)
    return s


def _check_shape(name: str, value: object, expected: tuple[int | str, ...]) -> Tensor:
    """``value`` as a tensor of the ``expected`` shape (a str entry: any size)."""
    if not isinstance(value, Tensor):
        raise TypeError(f"experience.{name} must be a tensor, got {type(value).__name__}")
    shape = tuple(value.shape)
    fits = len(shape) == len(expected) and all(
        isinstance(e, str) or s == e for s, e in zip(shape, expected, strict=True)
    )
    if not fits:
        want = ", ".join(str(e) for e in expected)
        raise ValueError(f"experience.{name} must have shape ({want}), got {shape}")
    return value


class HiREPSBase:
    """Shared bookkeeping: kappa_rel, prune_threshold, generator, iteration and their checkpoint."""

    policies: Sequence[HierarchicalPolicy]
    policy: HierarchicalPolicy  # the variants with one policy

    def __init__(
        self,
        policy: HierarchicalPolicy | None = None,
        *,
        kappa_rel: float | None,
        prune_threshold: float,
        seed: int | Sequence[int] | None,
        population: int | None = None,
    ) -> None:
        """``policy``: the one policy of a variant with one (its population taken from it)."""
        if policy is not None:
            if not isinstance(policy, HierarchicalPolicy):
                got = type(policy).__name__
                raise TypeError(f"policy must be a HierarchicalPolicy, got {got}")
            population, self.policy, self.policies = policy.population, policy, (policy,)
        if kappa_rel is not None:
            kappa_rel = check_nonnegative_float("kappa_rel", kappa_rel)
        self.kappa_rel = kappa_rel
        self.prune_threshold = check_prune_threshold(prune_threshold)
        seeds, many = population_seeds(seed, population)
        self.population = population
        self._seeds = seeds if many and population is not None else None  # checked above
        gens = [torch.Generator().manual_seed(s) for s in seeds]
        self.generator: torch.Generator | list[torch.Generator] = gens if many else gens[0]
        self.iteration = 0

    @property
    def seeds(self) -> list[int] | None:
        """A population's S seeds, which name its members in the dual's warnings ("member 1
        (seed 4)"): those given to ``create``, or to the constructor (None for one run)."""
        return self._seeds

    @seeds.setter
    def seeds(self, seeds: Sequence[int] | None) -> None:
        S = self.population
        if seeds is not None:
            if (
                S is None
                or not isinstance(seeds, Sequence)
                or isinstance(seeds, str | bytes)
                or len(seeds) != S
            ):
                want = "None for one run" if S is None else f"{S} integers, one per member,"
                raise ValueError(f"seeds must be {want} got {seeds!r}")
            seeds = [check_seed(f"seeds[{s}]", x) for s, x in enumerate(seeds)]
        self._seeds = None if seeds is None else list(seeds)

    @property
    def device(self) -> torch.device:
        """Where the policies, the update's samples and its dual live."""
        return self.policies[0].sub_policies[0].bias.device

    def _states(self, states: Any) -> Tensor:
        """``states`` ([S,] N, C) checked, as float64: each variant's own check."""
        raise NotImplementedError

    def _at(self, states: Any, step: int) -> tuple[HierarchicalPolicy, Tensor]:
        """Step ``step``'s policy (the step checked first) and the checked ``states``."""
        return self.policies[check_step(step, len(self.policies))], self._states(states)

    def _experience(self, experience: Experience, transitions: bool = False) -> Experience:
        """``experience`` with its shapes checked against the K policies (``transitions``:
        next_states, for the infinite-horizon variant)."""
        if not isinstance(experience, Experience):
            raise TypeError(f"learn takes an Experience, got {type(experience).__name__}")
        K, C, D = len(self.policies), self.policies[0].context_dim, self.policies[0].action_dim
        lead: tuple[int | str, ...] = () if self.population is None else (self.population,)
        rewards = _check_shape("rewards", experience.rewards, (*lead, "N", K))
        N = rewards.shape[len(lead)]
        _check_shape("states", experience.states, (*lead, N, K, C))
        _check_shape("actions", experience.actions, (*lead, N, K, D))
        algorithm = type(self).__name__
        if not transitions:
            for name in ("next_states", "terminated"):
                if getattr(experience, name) is not None:
                    raise ValueError(
                        f"experience.{name} is read by InfiniteHorizonHiREPS only; {algorithm} "
                        f"learns from states, actions and rewards (leave {name} None)"
                    )
            return experience
        if experience.next_states is None:
            shape = ", ".join(map(str, (*lead, N, K, C)))
            raise ValueError(f"{algorithm} needs experience.next_states ({shape})")
        _check_shape("next_states", experience.next_states, (*lead, N, K, C))
        if experience.terminated is not None:  # its dtype: checked by update
            _check_shape("terminated", experience.terminated, (*lead, N, K))
        return experience

    @torch.no_grad()
    def sample(self, states: Tensor | int | None, step: int = 0) -> Tensor:
        """Exploring actions ([S,] N, D) for states ([S,] N, C) at ``step`` (in [0, K)), from
        the seeded generator(s); the episodic variant without context also takes a count N.

        Raises:
            MemoryError: the N x options samples do not fit in memory (the generators are left
                as they were, as for any failed call).
        """
        policy, s = self._at(states, step)
        gen = self.generator
        gens = [g for g in (gen if isinstance(gen, list | tuple) else [gen]) if g is not None]
        saved = [g.get_state() for g in gens]
        try:
            return policy.sample(s, self.generator)[0]
        except BaseException as exc:
            for g, state in zip(gens, saved, strict=True):
                g.set_state(state)
            if (too_many := _out_of_memory(exc, "sampling", s, policy)) is not None:
                raise too_many from exc
            raise

    @torch.no_grad()
    def mean_action(self, states: Tensor | int | None, step: int = 0) -> Tensor:
        """Noise-free actions ([S,] N, D) at ``step``: the mean of the most probable option.

        Raises:
            MemoryError: the N x options values do not fit in memory.
        """
        policy, s = self._at(states, step)
        try:
            return policy.mean_action(s)[0]
        except BaseException as exc:
            if (too_many := _out_of_memory(exc, "the mean action of", s, policy)) is not None:
                raise too_many from exc
            raise

    def to(self, device: torch.device | str) -> Self:
        """Move policies, feature maps and learned values to ``device``; return ``self``. The
        generators stay on the CPU. ValueError: unknown or absent device (nothing moved)."""
        dev = check_present_device(device)
        for name, value in list(vars(self).items()):
            if isinstance(value, torch.nn.Module):
                value.to(dev)
            elif isinstance(value, Tensor):
                setattr(self, name, value.to(dev))
            elif isinstance(value, list) and value and isinstance(value[0], torch.nn.Module):
                for module in value:
                    module.to(dev)
        return self

    def _state(self, **learned: Any) -> dict[str, Any]:
        """A checkpoint: copies of ``learned`` (the variant's entries) and the shared entries,
        which later updates leave as they are."""
        gen = self.generator
        return {
            **copy.deepcopy(learned),
            "generator": [g.get_state() for g in gen] if isinstance(gen, list) else gen.get_state(),
            "iteration": self.iteration,
            "kappa_rel": self.kappa_rel,
        }

    def _keys_checked(self, state: object, *keys: str) -> Mapping[str, Any]:
        """``state`` as a mapping with exactly the variant's ``keys``, ``iteration`` and
        ``kappa_rel`` (and optionally ``generator``)."""
        algorithm, required = type(self).__name__, {*keys, "iteration", "kappa_rel"}
        if not isinstance(state, Mapping):
            got = type(state).__name__
            raise TypeError(f"{algorithm}.load_state_dict takes a mapping, got {got}")
        given = set(state)
        missing, unexpected = sorted(required - given), sorted(given - required - {"generator"})
        if missing or unexpected:
            writer = next((w for k, w in _WRITERS.items() if k in given), "an unknown writer")
            raise ValueError(
                f"{algorithm}.load_state_dict: this state does not fit (missing keys {missing}, "
                f"unexpected keys {unexpected}); it looks like a checkpoint of {writer}"
            )
        return state

    def _load_shared(self, state: Mapping[str, Any]) -> None:
        """Check the shared entries of :meth:`_state`, then set them (no generator: keep the
        current one); the variants call it once their own entries are checked."""
        gen = state.get("generator")
        if gen is not None:
            ours = self.generator
            many = isinstance(gen, list | tuple)
            if many != isinstance(ours, list) or (isinstance(ours, list) and len(gen) != len(ours)):
                size = len(ours) if isinstance(ours, list) else None
                raise ValueError(
                    f"the state's generators ({len(gen) if many else 'one'}) do not fit this "
                    f"algorithm's ({size or 'one'}): a checkpoint of another population size"
                )
            try:
                for g in gen if many else [gen]:
                    torch.Generator().set_state(g)
            except (RuntimeError, TypeError) as exc:
                msg = f"the state's generator is not a CPU generator state: {exc}"
                raise ValueError(msg) from None
        iteration = check_count("iteration", state["iteration"], 0)
        kappa_rel = state["kappa_rel"]
        if kappa_rel is not None:
            kappa_rel = check_nonnegative_float("kappa_rel", kappa_rel)
        if gen is not None:
            if isinstance(self.generator, list):
                for g, saved in zip(self.generator, gen, strict=True):
                    g.set_state(saved)
            else:
                self.generator.set_state(gen)
        self.iteration, self.kappa_rel = iteration, kappa_rel


def _out_of_memory(
    exc: BaseException, doing: str, s: Tensor, policy: HierarchicalPolicy
) -> MemoryError | None:
    """A MemoryError naming N when ``exc`` is torch's failure to allocate for states s
    ([S,] N, C), else None."""
    if not isinstance(exc, torch.OutOfMemoryError) and not any(
        why in str(exc) for why in ("can't allocate", "size calculation overflowed")
    ):
        return None
    N, O, D, lead = s.shape[-2], policy.n_options, policy.action_dim, s.shape[:-2]
    return MemoryError(
        f"{doing} N = {N:,} needs {'S x ' if lead else ''}N x {O} options x {D} float64 values "
        f"({lead.numel() * N * O * D * 8 / 1e9:.3g} GB) several times at once, more than this "
        "machine could allocate: ask for fewer"
    )


_WRITERS = {
    "policies": "TimeIndexedHiREPS",
    "gamma": "InfiniteHorizonHiREPS",
    "policy": "EpisodicHiREPS / REPS",
}
"""A checkpoint's telling key -> the algorithm that writes it (the first that fits)."""


def check_epsilons(epsilon: object, K: int) -> list[float]:
    """epsilon (one number or K, e.g. a (K,) tensor) as K floats > 0."""
    shape = getattr(epsilon, "shape", None)
    if isinstance(epsilon, str | bytes | Mapping):
        raise TypeError(
            f"epsilon must be a float or {K} floats, got {type(epsilon).__name__} {epsilon!r}"
        )
    if isinstance(epsilon, numbers.Real | bool) or (shape is not None and len(shape) == 0):
        return [check_positive_float("epsilon", epsilon)] * K
    try:
        items = list(epsilon)  # type: ignore[call-overload]
    except TypeError:
        raise TypeError(
            f"epsilon must be a float or {K} floats, got {type(epsilon).__name__}"
        ) from None
    if len(items) != K:
        raise ValueError(
            f"epsilon must be finite and > 0, one float or {K} (one per step), got {epsilon}"
        )
    return [check_positive_float(f"epsilon[{k}]", e) for k, e in enumerate(items)]


def check_saved_values(saved: object, current: Tensor) -> Tensor:
    """A checkpoint's value weights as a finite float64 copy of ``current``'s shape."""
    v = as_float_tensor("value_weights", saved).clone()
    if v.shape != current.shape:
        raise ValueError(
            f"value_weights: saved {tuple(v.shape)}, expected {tuple(current.shape)} (a "
            "checkpoint with other value features or another number of steps?)"
        )
    check_finite("value_weights", v, "")
    return v.to(current.device)
