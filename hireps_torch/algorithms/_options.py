"""The option-specific steps every HiREPS variant shares around its dual.

Before the dual: the responsibilities p~_io = p(o | s_i, theta_i) of the sampling policy on
the active options and the entropy bound kappa = kappa_rel * mean_i H[p~_i.]
(:func:`option_bound`). After it: the weighted refit of gating and options, pruning, and the
diagnostics every update reports (:func:`refit_and_report`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from hireps_torch.dual import DualSolution
from hireps_torch.policies import HierarchicalPolicy


@dataclass(frozen=True)
class OptionBound:
    """Inputs of the dual that come from the options.

    Attributes:
        log_responsibilities: (N, O_active) log p~ on the active options, or None when only one
            option is active (the dual then has no option term).
        option_entropy: mean entropy of the responsibilities (0 with one active option).
        kappa: absolute entropy bound, or None when there is none.
    """

    log_responsibilities: Tensor | None
    option_entropy: float
    kappa: float | None

    @property
    def n_columns(self) -> int:
        """Option columns of the dual's weights: O_active, or 1 with one active option."""
        lr = self.log_responsibilities
        return 1 if lr is None else lr.shape[1]


def option_bound(
    policy: HierarchicalPolicy, context: Tensor, theta: Tensor, kappa_rel: float | None
) -> OptionBound:
    """Responsibilities of the sampling policy and the entropy bound.

    Args:
        policy: the sampling policy.
        context: (N, S).
        theta: (N, D).
        kappa_rel: bound as a fraction of the mean responsibility entropy, or None.
    """
    active = policy.active
    if int(active.sum()) < 2:
        return OptionBound(None, 0.0, None)
    lr = policy.log_responsibilities(context, theta)[:, active]
    p = lr.exp()
    entropy = float(-(torch.where(p > 0, p * lr, 0.0)).sum(-1).mean())
    kappa = None if kappa_rel is None else kappa_rel * entropy
    return OptionBound(lr, entropy, kappa)


def refit_and_report(
    policy: HierarchicalPolicy,
    context: Tensor,
    theta: Tensor,
    sol: DualSolution,
    bound: OptionBound,
    prune_threshold: float,
) -> dict[str, Any]:
    """Refit the policy to the dual's weights, prune, and return the shared diagnostics.

    Args:
        policy: updated in place.
        context: (N, S) states / contexts of the samples.
        theta: (N, D) their actions / parameters.
        sol: the dual's solution; ``sol.weights`` is (N, O_active).
        bound: what :func:`option_bound` returned for these samples.
        prune_threshold: options with prior mass below it are pruned (0: never).
    """
    weights = torch.zeros(context.shape[0], policy.n_options, dtype=torch.float64)
    weights[:, policy.active] = sol.weights
    policy.weighted_fit(context, theta, weights)
    pruned: list[int] = []
    if policy.n_options > 1 and prune_threshold > 0:
        pruned = policy.prune(context, prune_threshold)
    prior = policy.gating.probs(policy.gating_features(context)).mean(0)
    ent = torch.stack([o.entropy() for o in policy.sub_policies])
    return {
        "eta": sol.eta,
        "xi": sol.xi,
        "kappa": math.nan if bound.kappa is None else bound.kappa,
        "kl": sol.kl,
        "cross_entropy": sol.cross_entropy,
        "effective_sample_size": sol.effective_sample_size,
        "option_entropy": bound.option_entropy,
        "policy_entropy": float((prior * ent).sum()),
        "n_active_options": int(policy.active.sum()),
        "pruned": pruned,
        "dual_converged": sol.converged,
        "dual_iterations": sol.iterations,
        "feature_error": sol.feature_error,
    }
