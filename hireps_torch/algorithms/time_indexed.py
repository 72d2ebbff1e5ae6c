"""Time-indexed HiREPS (Daniel, Neumann & Peters): one policy per decision step k = 0..K-1.

The dual (:func:`hireps_torch.dual.solve_time_indexed_dual`) gives per-step weights

    P_k,io ∝ p~_k,io^(1 + xi_k/eta_k) exp(delta_k,i / eta_k),
    delta_k,i = R_k,i + v_{k+1}^T phi(s_{k+1,i}) - v_k^T phi(s_k,i),    V_K = 0,

with KL(P_k || q p~_k) = epsilon_k, E_P_k[-log p~_k] <= kappa_k and the state distributions
chained through the value features phi; each step's policy is then refitted and pruned.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Unpack

import torch
from torch import Tensor

from hireps_torch.algorithms._options import (
    apply_refit,
    each,
    option_bounds,
    per_member,
    plan_refit,
)
from hireps_torch.algorithms.base import (
    Experience,
    HiREPSBase,
    PolicyKwargs,
    check_epsilons,
    check_saved_values,
    check_step,
    checked_states,
    member_policies,
)
from hireps_torch.checks import (
    FIX_SAMPLES,
    as_checked,
    as_float_tensor,
    check_count,
    check_finite,
)
from hireps_torch.dual.inputs import warn_if_degenerate
from hireps_torch.dual.solver import LbfgsSettings
from hireps_torch.dual.time_indexed import time_indexed_solution
from hireps_torch.features import FeatureMap, QuadraticFeatures, check_feature_map
from hireps_torch.policies import HierarchicalPolicy

__all__ = ["TimeIndexedHiREPS"]

_PER_STEP = (  # diagnostics that tell() reports as one entry per step
    "eta xi kappa kl cross_entropy effective_sample_size option_entropy policy_entropy "
    "n_active_options pruned refitted"
).split()


class TimeIndexedHiREPS(HiREPSBase):
    """Time-indexed HiREPS, ask/tell and :class:`~hireps_torch.algorithms.Algorithm` (K steps).

    Example (K = 3 shots, 2-D state, 14 parameters per shot)::

        algo = TimeIndexedHiREPS.create(3, param_dim=14, context_dim=2, n_options=5, seed=0)
        for k in range(3):  # s (N, 3, 2): s[:, k + 1] is where theta[:, k] led
            theta[:, k] = algo.ask(k, s[:, k])  # then run it: s[:, k + 1], r[:, k]
        diagnostics = algo.tell(s, theta, r)  # r (N, 3)

    Args:
        policies: K hierarchical policies of the state, policy k acting at step k (updated in
            place), sharing the parameter dimension D.
        value_features: features phi(s) of V_k(s) = v_k^T phi(s); ``in_features`` = C.
        epsilon: KL bound per iteration, > 0: one float or K floats.
        kappa_rel: each step's entropy bound as a fraction of its current mean option entropy
            (0.8-0.9 in the paper); None disables the bound.
        prune_threshold: options whose prior mass falls below this are pruned (0: never).
        seed: seed of the sampling generator.

    ``tell`` / ``learn`` and ``load_state_dict`` either complete or raise and change nothing.
    """

    def __init__(
        self,
        policies: Sequence[HierarchicalPolicy],
        value_features: FeatureMap,
        *,
        epsilon: float | Sequence[float] = 1.0,
        kappa_rel: float | None = 0.9,
        prune_threshold: float = 1e-4,
        seed: int | Sequence[int] | None = None,
    ) -> None:
        if not isinstance(policies, Sequence) or isinstance(policies, str):
            raise TypeError(
                f"policies must be a sequence of K HierarchicalPolicy (one per decision step), "
                f"got {type(policies).__name__}"
            )
        K = len(policies)
        if K < 1:
            raise ValueError("policies must hold one policy per decision step (K >= 1), got 0")
        eps = check_epsilons(epsilon, K)
        sizes = [getattr(pol, "population", None) for pol in policies]
        if len(set(sizes)) != 1:
            raise ValueError(
                f"the policies must all be populations of one size or all single, got {sizes}"
            )
        super().__init__(
            kappa_rel=kappa_rel, prune_threshold=prune_threshold, seed=seed, population=sizes[0]
        )
        if check_feature_map("value_features", value_features) is None:
            raise TypeError("value_features must be a feature map (e.g. QuadraticFeatures)")
        C = value_features.in_features
        for k, pol in enumerate(policies):
            if not isinstance(pol, HierarchicalPolicy):
                raise TypeError(
                    f"policy {k} must be a HierarchicalPolicy, got {type(pol).__name__}"
                )
            dims = (pol.gating_features.in_features, pol.policy_features.in_features)
            if dims != (C, C):
                raise ValueError(
                    f"policy {k} sees states of dimension {dims} (gating, options) but the value "
                    f"features take C = {C}"
                )
        if len({pol.action_dim for pol in policies}) != 1:
            raise ValueError(
                f"all policies must share the parameter dimension, got "
                f"{[pol.action_dim for pol in policies]}"
            )
        self.policies = list(policies)
        self.value_features = value_features
        self.epsilon = eps
        self.value_weights = torch.zeros(
            *policies[0].batch_shape, K, value_features.out_features, dtype=torch.float64
        )
        self.to(self.device)  # every step's policy and the value features where step 0's is

    @classmethod
    def create(
        cls,
        K: int,
        param_dim: int,
        context_dim: int,
        *,
        n_options: int = 5,
        init_mean: Tensor | None = None,
        epsilon: float | Sequence[float] = 1.0,
        kappa_rel: float | None = 0.9,
        value_features: FeatureMap | None = None,
        prune_threshold: float = 1e-4,
        seed: int | Sequence[int] | None = None,
        population: int | None = None,
        **policy_kwargs: Unpack[PolicyKwargs],
    ) -> TimeIndexedHiREPS:
        """Build K fresh softmax-gated mixtures of linear-Gaussian options, one per step.

        Args:
            K: number of decision steps, >= 1.
            param_dim: D, parameters per decision.
            context_dim: C, the state dimension, >= 1.
            n_options: options per step.
            init_mean: (D,) shared by all steps or (K, D) per step; zeros by default.
            epsilon: KL bound, one float or K floats.
            kappa_rel: relative entropy bound (None: off).
            value_features: value features phi (default: the squared expansion of the state).
            prune_threshold: prior mass below which options are pruned (0: never).
            seed: seeds the initial option means (None: 0) and, by its "sampling" ``stream_seed``,
                the sampling generator; a sequence of S distinct seeds builds a population.
            population: S independent runs (see :meth:`EpisodicHiREPS.create`).
            **policy_kwargs: see :class:`~hireps_torch.algorithms.base.PolicyKwargs`.
        """
        K = check_count("K (the number of decision steps)", K, 1)
        context_dim = check_count("context_dim (the state dimension)", context_dim, 1)
        param_dim = check_count("param_dim", param_dim, 1)
        mean = torch.zeros(K, param_dim, dtype=torch.float64)
        if init_mean is not None:
            m = as_float_tensor("init_mean", init_mean)
            if m.shape not in ((param_dim,), (K, param_dim)):
                raise ValueError(
                    f"init_mean must have shape (D,) = ({param_dim},) or (K, D) = "
                    f"({K}, {param_dim}), got {tuple(m.shape)}"
                )
            mean = mean + m
        policies, sampling, seeds = member_policies(
            seed, population, list(mean), n_options, context_dim, param_dim, **policy_kwargs
        )
        algo = cls(
            policies,
            QuadraticFeatures(context_dim) if value_features is None else value_features,
            epsilon=epsilon,
            kappa_rel=kappa_rel,
            prune_threshold=prune_threshold,
            seed=sampling,
        )
        algo.seeds = seeds
        return algo

    @property
    def n_steps(self) -> int:
        """K, the number of decision steps."""
        return len(self.policies)

    # ---- input handling ---------------------------------------------------------------------
    def _states(self, states: Tensor) -> Tensor:
        """States ([S,] N, C) at one step, N >= 1, as checked float64."""
        C, lead = self.value_features.in_features, self.policies[0].batch_shape
        return checked_states(states, "contexts", lead, C, self.device, squeeze=True)

    def _episodes(
        self, states: Tensor, params: Tensor, rewards: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Checked float64 states ([S,] N, K, C), params ([S,] N, K, D), rewards ([S,] N, K)."""
        K = self.n_steps
        lead = self.policies[0].batch_shape
        names = "(population, N, K) = " if lead else "(N, K) = "
        shape, dev = (*lead, None, K), self.device
        R = as_checked("rewards", rewards, shape, device=dev, advice=FIX_SAMPLES, names=names)
        N = R.shape[-2]
        if N < 2:
            raise ValueError(f"the dual needs at least 2 samples, got N = {N}")
        C, D = self.value_features.in_features, self.policies[0].action_dim
        s = as_checked("states", states, (*lead, N, K, C), device=dev)
        theta = as_checked("params", params, (*lead, N, K, D), device=dev)
        return s, theta, R

    # ---- ask / tell -------------------------------------------------------------------------
    def ask(self, step: int, contexts: Tensor) -> Tensor:
        """Sample one parameter vector per state from step ``step``'s policy.

        Args:
            step: decision step k in [0, K).
            contexts: (N, C) states at that step.

        Returns:
            theta: (N, D) float64.
        """
        return self.sample(contexts, step)

    def act(self, step: int, contexts: Tensor) -> Tensor:
        """Noise-free policy of step ``step`` (mean of the most probable option): (N, D)."""
        return self.mean_action(contexts, step)

    def value(self, step: int, contexts: Tensor) -> Tensor:
        """V_k(s) = v_k^T phi(s) from the last update, up to a constant: (N, C) -> (N,)."""
        k = check_step(step, self.n_steps)
        phi = self.value_features(self._states(contexts))
        return (phi @ self.value_weights[..., k, :, None])[..., 0]

    @torch.no_grad()
    def tell(self, states: Tensor, params: Tensor, rewards: Tensor) -> dict[str, Any]:
        """Update every step's policy from N episodes drawn with it; raising changes nothing.

        Args:
            states: (N, K, C) state at each decision step (s_{k+1} is where decision k led).
            params: (N, K, D) parameters returned by :meth:`ask` at each step.
            rewards: (N, K) reward of each decision (higher is better).

        Returns:
            Diagnostics: lists of K ``eta, xi, kappa, kl, cross_entropy,
            effective_sample_size, option_entropy, policy_entropy, n_active_options, pruned,
            refitted, mean_rewards``; scalars ``feature_error, dual_converged,
            dual_iterations, mean_return`` (of the summed rewards), ``max_return, iteration``;
            ``kappa`` is NaN where the entropy bound is off; ``policy_entropy`` as in
            :meth:`EpisodicHiREPS.tell`.
        """
        s, theta, R = self._episodes(states, params, rewards)
        lead, (N, K) = R.shape[:-2], R.shape[-2:]
        bounds, lr, kappa = option_bounds(self.policies, s, theta, self.kappa_rel)
        warn_if_degenerate(self.epsilon, N, 3)
        phi = self.value_features(s).to(R)  # ([S,] N, K, F)
        check_finite("value features", phi)
        S = lr.shape[0]  # the dual's problems (1 for one run)
        sol = time_indexed_solution(
            R.reshape(S, N, K).transpose(1, 2),
            lr.transpose(1, 2),
            R.new_tensor(self.epsilon).expand(S, K),
            phi.reshape(S, N, K, -1).transpose(1, 2),
            None,
            kappa,
            LbfgsSettings(),  # the wrapper's defaults
            seeds=self.seeds,
        )
        refits = [  # every step's refit first: a failing step leaves all policies unchanged
            plan_refit(pol, s[..., k, :], theta[..., k, :], sol, bounds[k], block=k)
            for k, pol in enumerate(self.policies)
        ]
        self.value_weights = sol.v.reshape(*lead, K, -1).clone()
        reports = [
            apply_refit(pol, s[..., k, :], refit, self.prune_threshold)
            for k, (pol, refit) in enumerate(zip(self.policies, refits, strict=True))
        ]
        self.iteration += 1
        returns = R.sum(-1)
        per_step = {key: [r[key] for r in reports] for key in _PER_STEP}
        if lead:  # member s's entries: one per step
            per_step = {key: [list(x) for x in zip(*v, strict=True)] for key, v in per_step.items()}
        mean_return, max_return = torch.stack([returns.mean(-1), returns.amax(-1)]).tolist()
        return {
            "iteration": per_member(self.iteration, lead),
            **per_step,
            "feature_error": sol.feature_error.reshape(lead).tolist(),
            "dual_converged": each(sol.converged.reshape(lead).tolist(), bool),
            "dual_iterations": sol.iterations.reshape(lead).tolist(),
            "mean_rewards": R.mean(-2).tolist(),
            "mean_return": mean_return,
            "max_return": max_return,
        }

    # ---- the shared interface (Algorithm) ---------------------------------------------------
    def learn(self, experience: Experience) -> dict[str, Any]:
        """:meth:`tell` from states (N, K, C), parameters (N, K, D) and rewards (N, K)."""
        e = self._experience(experience)
        return self.tell(e.states, e.actions, e.rewards)

    # ---- checkpointing ----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the run bit-for-bit, as a copy (later updates leave it
        as it is)."""
        return self._state(
            policies=[pol.state_dict() for pol in self.policies],
            value_weights=self.value_weights,
            epsilon=list(self.epsilon),
        )

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; one that does not fit raises, changing nothing."""
        state = self._keys_checked(state, "policies", "value_weights", "epsilon")
        saved = state["policies"]
        if not isinstance(saved, Sequence) or len(saved) != self.n_steps:
            n = len(saved) if isinstance(saved, Sequence) else type(saved).__name__
            raise ValueError(
                f"the state holds {n} policies, this algorithm has K = {self.n_steps} steps"
            )
        for k, (pol, sd) in enumerate(zip(self.policies, saved, strict=True)):
            try:
                pol.check_state_dict(sd)
            except ValueError as exc:
                raise ValueError(f"step {k}: {exc}") from None
        v = check_saved_values(state["value_weights"], self.value_weights)
        epsilon = check_epsilons(state["epsilon"], self.n_steps)
        self._load_shared(state)
        for pol, sd in zip(self.policies, saved, strict=True):
            pol.load_state_dict(sd)
        self.value_weights, self.epsilon = v, epsilon
