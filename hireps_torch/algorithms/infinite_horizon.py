"""Infinite-horizon HiREPS: a stationary state-action-option distribution under restarts.

Each iteration (Daniel, Neumann & Peters, "Hierarchical Relative Entropy Policy Search",
infinite-horizon formulation):

1. the hierarchical policy pi(a | s) = sum_o pi(o | s) pi(a | s, o) acts in the restart process
   (with probability 1 - gamma per decision the system restarts from the start distribution);
   each sample is one decision: (s_i, a_i, r_i, s'_i);
2. responsibilities p~_io = p(o | s_i, a_i) of the sampling policy and the entropy bound
   kappa = kappa_rel * mean_i H[p~_i.];
3. the dual (:func:`hireps_torch.dual.solve_infinite_horizon_dual`)

       P_io ∝ p~_io^(1 + xi/eta) exp((r_i + gamma v^T phi(s'_i) - v^T phi(s_i)) / eta)

   with KL(P || q p~) = epsilon, E_P[-log p~] <= kappa and the stationarity constraint
   sum_i w_i (phi(s_i) - gamma phi(s'_i)) = (1 - gamma) phi_hat_0 on the value features phi;
4. weighted maximum-likelihood refit of gating and options with the weights P
   (:meth:`HierarchicalPolicy.weighted_fit`), then pruning;
5. diagnostics: eta, xi, kappa, realised KL, cross-entropy, effective sample size, entropies.

One option and ``kappa_rel=None`` give infinite-horizon REPS (Peters et al. 2010).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from hireps_torch.algorithms._options import option_bound, refit_and_report
from hireps_torch.algorithms.base import (
    Experience,
    HiREPSBase,
    PolicyKwargs,
    check_experience,
    check_step,
    fresh_policies,
)
from hireps_torch.checks import as_finite_f64, check_positive_float
from hireps_torch.dual import solve_infinite_horizon_dual
from hireps_torch.features import FeatureMap
from hireps_torch.policies import HierarchicalPolicy

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["InfiniteHorizonHiREPS"]


class InfiniteHorizonHiREPS(HiREPSBase):
    """Infinite-horizon HiREPS over transitions of a restart process (and the shared
    :class:`~hireps_torch.algorithms.Algorithm` interface: one decision step, K = 1).

    Example::

        algo = InfiniteHorizonHiREPS(policy, FourierFeatures(low, high), start_states,
                                     gamma=0.996, epsilon=0.5)
        diagnostics = algo.update(states, actions, rewards, next_states)

    Args:
        policy: the hierarchical policy (updated in place); its context is the state.
        value_features: features phi(s) of the value function (e.g. :class:`FourierFeatures`).
        initial_states: (M, S) draws from the start distribution; phi_hat_0 is their mean
            feature vector.
        gamma: 1 - restart probability per decision, in (0, 1).
        epsilon: KL bound per iteration, > 0.
        kappa_rel: entropy bound as a fraction of the current mean option entropy; None: off.
        prune_threshold: options whose prior mass falls below this are pruned (0: never).
        seed: seed of the generator of :meth:`sample` (None: 0). The update draws nothing.
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
        seed: int | None = None,
    ) -> None:
        self.epsilon = check_positive_float("epsilon", epsilon)
        if not (math.isfinite(gamma) and 0.0 < gamma < 1.0):
            raise ValueError(f"gamma must be in (0, 1), got {gamma}")
        super().__init__(kappa_rel=kappa_rel, prune_threshold=prune_threshold, seed=seed)
        s0 = torch.as_tensor(initial_states, dtype=torch.float64)
        if s0.dim() != 2 or s0.shape[1] != value_features.in_features or s0.shape[0] < 1:
            raise ValueError(
                f"initial_states must have shape (M, {value_features.in_features}), got "
                f"{tuple(s0.shape)}"
            )
        self.policy = policy
        self.value_features = value_features
        self.initial_features = value_features(s0).mean(0)
        self.gamma = float(gamma)
        self.value_weights = torch.zeros(value_features.out_features, dtype=torch.float64)

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
        seed: int | None = None,
        **policy_kwargs: Unpack[PolicyKwargs],
    ) -> InfiniteHorizonHiREPS:
        """Build the algorithm with a fresh softmax-gated mixture of linear-Gaussian options.

        The gating sees the squared expansion of the state by default, the options the state
        itself (linear options). Option means start at ``init_mean + spread * init_std *
        randn`` (see :meth:`HierarchicalPolicy.create`).

        Args:
            state_dim: S, >= 1.
            action_dim: A.
            value_features: features phi(s) of the value function, ``in_features = S``.
            initial_states: (M, S) draws from the start distribution.
            gamma: 1 - restart probability per decision, in (0, 1).
            n_options: O.
            init_mean: (A,) or (O, A) initial option means; zeros by default.
            epsilon: KL bound.
            kappa_rel: relative entropy bound (None: off).
            prune_threshold: prior mass below which options are pruned (0: never).
            seed: seeds the initial option means (and, as seed + 1, the sampling generator).
            **policy_kwargs: ``init_std, spread, gating_features, policy_features,
                min_variance, covariance_prior`` (see
                :class:`~hireps_torch.algorithms.base.PolicyKwargs`).
        """
        if state_dim < 1:
            raise ValueError(f"state_dim must be >= 1, got {state_dim}")
        if value_features.in_features != state_dim:
            raise ValueError(
                f"value_features take states of dimension {value_features.in_features}, "
                f"not state_dim = {state_dim}"
            )
        (policy,) = fresh_policies(
            [init_mean], n_options, state_dim, action_dim, seed, **policy_kwargs
        )
        return cls(
            policy,
            value_features,
            initial_states,
            gamma=gamma,
            epsilon=epsilon,
            kappa_rel=kappa_rel,
            prune_threshold=prune_threshold,
            seed=None if seed is None else int(seed) + 1,
        )

    def value(self, states: Tensor) -> Tensor:
        """Current value estimate v^T phi(s) (from the last dual solve): (N, S) -> (N,)."""
        return self.value_features(torch.as_tensor(states, dtype=torch.float64)) @ (
            self.value_weights
        )

    @torch.no_grad()
    def update(
        self,
        states: Tensor,
        actions: Tensor,
        rewards: Tensor,
        next_states: Tensor,
        terminated: Tensor | None = None,
    ) -> dict[str, Any]:
        """One policy update from transitions sampled with the current policy.

        Args:
            states: (N, S) states where the decisions were taken.
            actions: (N, A) actions taken.
            rewards: (N,) reward of each decision.
            next_states: (N, S) states reached (before any restart).
            terminated: optional (N,) bool, the decision ended the episode in a terminal state
                (e.g. a ball that fell off). The process then restarts for sure, so the next
                state's expected features are those of the start distribution, phi_hat_0,
                in the Bellman error and the stationarity constraint.

        Returns:
            Diagnostics: ``eta, xi, kappa, kl, cross_entropy, effective_sample_size,
            option_entropy, policy_entropy, n_active_options, pruned, mean_reward,
            feature_error, dual_converged, dual_iterations, iteration``.
        """
        R = torch.as_tensor(rewards, dtype=torch.float64).reshape(-1)
        N = R.shape[0]
        S = self.value_features.in_features
        s = as_finite_f64("states", states, (N, S))
        s_next = as_finite_f64("next_states", next_states, (N, S))
        a = as_finite_f64("actions", actions, (N, self.policy.action_dim))

        next_features = self.value_features(s_next)
        if terminated is not None:
            term = torch.as_tensor(terminated).reshape(-1)
            if term.shape != (N,) or term.dtype != torch.bool:
                raise ValueError(
                    f"terminated must be a bool tensor of shape ({N},), got {term.dtype} "
                    f"{tuple(term.shape)}"
                )
            next_features = torch.where(term[:, None], self.initial_features, next_features)
        bound = option_bound(self.policy, s, a, self.kappa_rel)
        sol = solve_infinite_horizon_dual(
            R,
            self.value_features(s),
            next_features,
            self.initial_features,
            gamma=self.gamma,
            epsilon=self.epsilon,
            log_responsibilities=bound.log_responsibilities,
            kappa=bound.kappa,
        )
        self.value_weights = sol.v.clone()
        report = refit_and_report(self.policy, s, a, sol, bound, self.prune_threshold)
        self.iteration += 1
        return {"iteration": self.iteration, **report, "mean_reward": float(R.mean())}

    # ---- the shared interface (Algorithm) ---------------------------------------------------
    @property
    def policies(self) -> tuple[HierarchicalPolicy]:
        """The one policy, as the interface's one-entry sequence."""
        return (self.policy,)

    def _states(self, states: Tensor) -> Tensor:
        S = self.value_features.in_features
        s = torch.as_tensor(states, dtype=torch.float64)
        if s.dim() != 2 or s.shape[1] != S:
            raise ValueError(f"states must have shape (N, {S}), got {tuple(s.shape)}")
        return as_finite_f64("states", s)

    @torch.no_grad()
    def sample(self, states: Tensor, step: int = 0) -> Tensor:
        """Exploring actions (N, A) for states (N, S), drawn with the algorithm's generator;
        ``step`` must be 0."""
        check_step(step, 1)
        return self.policy.sample(self._states(states), self.generator)[0]

    @torch.no_grad()
    def mean_action(self, states: Tensor, step: int = 0) -> Tensor:
        """Noise-free actions (N, A) (mean of the most probable option); ``step`` must be 0."""
        check_step(step, 1)
        return self.policy.mean_action(self._states(states))[0]

    def learn(self, experience: Experience) -> dict[str, Any]:
        """:meth:`update` from decisions: states, next_states (N, 1, S), actions (N, 1, A),
        rewards (N, 1) and optionally terminated (N, 1)."""
        S, A = self.value_features.in_features, self.policy.action_dim
        name = type(self).__name__
        check_experience(experience, 1, S, A, transitions=True, algorithm=name)
        e = experience
        assert e.next_states is not None  # checked above
        term = None if e.terminated is None else e.terminated[:, 0]
        return self.update(
            e.states[:, 0], e.actions[:, 0], e.rewards[:, 0], e.next_states[:, 0], term
        )

    # ---- checkpointing ----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the run bit-for-bit."""
        return self._state(
            policy=self.policy.state_dict(),
            value_weights=self.value_weights.clone(),
            gamma=self.gamma,
            epsilon=self.epsilon,
        )

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.value_weights = state["value_weights"].clone()
        self._load_state(state)
        self.gamma = float(state["gamma"])
        self.epsilon = float(state["epsilon"])
