"""The option-specific steps every HiREPS variant shares around its dual.

Before the dual: the responsibilities p~_io = p(o | s_i, theta_i) of the sampling policy on
the active options and the entropy bound kappa = kappa_rel * mean_i H[p~_i.]
(:func:`option_bound`; the time-indexed variant stacks its steps' with :func:`stack_bounds`).
After it: the weighted refit of gating and options, computed first (:func:`plan_refit`) and
applied only when every policy's refit succeeded (:func:`apply_refit`: set the new values,
prune, report the diagnostics), so a failing update changes nothing.

No drift without information. When the returns carry no information (e.g. a flat reward),
the dual says so with eta = inf: the return term exp(R / eta) is flat, and the new
distribution is the sampling one, P_io = q_i p~_io (q uniform over the samples), or, when the
entropy bound is active, its projection onto the bound, P_io ∝ q_i p~_io^(1 + xi/eta). The
policy is then left exactly as it is (:func:`carries_information`):

- the target q p~ is the old policy itself, but refitting to it does not keep the policy in
  expectation: the maximum-likelihood covariance shrinks by (N_eff - 1) / N_eff per refit,
  and even the unbiased (Bessel, 1 - sum w^2) estimate random-walks downwards in log scale
  (Jensen: E[log s^2] < log sigma^2); measured over 100 flat iterations of a 2-D Gaussian,
  N = 10: median final std 1e-4 (the floor) with maximum likelihood, 4e-4 with the unbiased
  estimate; N = 50: 0.07 and 0.2. The gating's mixture weights random-walk too, until options
  are pruned (EpisodicHiREPS, 5 options, N = 50: 1 option left, std 0.06-0.09);
- the entropy bound alone (kappa = kappa_rel * current entropy always binds) only sharpens the
  responsibilities: with no return to specialise on, each refit shrinks every option onto its
  own samples and the richest option takes over (5 seeds, 5 options, kappa_rel 0.9, N = 50,
  100 flat iterations: 4 of 5 options pruned in every seed, stds down to 1e-4). That is drift
  too, so the bound does not act without return information either.

Informative updates are unchanged: weighted maximum likelihood, bit for bit as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import torch
from torch import Tensor

from hireps_torch.dual import DualSolution, PopulationDualSolution
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


UNIFORM_RTOL = 1e-6
"""Relative tolerance of :func:`carries_information`: weights within it of q_i p~_io carry no
information (the dual's no-information solution is exact up to round-off, ~1e-15; an
informative solution moves them by ~sqrt(2 epsilon), orders of magnitude more)."""


def carries_information(sol: DualSolution, bound: OptionBound) -> bool:
    """Whether the dual's weights carry information about the returns.

    False when ``sol.eta`` is infinite (the dual found the returns flat beyond what the
    features fix, whatever the entropy bound did to the weights), or when every entry of
    ``sol.weights`` (N, O_active) is within a relative :data:`UNIFORM_RTOL` of the sampling
    distribution p~_io / N (1 / N with one option, where the dual has one column; the KL to
    it is then below ~1e-12). The update then has nothing to learn from.
    """
    return _judge(sol, bound)[1]


def _judge(sol: DualSolution, bound: OptionBound) -> tuple[bool, bool]:
    """(whether ``sol.weights`` are finite, :func:`carries_information`), in one transfer."""
    w = sol.weights
    finite = torch.isfinite(w).all()
    if math.isinf(sol.eta):
        return bool(finite), False
    N = w.shape[0]
    lr = bound.log_responsibilities
    old = w.new_tensor(1.0 / N) if lr is None else lr.exp() / N
    if old.dim() and old.shape != w.shape:
        return bool(finite), True
    flat = ((w - old).abs() <= UNIFORM_RTOL * old).all()
    ok, uniform = torch.stack([finite, flat]).tolist()
    return ok, not uniform


@dataclass(frozen=True)
class Refit:
    """A computed (not yet applied) update of one policy.

    Attributes:
        values: the policy's new values (``state_dict`` names -> tensors), or None when the
            weights carry no information and the policy stays as it is.
        sol: the dual's solution for this policy.
        bound: what :func:`option_bound` returned for its samples.
    """

    values: dict[str, Tensor] | None
    sol: DualSolution
    bound: OptionBound


def plan_refit(
    policy: HierarchicalPolicy,
    context: Tensor,
    theta: Tensor,
    sol: DualSolution,
    bound: OptionBound,
) -> Refit:
    """The refit of ``policy`` to the dual's weights, computed and checked without changing it.

    Args:
        policy: the sampling policy.
        context: (N, S) states / contexts of the samples.
        theta: (N, D) their actions / parameters.
        sol: the dual's solution; ``sol.weights`` is (N, O_active).
        bound: what :func:`option_bound` returned for these samples.

    Raises:
        ValueError: when the dual's weights are not finite or the refit fails (naming the
            option), before anything changed.
    """
    finite, informed = _judge(sol, bound)
    if not finite:
        raise ValueError(
            f"the dual returned non-finite weights (eta = {sol.eta}, xi = {sol.xi}, converged "
            f"= {sol.converged}); the policy is left unchanged"
        )
    if not informed:
        return Refit(None, sol, bound)
    weights = sol.weights
    if weights.shape[-1] < policy.n_options:  # pruned options get weight 0
        weights = context.new_zeros(context.shape[0], policy.n_options, dtype=torch.float64)
        weights[:, policy.active] = sol.weights
    gf, pf = policy.gating_features(context), policy.policy_features(context)
    return Refit(policy.fit_checked(gf, pf, theta, weights), sol, bound)


def apply_refit(
    policy: HierarchicalPolicy, context: Tensor, refit: Refit, prune_threshold: float
) -> dict[str, Any]:
    """Set the planned values, prune, and return the shared diagnostics.

    Without information (``refit.values`` None) the policy is neither refitted nor pruned.

    Args:
        policy: updated in place.
        context: (N, S) states / contexts of the samples.
        refit: what :func:`plan_refit` computed for this policy and these samples.
        prune_threshold: options with prior mass below it are pruned (0: never).
    """
    pruned: list[int] = []
    if refit.values is not None:
        policy.set_checked(refit.values)
        if policy.n_options > 1 and prune_threshold > 0:
            pruned = cast(list[int], policy.prune(context, prune_threshold))
    sol, bound = refit.sol, refit.bound
    ent = torch.stack([o.entropy() for o in policy.sub_policies])
    prior = ent.new_ones(1)  # one option: pi(o | s) = 1
    if policy.n_options > 1:
        prior = policy.gating.probs(policy.gating_features(context)).mean(0)
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
        "refitted": refit.values is not None,
        "dual_converged": sol.converged,
        "dual_iterations": sol.iterations,
        "feature_error": sol.feature_error,
    }


def stack_bounds(
    bounds: list[OptionBound], N: int, device: torch.device
) -> tuple[Tensor | None, Tensor | None]:
    """Per-step responsibilities and entropy bounds as the dual's (N, K, O) and (K,) inputs,
    on ``device``.

    Steps may have different numbers of active options: the missing columns get log 0, and a
    step with one active option gets log p~ = 0 on it and no bound (kappa = inf). Returns
    (None, None) when every step has a single active option.
    """
    counts = [b.n_columns for b in bounds]
    O = max(counts)
    if O == 1:
        return None, None
    K = len(bounds)
    log_resp = torch.full((N, K, O), -math.inf, dtype=torch.float64, device=device)
    for k, b in enumerate(bounds):
        if b.log_responsibilities is None:
            log_resp[:, k, 0] = 0.0
        else:
            log_resp[:, k, : counts[k]] = b.log_responsibilities
    if all(b.kappa is None for b in bounds):
        return log_resp, None
    kappa = torch.tensor(
        [math.inf if b.kappa is None else b.kappa for b in bounds],
        dtype=torch.float64,
        device=device,
    )
    return log_resp, kappa


# ---- populations ----------------------------------------------------------------------------
# The same steps for a population of S policies (HierarchicalPolicy.stack): every member's
# dual is solved in one call, its refit computed in one batched call per option, and a member
# whose returns carry no information is left exactly as it is, whatever the others do.


@dataclass(frozen=True)
class PopulationBound:
    """:class:`OptionBound` of each member of a population.

    Attributes:
        log_responsibilities: (S, N, O) log p~ (-inf on a member's pruned options), or None
            when every member has one active option.
        option_entropy: (S,) mean entropy of each member's responsibilities.
        kappa: (S,) absolute entropy bounds (inf: none for that member), or None.
    """

    log_responsibilities: Tensor | None
    option_entropy: Tensor
    kappa: Tensor | None

    def member(self, s: int, active: Tensor) -> OptionBound:
        """Member s's bound as :func:`option_bound` returns it (its active columns)."""
        lr = self.log_responsibilities
        if lr is None or int(active[s].sum()) < 2:
            return OptionBound(None, 0.0, None)
        kappa = None if self.kappa is None else float(self.kappa[s])
        return OptionBound(lr[s][:, active[s]], float(self.option_entropy[s]), kappa)


def population_bound(
    policy: HierarchicalPolicy, context: Tensor, theta: Tensor, kappa_rel: float | None
) -> PopulationBound:
    """:func:`option_bound` of every member: context (S, N, C), theta (S, N, D)."""
    S = context.shape[0]
    several = policy.active.sum(-1) >= 2
    if not bool(several.any()):
        return PopulationBound(None, context.new_zeros(S, dtype=torch.float64), None)
    lr = policy.log_responsibilities(context, theta)
    p = lr.exp()
    entropy = -(torch.where(p > 0, p * lr, 0.0)).sum(-1).mean(-1)
    entropy = torch.where(several, entropy, 0.0)
    kappa = None
    if kappa_rel is not None:
        kappa = torch.where(several, kappa_rel * entropy, math.inf)
    return PopulationBound(lr, entropy, kappa)


@dataclass(frozen=True)
class PopulationRefit:
    """A computed (not yet applied) update of a population.

    Attributes:
        values: the new values of the members with information (the others' entries are
            their current ones), or None when no member has any.
        informed: (S,) bool, the members whose weights carry information.
        weights: (S, N, O) the dual's weights on all options (0 on pruned ones).
        sol: the population's dual solution (block ``block``).
        bound: what :func:`population_bound` returned.
        block: the dual's block of this policy (the time-indexed step; 0 otherwise).
    """

    values: dict[str, Tensor] | None
    informed: Tensor
    weights: Tensor
    sol: PopulationDualSolution
    bound: PopulationBound
    block: int = 0


def plan_population_refit(
    policy: HierarchicalPolicy,
    context: Tensor,
    theta: Tensor,
    sol: PopulationDualSolution,
    bound: PopulationBound,
    block: int = 0,
) -> PopulationRefit:
    """:func:`plan_refit` of every member (nothing changes): context (S, N, C), theta
    (S, N, D), the dual's block ``block`` of each member."""
    w = sol.weights[:, block, :, : policy.n_options]
    S, N = w.shape[:2]
    if not bool(torch.isfinite(w).all()):
        s = int((~torch.isfinite(w)).flatten(1).any(1).nonzero()[0, 0])
        raise ValueError(
            f"member {s}: the dual returned non-finite weights (eta = "
            f"{float(sol.eta[s, block])}, converged = {bool(sol.converged[s])}); the policy is "
            "left unchanged"
        )
    active = policy.active
    if w.shape[-1] == policy.n_options:
        weights = w
    else:  # one active option in every member: the dual had one column
        weights = torch.where(active, w, 0.0)
    uniform = torch.where(active, 1.0 / N, 0.0)[:, None].expand(S, N, -1)
    lr = bound.log_responsibilities
    old = uniform if lr is None else lr.exp() / N
    flat = ((weights - old).abs() <= UNIFORM_RTOL * old).flatten(1).all(1)
    informed = ~(torch.isinf(sol.eta[:, block]) | flat)
    if not bool(informed.any()):
        return PopulationRefit(None, informed, weights, sol, bound, block)
    safe = torch.where(informed[:, None, None], weights, old)  # the others' fits are discarded
    new = policy.fit_parameters(context, theta, safe)
    current = policy.state_dict()
    values = {
        k: torch.where(informed.view(-1, *[1] * (v.dim() - 1)), v, current[k])
        for k, v in new.items()
    }
    return PopulationRefit(values, informed, weights, sol, bound, block)


def apply_population_refit(
    policy: HierarchicalPolicy, context: Tensor, refit: PopulationRefit, prune_threshold: float
) -> dict[str, list[Any]]:
    """:func:`apply_refit` of every member: the diagnostics as lists of S entries (member
    s's are those :func:`apply_refit` reports for it alone)."""
    S = refit.informed.shape[0]
    pruned: list[list[int]] = [[] for _ in range(S)]
    if refit.values is not None:
        policy.set_checked(refit.values)
        if policy.n_options > 1 and prune_threshold > 0:
            before = policy.active.clone()
            found = cast(list[list[int]], policy.prune(context, prune_threshold))
            policy.gating.active.copy_(torch.where(refit.informed[:, None], policy.active, before))
            pruned = [p if bool(refit.informed[s]) else [] for s, p in enumerate(found)]
    sol, bound, k = refit.sol, refit.bound, refit.block
    prior = policy.gating.probs(policy.gating_features(context)).mean(-2)
    ent = torch.stack([o.entropy() for o in policy.sub_policies], -1)
    kappa = bound.kappa if bound.kappa is not None else prior.new_full((S,), math.inf)
    return {
        "eta": sol.eta[:, k].tolist(),
        "xi": sol.xi[:, k].tolist(),
        "kappa": [math.nan if math.isinf(x) else x for x in kappa.tolist()],
        "kl": sol.kl[:, k].tolist(),
        "cross_entropy": sol.cross_entropy[:, k].tolist(),
        "effective_sample_size": sol.effective_sample_size[:, k].tolist(),
        "option_entropy": bound.option_entropy.tolist(),
        "policy_entropy": (prior * ent).sum(-1).tolist(),
        "n_active_options": policy.active.sum(-1).tolist(),
        "pruned": pruned,
        "refitted": refit.informed.tolist(),
        "dual_converged": sol.converged.tolist(),
        "dual_iterations": [sol.iterations] * S,
        "feature_error": sol.feature_error.tolist(),
    }


def stack_population_bounds(
    bounds: list[PopulationBound], policies: list[HierarchicalPolicy]
) -> tuple[Tensor | None, Tensor | None]:
    """:func:`stack_bounds` of a population: the steps' (S, N, O_k) responsibilities as the
    dual's (S, N, K, O) (a step whose members all have one active option gets log 1 on it,
    missing columns log 0) and the bounds as (S, K) (inf: none). (None, None) when no step
    has a member with two active options."""
    if all(b.log_responsibilities is None for b in bounds):
        return None, None
    O = max(p.n_options for p in policies)
    S = bounds[0].option_entropy.shape[0]
    N = next(b.log_responsibilities.shape[1] for b in bounds if b.log_responsibilities is not None)
    dev = bounds[0].option_entropy.device
    log_resp = torch.full((S, N, len(bounds), O), -math.inf, dtype=torch.float64, device=dev)
    for k, (b, pol) in enumerate(zip(bounds, policies, strict=True)):
        lr = b.log_responsibilities
        if lr is None:  # one active option in each member: log 1 on it
            lr = torch.where(pol.active, 0.0, -math.inf)[:, None, :].expand(S, N, -1)
        log_resp[:, :, k, : lr.shape[-1]] = lr
    if all(b.kappa is None for b in bounds):
        return log_resp, None
    kappa = torch.stack(
        [torch.full((S,), math.inf, device=dev) if b.kappa is None else b.kappa for b in bounds],
        -1,
    )
    return log_resp, kappa.to(torch.float64)
