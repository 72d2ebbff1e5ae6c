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
from typing import Any

import torch
from torch import Tensor

from hireps_torch.checks import as_finite_f64
from hireps_torch.algorithms._options import option_bound, refit_and_report
from hireps_torch.dual import solve_infinite_horizon_dual
from hireps_torch.features import FeatureMap
from hireps_torch.policies import HierarchicalPolicy

__all__ = ["InfiniteHorizonHiREPS"]


class InfiniteHorizonHiREPS:
    """Infinite-horizon HiREPS over transitions of a restart process.

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
    ) -> None:
        if not (math.isfinite(epsilon) and epsilon > 0):
            raise ValueError(f"epsilon must be finite and > 0, got {epsilon}")
        if not (math.isfinite(gamma) and 0.0 < gamma < 1.0):
            raise ValueError(f"gamma must be in (0, 1), got {gamma}")
        if kappa_rel is not None and not (math.isfinite(kappa_rel) and kappa_rel >= 0):
            raise ValueError(f"kappa_rel must be finite and >= 0 (or None), got {kappa_rel}")
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
        self.epsilon = float(epsilon)
        self.kappa_rel = None if kappa_rel is None else float(kappa_rel)
        self.prune_threshold = float(prune_threshold)
        self.iteration = 0
        self.value_weights = torch.zeros(value_features.out_features, dtype=torch.float64)

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

    # ---- checkpointing ----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "policy": self.policy.state_dict(),
            "value_weights": self.value_weights.clone(),
            "iteration": self.iteration,
            "gamma": self.gamma,
            "epsilon": self.epsilon,
            "kappa_rel": self.kappa_rel,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.value_weights = state["value_weights"].clone()
        self.iteration = int(state["iteration"])
        self.gamma = float(state["gamma"])
        self.epsilon = float(state["epsilon"])
        self.kappa_rel = state["kappa_rel"]
