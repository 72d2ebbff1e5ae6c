"""Episodic / contextual HiREPS (Daniel, Neumann & Peters), and REPS as its one-option case.

Per iteration: ``ask`` N parameters theta_i ~ pi(theta | s_i); ``tell`` their returns R_i; the
dual (:func:`hireps_torch.dual.solve_episodic_dual`) gives

    P_io ∝ p~_io^(1 + xi/eta) exp((R_i - v^T phi(s_i)) / eta)

with KL(P || q p~) = epsilon, E_P[-log p~] <= kappa and the context features phi matched; then
the weighted maximum-likelihood refit and pruning.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Self, Unpack

import torch
from torch import Tensor

from hireps_torch.algorithms._options import apply_refit, option_bounds, per_member, plan_refit
from hireps_torch.algorithms.base import (
    Experience,
    HiREPSBase,
    PolicyKwargs,
    checked_states,
    member_policies,
)
from hireps_torch.checks import (
    as_float_tensor,
    check_count,
    check_finite,
    check_nonnegative_float,
    check_positive_float,
)
from hireps_torch.dual.episodic import episodic_solution
from hireps_torch.dual.inputs import warn_if_degenerate
from hireps_torch.dual.solutions import DualSolution
from hireps_torch.dual.solver import LbfgsSettings
from hireps_torch.dual.versatile import entropy_floor_solution
from hireps_torch.features import FeatureMap, QuadraticFeatures, check_feature_map
from hireps_torch.policies import HierarchicalPolicy

__all__ = ["REPS", "EpisodicHiREPS"]


class EpisodicHiREPS(HiREPSBase):
    """Episodic HiREPS: ask/tell and :class:`~hireps_torch.algorithms.Algorithm` (K = 1).

    Example (no context)::

        algo = EpisodicHiREPS.create(param_dim=2, n_options=10, init_std=2.0, seed=0)
        for _ in range(50):
            theta = algo.ask(50)                    # (50, 2)
            diagnostics = algo.tell(None, theta, objective(theta))

    Args:
        policy: the hierarchical policy to improve (updated in place).
        epsilon: KL bound per iteration, > 0.
        kappa_rel: entropy bound as a fraction of the current mean option entropy of the
            responsibilities (0.8-0.9 in the paper); None disables the bound (xi = 0).
        context_dim: C (0: no context).
        context_features: features whose expectation the dual keeps (default: the squared
            expansion of the context).
        prune_threshold: options whose prior mass falls below this are pruned.
        seed: seed of the sampling generator.
        prior_entropy_floor: delta in [0, 1] (None: off, the paper's HiREPS): the new options'
            prior keeps an entropy of at least ``delta log O`` (O the options built; at most
            ``log(active options) - 0.05``; lowered towards the ordinary update's entropy where
            the other bounds leave it out of reach: :mod:`hireps_torch.dual.versatile`);
            ``tell`` then also reports ``lambda``, ``prior_entropy`` and ``entropy_floor``.

    ``tell`` and ``load_state_dict`` either complete or raise and change nothing.
    """

    def __init__(
        self,
        policy: HierarchicalPolicy,
        *,
        epsilon: float = 1.0,
        kappa_rel: float | None = 0.9,
        context_dim: int = 0,
        context_features: FeatureMap | None = None,
        prune_threshold: float = 1e-4,
        seed: int | Sequence[int] | None = None,
        prior_entropy_floor: float | None = None,
    ) -> None:
        self.epsilon = check_positive_float("epsilon", epsilon)
        if prior_entropy_floor is not None:
            floor = check_nonnegative_float("prior_entropy_floor", prior_entropy_floor)
            if floor > 1:
                raise ValueError(f"prior_entropy_floor must be in [0, 1], got {floor}")
        self.prior_entropy_floor = prior_entropy_floor
        super().__init__(policy, kappa_rel=kappa_rel, prune_threshold=prune_threshold, seed=seed)
        context_dim = check_count("context_dim", context_dim, 0)
        if policy.context_dim != context_dim:
            raise ValueError(
                f"the policy takes contexts of dimension {policy.context_dim} but context_dim = "
                f"{context_dim}"
            )
        check_feature_map("context_features", context_features)
        if context_features is not None and context_features.in_features != context_dim:
            raise ValueError(
                f"context_features take contexts of dimension {context_features.in_features}, "
                f"not context_dim = {context_dim}"
            )
        self.context_dim = context_dim
        self.context_features = context_features or (
            QuadraticFeatures(context_dim) if context_dim > 0 else None
        )
        self.to(self.device)  # the feature maps where the policy is

    @classmethod
    def create(
        cls,
        param_dim: int,
        *,
        context_dim: int = 0,
        n_options: int = 5,
        init_mean: Tensor | None = None,
        epsilon: float = 1.0,
        kappa_rel: float | None = 0.9,
        prune_threshold: float = 1e-4,
        seed: int | Sequence[int] | None = None,
        population: int | None = None,
        prior_entropy_floor: float | None = None,
        **policy_kwargs: Unpack[PolicyKwargs],
    ) -> Self:
        """Build the algorithm with a fresh softmax-gated mixture of linear-Gaussian options.

        Args:
            param_dim: D.
            context_dim: C (0: no context).
            n_options: O.
            init_mean: (D,) or (O, D) initial option means; zeros by default.
            epsilon: KL bound.
            kappa_rel: relative entropy bound (None: off).
            prune_threshold: prior mass below which options are pruned (0: never).
            seed: seeds the initial option means (None: 0) and, by its "sampling" ``stream_seed``,
                the sampling generator; a sequence of S distinct seeds builds a population.
            population: S independent runs in one algorithm (default seeds 0 .. S-1): every
                input and output gains a leading S, diagnostics one entry per member; member
                s draws and learns what it would alone (to round-off).
            prior_entropy_floor: see the class docstring (None: off).
            **policy_kwargs: see :class:`~hireps_torch.algorithms.base.PolicyKwargs`.
        """
        param_dim = check_count("param_dim", param_dim, 1)
        policy, sampling, seeds = member_policies(
            seed, population, [init_mean], n_options, context_dim, param_dim, **policy_kwargs
        )
        algo = cls(
            policy[0],
            epsilon=epsilon,
            kappa_rel=kappa_rel,
            prune_threshold=prune_threshold,
            context_dim=context_dim,
            seed=sampling,
            prior_entropy_floor=prior_entropy_floor,
        )
        algo.seeds = seeds
        return algo

    # ---- input handling ---------------------------------------------------------------------
    def _states(self, contexts: Tensor | int | None, n: int | None = None) -> Tensor:
        """Checked float64 contexts ([S,] N, C); a count / None (``n`` samples) without context."""
        if _is_count(contexts):
            if self.context_dim > 0:
                raise ValueError(
                    f"this algorithm is contextual (context_dim = {self.context_dim}): pass a "
                    f"(N, {self.context_dim}) tensor of contexts, got {contexts!r}"
                )
            count = n if contexts is None else check_count("the number of samples", contexts, 1)
            if count is None:
                raise ValueError("without context, pass the number of samples N >= 1, got None")
            if count < 1:
                raise ValueError(f"the number of samples must be >= 1, got {count}")
            if count >= 2**63:  # torch's sizes are int64
                raise ValueError(f"the number of samples must be below 2**63, got {count}")
            shape = (*self.policy.batch_shape, count, 0)
            return torch.zeros(shape, dtype=torch.float64, device=self.device)
        lead, C = self.policy.batch_shape, self.context_dim
        hint = " (this algorithm has no context: pass the number of samples, or None to tell)"
        hint = hint if C == 0 else ""
        return checked_states(
            contexts, "contexts", lead, C, self.device, noun="context", hint=hint, squeeze=True
        )

    def _samples(
        self, contexts: Tensor | int | None, params: Tensor, returns: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Checked float64 contexts ([S,] N, C), params ([S,] N, D) and returns ([S,] N)."""
        lead, D = self.policy.batch_shape, self.policy.action_dim
        dev = self.device
        theta = as_float_tensor("params", params, device=dev)
        R = as_float_tensor("returns", returns, device=dev)
        if R.dim() != 1 + len(lead) or R.shape[:-1] != lead:
            n = f"({theta.shape[-2]},)" if theta.dim() == 2 else "(N,)"
            if lead:
                n = f"(S, N) = ({lead[0]}, N)"
            raise ValueError(
                f"returns must have shape {n} (one return per row of params "
                f"{tuple(theta.shape)}), got {tuple(R.shape)}"
            )
        N = R.shape[-1]
        if theta.shape != (*lead, N, D):
            raise ValueError(
                f"params must have shape {(*lead, N, D)} to match returns {tuple(R.shape)}, got "
                f"{tuple(theta.shape)}"
            )
        if not math.isfinite(float(R.sum()) + float(theta.sum())):  # else: which one?
            check_finite("returns", R)
            check_finite("params", theta)
        c = self._states(contexts, n=N)
        if c.shape[-2] != N:
            raise ValueError(f"got {c.shape[-2]} contexts for {N} params and returns")
        if N < 2:
            raise ValueError(f"the dual needs at least 2 samples, got N = {N}")
        return c, theta, R

    # ---- ask / tell -------------------------------------------------------------------------
    def ask(self, contexts: Tensor | int | None) -> Tensor:
        """Sample one parameter vector per context.

        Args:
            contexts: (N, C), or the count N >= 1 without context.

        Returns:
            theta: (N, D) float64.
        """
        return self.sample(contexts)

    def act(self, contexts: Tensor | int | None) -> Tensor:
        """Noise-free policy (mean of the most probable option): (N, D)."""
        return self.mean_action(contexts)

    @torch.no_grad()
    def tell(
        self, contexts: Tensor | int | None, params: Tensor, returns: Tensor
    ) -> dict[str, Any]:
        """Update the policy from samples drawn with it; raising changes nothing.

        Args:
            contexts: (N, C) (None or N without context).
            params: (N, D) from :meth:`ask`.
            returns: exactly (N,), higher is better.

        Returns:
            Diagnostics: ``eta, xi, kappa, kl, cross_entropy, effective_sample_size,
            option_entropy`` (before), ``policy_entropy`` (after), ``n_active_options, pruned,
            refitted`` (False: no information), ``mean_return, max_return, dual_converged,
            dual_iterations, feature_error, iteration``; ``kappa`` is NaN where the entropy
            bound is off; ``policy_entropy`` is the options' Gaussian entropies weighted by
            the gating's prior (not the mixture's entropy).
        """
        c, theta, R = self._samples(contexts, params, returns)
        (bound,), lr, kappa = option_bounds(
            self.policies, c[..., None, :], theta[..., None, :], self.kappa_rel
        )
        lead, N = R.shape[:-1], R.shape[-1]
        warn_if_degenerate([self.epsilon], N, 3)
        R1 = R.reshape(-1, N)  # the dual's S problems (1 for one run)
        phi = None
        if self.context_features is not None:
            phi = self.context_features(c).to(R).reshape(*R1.shape, -1)
            check_finite("context features", phi)
        eps = R.new_full((R1.shape[0], 1), self.epsilon)
        sol = episodic_solution(R1, lr[:, :, 0], eps, phi, kappa, LbfgsSettings(), seeds=self.seeds)
        floored: dict[str, Any] = {}
        if self.prior_entropy_floor is not None:
            sol, floored = self._floored(R1, lr[:, :, 0], eps, phi, kappa, sol)
        refit = plan_refit(self.policy, c, theta, sol, bound)
        report = apply_refit(self.policy, c, refit, self.prune_threshold)
        self.iteration += 1
        mean_return, max_return = torch.stack([R.mean(-1), R.amax(-1)]).tolist()
        return {
            "iteration": per_member(self.iteration, lead),
            **report,
            "mean_return": mean_return,
            "max_return": max_return,
            **floored,
        }

    def _floored(
        self,
        R: Tensor,
        lr: Tensor,
        eps: Tensor,
        phi: Tensor | None,
        kappa: Tensor | None,
        sol: DualSolution,
    ) -> tuple[DualSolution, dict[str, Any]]:
        """``sol`` with the options' prior entropy floor (R (S, N), lr (S, N, O)) and its
        diagnostics: the multiplier, the realised prior entropy and the floor (nats)."""
        S, O = R.shape[0], self.policy.n_options
        active = self.policy.active.reshape(S, O)
        if lr.shape[-1] != O:  # one active option per member: no entropy to keep
            zero = [0.0] * S
            return sol, {"lambda": zero, "prior_entropy": zero, "entropy_floor": zero}
        lr = torch.where(active[:, None, :], lr, -math.inf)  # pruned options stay empty
        # delta log O, but at most what the active options can hold (less a margin: their
        # uniform prior is one step's reach only rarely)
        most = torch.log(active.sum(-1).to(R)) - 0.05
        floor = torch.clamp(most, max=self.prior_entropy_floor * math.log(O)).clamp_min(0.0)  # type: ignore[operator]
        sol, lam, H, floor = entropy_floor_solution(R, lr, eps, phi, kappa, floor, sol)
        lead = self.policy.batch_shape
        return sol, {
            "lambda": lam.reshape(lead).tolist(),
            "prior_entropy": H.reshape(lead).tolist(),
            "entropy_floor": floor.reshape(lead).tolist(),
        }

    # ---- the shared interface (Algorithm) ---------------------------------------------------
    def learn(self, experience: Experience) -> dict[str, Any]:
        """:meth:`tell` from contexts (N, 1, C), parameters (N, 1, D) and returns (N, 1)."""
        e = self._experience(experience)
        return self.tell(e.states[..., 0, :], e.actions[..., 0, :], e.rewards[..., 0])

    # ---- checkpointing ----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the run bit-for-bit, as a copy (later updates leave it
        as it is)."""
        return self._state(policy=self.policy.state_dict(), epsilon=self.epsilon)

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; one that does not fit raises, changing nothing."""
        state = self._keys_checked(state, "policy", "epsilon")
        self.policy.check_state_dict(state["policy"])
        epsilon = check_positive_float("epsilon", state["epsilon"])
        self._load_shared(state)
        self.policy.load_state_dict(state["policy"])
        self.epsilon = epsilon


def _is_count(contexts: object) -> bool:
    """None or one number (int, 0-d tensor): a count of context-free samples."""
    if contexts is None:
        return True
    if isinstance(contexts, list | tuple):
        return False
    shape = getattr(contexts, "shape", None)
    return shape is None or len(shape) == 0


class REPS(EpisodicHiREPS):
    """Episodic / contextual REPS: one linear-Gaussian option and no entropy bound."""

    @classmethod
    def create(  # type: ignore[override]
        cls,
        param_dim: int,
        *,
        context_dim: int = 0,
        init_mean: Tensor | None = None,
        init_std: float | Tensor = 1.0,
        epsilon: float = 1.0,
        policy_features: FeatureMap | None = None,
        min_variance: float | Tensor = 1e-8,
        covariance_prior: float = 0.0,
        mean_prior: float = 0.0,
        seed: int | Sequence[int] | None = None,
        population: int | None = None,
    ) -> Self:
        """Build REPS with one linear-Gaussian option (see :meth:`EpisodicHiREPS.create`)."""
        return super().create(
            param_dim,
            context_dim=context_dim,
            n_options=1,
            init_mean=init_mean,
            epsilon=epsilon,
            kappa_rel=None,
            seed=seed,
            population=population,
            init_std=init_std,
            policy_features=policy_features,
            min_variance=min_variance,
            covariance_prior=covariance_prior,
            mean_prior=mean_prior,
        )
