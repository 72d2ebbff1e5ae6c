"""The option-specific steps every HiREPS variant shares around its dual.

Before the dual: the responsibilities p~_io = p(o | s_i, theta_i) of the sampling policy on
the active options and the entropy bound kappa = kappa_rel * mean_i H[p~_i.]
(:func:`option_bound`; the time-indexed variant stacks its steps' with :func:`stack_bounds`).
Every function takes a policy of any batch shape: () for one run, (S,) for a population of
S members (member s computes what it would alone).
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
from typing import Any

import torch
from torch import Tensor

from hireps_torch.dual import DualSolution
from hireps_torch.dual.inputs import LOG_RESP_FLOOR
from hireps_torch.policies import HierarchicalPolicy


@dataclass(frozen=True)
class OptionBound:
    """Inputs of the dual that come from the options.

    Attributes:
        log_responsibilities: ([S,] N, O) log p~ (-inf on pruned options), or None when no
            member has two active options (the dual then has no option term).
        option_entropy: ([S,]) mean entropy of the responsibilities (0 with one active option).
        kappa: ([S,]) absolute entropy bound (inf: none for that member), or None.
    """

    log_responsibilities: Tensor | None
    option_entropy: Tensor
    kappa: Tensor | None

    def dual_inputs(self, R: Tensor) -> tuple[Tensor, Tensor | None]:
        """The dual's (S, N, O) log responsibilities (log 0 floored; (S, N, 1) zeros without
        an option term) and (S, 1) bounds (or None) for its (S, N) returns R."""
        lr = self.log_responsibilities
        kappa = None if self.kappa is None else self.kappa.reshape(-1, 1)
        if lr is None:
            return R.new_zeros(*R.shape, 1), kappa
        return lr.reshape(*R.shape, lr.shape[-1]).clamp_min(LOG_RESP_FLOOR), kappa


def option_bound(
    policy: HierarchicalPolicy, context: Tensor, theta: Tensor, kappa_rel: float | None
) -> OptionBound:
    """Responsibilities of the sampling policy and the entropy bound of each member.

    Args:
        policy: the sampling policy.
        context: ([S,] N, C).
        theta: ([S,] N, D).
        kappa_rel: bound as a fraction of the mean responsibility entropy, or None.
    """
    if policy.n_options < 2:
        return OptionBound(None, context.new_zeros(policy.batch_shape), None)
    several = policy.active.sum(-1) >= 2
    if not bool(several.any()):
        return OptionBound(None, context.new_zeros(policy.batch_shape), None)
    lr = policy.log_responsibilities(context, theta)
    p = lr.exp()
    entropy = torch.where(several, -(torch.where(p > 0, p * lr, 0.0)).sum(-1).mean(-1), 0.0)
    kappa = None if kappa_rel is None else torch.where(several, kappa_rel * entropy, math.inf)
    return OptionBound(lr, entropy, kappa)


UNIFORM_RTOL = 1e-6
"""Relative tolerance of :func:`informed_members`: weights within it of q_i p~_io carry no
information (the dual's no-information solution is exact up to round-off, ~1e-15; an
informative solution moves them by ~sqrt(2 epsilon), orders of magnitude more)."""


def informed_members(
    weights: Tensor, eta: Tensor, bound: OptionBound, active: Tensor, kl: float = 0.0
) -> Tensor:
    """([S,]) bool: whether each member's dual weights carry information about the returns.

    False where eta is infinite (the dual found the returns flat beyond what the features
    fix, whatever the entropy bound did to the weights), or where every entry of ``weights``
    ([S,] N, O) is within a relative :data:`UNIFORM_RTOL` of the sampling distribution
    p~_io / N (the KL to it is then below the chi-square divergence, at most
    ``UNIFORM_RTOL ** 2``). The update then has nothing to learn from. ``active`` is the
    policy's ([S,] O) mask of options not pruned; ``kl``, the smallest realised KL of the
    members where known: above twice that bound no member's weights are that close, and the
    entries are not compared.
    """
    moved = eta != math.inf
    if kl > 2.0 * UNIFORM_RTOL**2:
        return moved
    N = weights.shape[-2]
    lr = bound.log_responsibilities
    old = torch.where(active, 1.0 / N, 0.0)[..., None, :] if lr is None else lr.exp() / N
    flat = ((weights - old).abs() <= UNIFORM_RTOL * old).flatten(-2).all(-1)
    return moved & ~flat


@dataclass(frozen=True)
class Refit:
    """A computed (not yet applied) update of a policy.

    Attributes:
        values: the new values (``state_dict`` names -> tensors; a member without information
            keeps its current ones), or None when no member's weights carry information.
        informed: ([S,]) bool, the members whose weights carry information.
        sol: the dual's solution (leading S, 1 for one run).
        bound: what :func:`option_bound` returned for the samples.
        block: the dual's block of this policy (the time-indexed step; 0 otherwise).
    """

    values: dict[str, Tensor] | None
    informed: Tensor
    sol: DualSolution
    bound: OptionBound
    block: int = 0


def plan_refit(
    policy: HierarchicalPolicy,
    context: Tensor,
    theta: Tensor,
    sol: DualSolution,
    bound: OptionBound,
    block: int = 0,
) -> Refit:
    """The refit of ``policy`` to the dual's weights of block ``block``, computed and checked
    without changing the policy.

    Args:
        policy: the sampling policy.
        context: ([S,] N, C) states / contexts of the samples.
        theta: ([S,] N, D) their actions / parameters.
        sol: the dual's solution; ``sol.weights`` is (S, K, N, O) (O = 1 without option term).
        bound: what :func:`option_bound` returned for these samples.

    Raises:
        ValueError: when the dual's weights are not finite or the refit fails (naming the
            member and the option), before anything changed.
    """
    lead, O = policy.batch_shape, policy.n_options
    w = sol.weights[:, block, :, :O]
    N = w.shape[-2]
    w = w.reshape(*lead, N, w.shape[-1])
    active = policy.active
    if w.shape[-1] != O:  # no option term: the one active option of each member gets it all
        w = torch.where(active[..., None, :], w, 0.0)
    eta = sol.eta[:, block].reshape(lead)
    kl = sol.numbers[2] if sol.numbers is not None else float(sol.kl[:, block].min())
    informed = informed_members(w, eta, bound, active, kl)
    flags = informed.reshape(-1).tolist()
    any_informed, every = any(flags), all(flags)
    if not math.isfinite(float(w.sum())):  # each member's weights sum to 1 where finite
        bad = (~torch.isfinite(w).flatten(-2).all(-1)).reshape(-1).nonzero()[0, 0]
        who = f"member {int(bad)}: " if lead else ""
        raise ValueError(
            f"{who}the dual returned non-finite weights (eta = {float(sol.eta[bad, block])}, "
            f"converged = {bool(sol.converged[bad])}); the policy is left unchanged"
        )
    if not any_informed:
        return Refit(None, informed, sol, bound, block)
    if not every:  # the others' fits are discarded
        w = torch.where(informed[..., None, None], w, active[..., None, :].to(w))
    gf = policy.gating_features(context) if policy.n_options > 1 else None
    pf = policy.policy_features(context)
    values = policy.fit_checked(gf, pf, theta, w)
    if not every:
        current = policy.state_dict()
        values = {
            k: torch.where(informed.view(-1, *[1] * (v.dim() - 1)), v, current[k])
            for k, v in values.items()
        }
    return Refit(values, informed, sol, bound, block)


def apply_refit(
    policy: HierarchicalPolicy, context: Tensor, refit: Refit, prune_threshold: float
) -> dict[str, Any]:
    """Set the planned values, prune, and return the shared diagnostics: one number per
    entry for one run, a list of S for a population (member s's are those it reports alone).

    A member without information is neither refitted nor pruned.

    Args:
        policy: updated in place.
        context: ([S,] N, C) states / contexts of the samples.
        refit: what :func:`plan_refit` computed for this policy and these samples.
        prune_threshold: options with prior mass below it are pruned (0: never).
    """
    lead = policy.batch_shape
    pruned: Any = [[] for _ in range(lead[0])] if lead else []
    if refit.values is not None:
        policy.set_checked(refit.values)
        if policy.n_options > 1 and prune_threshold > 0:
            pruned = policy.prune(context, prune_threshold, members=refit.informed)
    sol, bound, k = refit.sol, refit.bound, refit.block
    subs = policy.sub_policies
    if policy.n_options > 1:
        prior = policy.gating.probs(policy.gating_features(context)).mean(-2)
        ent = (prior * torch.stack([o.entropy() for o in subs], -1)).sum(-1)
    else:  # one option: pi(o | s) = 1
        ent = subs[0].entropy()
    kappa = bound.kappa if bound.kappa is not None else ent.new_full(lead, math.inf)
    S = sol.eta.shape[0]
    policy_numbers = torch.stack(
        [kappa, bound.option_entropy, ent, policy.active.sum(-1).to(ent), refit.informed.to(ent)],
        -1,
    ).reshape(S, 5)
    if sol.numbers is not None:  # one problem with one block: the dual's numbers at hand
        eta_, xi_, kl_, ce_, ess_, error_, _ = sol.numbers
        head = [[eta_, xi_, kl_, ce_, ess_, float(sol.converged.tolist()[0]), error_]]
        rows = [h + p for h, p in zip(head, policy_numbers.tolist(), strict=True)]
    else:
        dual_numbers = torch.cat(
            [
                torch.stack(
                    [sol.eta, sol.xi, sol.kl, sol.cross_entropy, sol.effective_sample_size], -1
                )[:, k],
                torch.stack([sol.converged.to(sol.feature_error), sol.feature_error], -1),
            ],
            -1,
        )  # (S, 7)
        rows = torch.cat([dual_numbers, policy_numbers], -1).tolist()  # S rows of 12
    (eta, xi, kl, ce, ess, converged, error, kap, opt_ent, pol_ent, n_active, informed) = (
        [list(column) for column in zip(*rows, strict=True)] if lead else rows[0]
    )
    return {
        "eta": eta,
        "xi": xi,
        "kappa": each(kap, lambda x: math.nan if math.isinf(x) else x),
        "kl": kl,
        "cross_entropy": ce,
        "effective_sample_size": ess,
        "option_entropy": opt_ent,
        "policy_entropy": pol_ent,
        "n_active_options": each(n_active, int),
        "pruned": pruned,
        "refitted": each(informed, bool),
        "dual_converged": each(converged, bool),
        "dual_iterations": dual_iterations(sol, lead),
        "feature_error": error,
    }


def dual_iterations(sol: DualSolution, lead: tuple[int, ...]) -> Any:
    """Each member's dual iterations (one number for one run)."""
    counts = sol.iterations.tolist()
    return counts if lead else counts[0]


def each(values: Any, fn: Any) -> Any:
    """``fn`` of one number, or of each entry of a member list."""
    return [fn(v) for v in values] if isinstance(values, list) else fn(values)


def per_member(value: Any, lead: tuple[int, ...]) -> Any:
    """``value`` for one run (lead ()), a list of it for each of S members (lead (S,))."""
    return [value] * lead[0] if lead else value


def stack_bounds(
    bounds: list[OptionBound], policies: list[HierarchicalPolicy], N: int, like: Tensor
) -> tuple[Tensor, Tensor | None]:
    """The steps' bounds as the time-indexed dual's (S, N, K, O) log responsibilities (log 0
    floored; a step without option term gets log 1 on each member's active option, missing
    columns log 0; (S, N, K, 1) zeros when no step has one) and (S, K) entropy bounds (inf:
    none), or None."""
    K, S = len(bounds), math.prod(policies[0].batch_shape)
    if all(b.log_responsibilities is None for b in bounds):
        return like.new_zeros(S, N, K, 1), None
    O = max(p.n_options for p in policies)
    log_resp = like.new_full((S, N, K, O), -math.inf)
    for k, (b, pol) in enumerate(zip(bounds, policies, strict=True)):
        lr = b.log_responsibilities
        if lr is None:  # one active option in each member: log 1 on it
            lr = torch.where(pol.active, 0.0, -math.inf)[..., None, :].expand(
                *pol.batch_shape, N, -1
            )
        log_resp[:, :, k, : lr.shape[-1]] = lr.reshape(S, N, -1)
    if all(b.kappa is None for b in bounds):
        return log_resp.clamp_min(LOG_RESP_FLOOR), None
    kappa = torch.stack(
        [like.new_full((S,), math.inf) if b.kappa is None else b.kappa.reshape(S) for b in bounds],
        -1,
    )
    return log_resp.clamp_min(LOG_RESP_FLOOR), kappa.to(torch.float64)
