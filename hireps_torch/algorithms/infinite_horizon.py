"""Infinite-horizon HiREPS (Daniel, Neumann & Peters) over decisions (s_i, a_i, r_i, s'_i) of
a restart process (restart probability 1 - gamma per decision).

The dual (:func:`hireps_torch.dual.solve_infinite_horizon_dual`) gives

    P_io ∝ p~_io^(1 + xi/eta) exp((r_i + gamma v^T phi(s'_i) - v^T phi(s_i)) / eta)

with KL(P || q p~) = epsilon, E_P[-log p~] <= kappa and stationarity
sum_i w_i (phi(s_i) - gamma phi(s'_i)) = (1 - gamma) phi_hat_0; then the weighted refit and
pruning. One option and ``kappa_rel=None``: infinite-horizon REPS.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Unpack

import torch
from torch import Tensor

from hireps_torch._linalg import reduce_each
from hireps_torch.algorithms._options import apply_refit, option_bounds, per_member, plan_refit
from hireps_torch.algorithms.base import (
    Experience,
    HiREPSBase,
    PolicyKwargs,
    check_saved_values,
    checked_states,
    member_policies,
)
from hireps_torch.checks import (
    as_checked,
    as_float_tensor,
    check_count,
    check_finite,
    check_positive_float,
)
from hireps_torch.dual.infinite_horizon import check_gamma, infinite_horizon_solution
from hireps_torch.dual.inputs import warn_if_degenerate
from hireps_torch.dual.solver import LbfgsSettings
from hireps_torch.features import FeatureMap, check_feature_map
from hireps_torch.policies import HierarchicalPolicy

__all__ = ["InfiniteHorizonHiREPS"]


class InfiniteHorizonHiREPS(HiREPSBase):
    """Infinite-horizon HiREPS: ``update`` and :class:`~hireps_torch.algorithms.Algorithm` (K = 1).

    Args:
        policy: the hierarchical policy (updated in place); its context is the state.
        value_features: features phi(s) of the value function (e.g. :class:`FourierFeatures`).
        initial_states: (M, C) draws from the start distribution; phi_hat_0 is their mean
            feature vector (a population: shared, or (S, M, C), one set per member).
        gamma: 1 - restart probability per decision, in (0, 1).
        epsilon: KL bound per iteration, > 0.
        kappa_rel: entropy bound as a fraction of the current mean option entropy; None: off.
        prune_threshold: options whose prior mass falls below this are pruned (0: never).
        seed: seed of the generator of :meth:`sample` (None: 0).

    ``update`` / ``learn`` and ``load_state_dict`` either complete or raise and change nothing.
    """

    def __init__(
        self,
        policy: HierarchicalPolicy,
        value_features: FeatureMap,
        initial_states: Tensor,
        *,
        gamma: float,
        epsilon: float = 0.5,
        kappa_rel: float | None = 0.9,
        prune_threshold: float = 1e-4,
        seed: int | Sequence[int] | None = None,
    ) -> None:
        self.epsilon = check_positive_float("epsilon", epsilon)
        self.gamma = check_gamma(gamma)
        super().__init__(policy, kappa_rel=kappa_rel, prune_threshold=prune_threshold, seed=seed)
        if check_feature_map("value_features", value_features) is None:
            raise TypeError("value_features must be a feature map (e.g. FourierFeatures)")
        C = value_features.in_features
        if policy.context_dim != C:
            raise ValueError(
                f"value_features take states of dimension {C}, the policy of dimension "
                f"{policy.context_dim}"
            )
        self.value_features = value_features.to(self.device)  # where the policy is
        per_member = policy.population is not None and getattr(initial_states, "dim", int)() == 3
        s0 = self._states(initial_states, "initial_states", population=per_member)
        self.initial_features = value_features(s0).mean(-2)
        check_finite("value features of initial_states", self.initial_features)
        self.value_weights = s0.new_zeros(*policy.batch_shape, value_features.out_features)

    @classmethod
    def create(
        cls,
        state_dim: int,
        action_dim: int,
        *,
        value_features: FeatureMap,
        initial_states: Tensor,
        gamma: float,
        n_options: int = 5,
        init_mean: Tensor | None = None,
        epsilon: float = 0.5,
        kappa_rel: float | None = 0.9,
        prune_threshold: float = 1e-4,
        seed: int | Sequence[int] | None = None,
        population: int | None = None,
        **policy_kwargs: Unpack[PolicyKwargs],
    ) -> InfiniteHorizonHiREPS:
        """Build the algorithm with a fresh softmax-gated mixture of linear-Gaussian options.

        Args:
            state_dim: C, the state dimension, >= 1.
            action_dim: A.
            value_features: features phi(s) of the value function, ``in_features = C``.
            initial_states: (M, C) draws from the start distribution.
            gamma: 1 - restart probability per decision, in (0, 1).
            n_options: O.
            init_mean: (A,) or (O, A) initial option means; zeros by default.
            epsilon: KL bound.
            kappa_rel: relative entropy bound (None: off).
            prune_threshold: prior mass below which options are pruned (0: never).
            seed: seeds the initial option means (None: 0) and, by its "sampling" ``stream_seed``,
                the sampling generator; a sequence of S distinct seeds builds a population.
            population: S independent runs (see :meth:`EpisodicHiREPS.create`); the
                ``initial_states`` are shared.
            **policy_kwargs: see :class:`~hireps_torch.algorithms.base.PolicyKwargs`.
        """
        state_dim = check_count("state_dim", state_dim, 1)
        policy, sampling, seeds = member_policies(
            seed, population, [init_mean], n_options, state_dim, action_dim, **policy_kwargs
        )
        algo = cls(
            policy[0],
            value_features,
            initial_states,
            gamma=gamma,
            epsilon=epsilon,
            kappa_rel=kappa_rel,
            prune_threshold=prune_threshold,
            seed=sampling,
        )
        algo.seeds = seeds
        return algo

    def value(self, states: Tensor) -> Tensor:
        """v^T phi(s) from the last update: ([S,] N, C) -> ([S,] N)."""
        phi = self.value_features(self._states(states))
        return (phi @ self.value_weights[..., None])[..., 0]

    def _transitions(
        self,
        states: Tensor,
        actions: Tensor,
        rewards: Tensor,
        next_states: Tensor,
        terminated: Tensor | None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
        """Checked float64 inputs of :meth:`update` (terminated: bool or None)."""
        s = self._states(states)
        N, A = s.shape[-2], self.policy.action_dim
        lead = self.policy.batch_shape
        if N < 2:
            raise ValueError(f"the update needs at least 2 decisions, got states {tuple(s.shape)}")
        a = as_checked("actions", actions, (*lead, N, A), device=self.device)
        R = as_float_tensor("rewards", rewards, device=self.device)
        if R.shape != (*lead, N):
            raise ValueError(
                f"rewards must have shape {(*lead, N)} (one per decision of states "
                f"{tuple(s.shape)}), got {tuple(R.shape)}"
            )
        check_finite("rewards", R)
        s_next = self._states(next_states, "next_states")
        if s_next.shape != s.shape:
            raise ValueError(
                f"next_states must have shape {tuple(s.shape)}, got {tuple(s_next.shape)}"
            )
        term = None
        if terminated is not None:
            try:
                term = torch.as_tensor(terminated)
            except (TypeError, ValueError, RuntimeError, NotImplementedError):
                raise TypeError(
                    f"terminated must be a bool tensor of shape {(*lead, N)}, got "
                    f"{type(terminated).__name__} {terminated!r:.60}"
                ) from None
            if term.device != self.device:
                raise ValueError(
                    f"terminated is on device {term.device} but the other inputs are on "
                    f"{self.device}: move them to one device (e.g. terminated.to("
                    f"{str(self.device)!r}))"
                )
            if term.shape != (*lead, N) or term.dtype != torch.bool:
                raise ValueError(
                    f"terminated must be a bool tensor of shape {(*lead, N)}, got {term.dtype} "
                    f"{tuple(term.shape)}"
                )
        return s, a, R, s_next, term

    @torch.no_grad()
    def update(
        self,
        states: Tensor,
        actions: Tensor,
        rewards: Tensor,
        next_states: Tensor,
        terminated: Tensor | None = None,
        *,
        epsilon: float | None = None,
    ) -> dict[str, Any]:
        """One policy update from transitions sampled with it; raising changes nothing.

        Args:
            states: (N, C) states where the decisions were taken.
            actions: (N, A) actions taken.
            rewards: (N,) reward of each decision (exactly (N,): (N, 1) is refused).
            next_states: (N, C) states reached (before any restart).
            terminated: optional (N,) bool, ended in a terminal state: the next state's
                features are then phi_hat_0 (a sure restart).
            epsilon: this update's KL bound (a schedule's value); None: ``self.epsilon``.

        Returns:
            Diagnostics: as :meth:`EpisodicHiREPS.tell`'s, with ``mean_reward`` for
            ``mean_return, max_return``.
        """
        eps = self.epsilon if epsilon is None else check_positive_float("epsilon", epsilon)
        s, a, R, s_next, term = self._transitions(states, actions, rewards, next_states, terminated)
        next_features = self.value_features(s_next)
        if term is not None:
            phi0 = self.initial_features.unsqueeze(-2)  # ([S,] 1, F)
            next_features = torch.where(term[..., None], phi0, next_features)
        (bound,), lr, kappa = option_bounds(
            self.policies, s[..., None, :], a[..., None, :], self.kappa_rel
        )
        lead, N = R.shape[:-1], R.shape[-1]
        warn_if_degenerate([eps], N, 3)
        R1 = R.reshape(-1, N)  # the dual's S problems (1 for one run)
        phi = self.value_features(s).to(R).reshape(*R1.shape, -1)
        next_features = next_features.to(R).reshape(phi.shape)
        check_finite("value features", phi)
        check_finite("value features of next_states", next_features)
        sol = infinite_horizon_solution(
            R1,
            lr[:, :, 0],
            R.new_full((R1.shape[0], 1), eps),
            phi,
            next_features,
            self.initial_features.to(R).expand(*lead, -1).reshape(R1.shape[0], -1),
            self.gamma,
            kappa,
            LbfgsSettings(),  # the wrapper's defaults
            seeds=self.seeds,
        )
        refit = plan_refit(self.policy, s, a, sol, bound)
        self.value_weights = sol.v.reshape(*lead, -1).clone()
        report = apply_refit(self.policy, s, refit, self.prune_threshold)
        self.iteration += 1
        return {
            "iteration": per_member(self.iteration, lead),
            **report,
            "mean_reward": reduce_each(R, "mean", -1).tolist(),
        }

    # ---- the shared interface (Algorithm) ---------------------------------------------------
    def _states(self, states: Tensor, name: str = "states", *, population: bool = True) -> Tensor:
        """Checked float64 states ([S,] N, C) (no S when ``population`` is False)."""
        lead = self.policy.batch_shape if population else ()
        return checked_states(states, name, lead, self.value_features.in_features, self.device)

    def learn(self, experience: Experience) -> dict[str, Any]:
        """:meth:`update` from an :class:`Experience` with K = 1."""
        e = self._experience(experience, transitions=True)
        assert e.next_states is not None  # checked there
        term = None if e.terminated is None else e.terminated[..., 0]
        return self.update(
            e.states[..., 0, :],
            e.actions[..., 0, :],
            e.rewards[..., 0],
            e.next_states[..., 0, :],
            term,
        )

    # ---- checkpointing ----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the run bit-for-bit, as a copy (later updates leave it
        as it is)."""
        return self._state(
            policy=self.policy.state_dict(),
            value_weights=self.value_weights,
            gamma=self.gamma,
            epsilon=self.epsilon,
        )

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output (no generator: keep it); a misfit changes nothing."""
        state = self._keys_checked(state, "policy", "value_weights", "gamma", "epsilon")
        self.policy.check_state_dict(state["policy"])
        v = check_saved_values(state["value_weights"], self.value_weights)
        gamma = check_gamma(state["gamma"])
        epsilon = check_positive_float("epsilon", state["epsilon"])
        self._load_shared(state)
        self.policy.load_state_dict(state["policy"])
        self.value_weights, self.gamma, self.epsilon = v, gamma, epsilon
