"""Option steps every HiREPS variant shares around its dual (policies of batch shape () or
(S,)): responsibilities p~_io = p(o | s_i, theta_i) and kappa = kappa_rel * mean_i H[p~_i.]
before it, the refit after it (planned, then applied only when every policy's succeeded).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from hireps_torch._linalg import reduce_each
from hireps_torch.dual import DualSolution
from hireps_torch.dual.inputs import LOG_RESP_FLOOR
from hireps_torch.policies import HierarchicalPolicy


@dataclass(frozen=True)
class OptionBound:
    """The dual's option inputs: log_responsibilities ([S,] N, O) (-inf: pruned; None: no
    option term), option_entropy ([S,]) and kappa ([S,], inf: no bound; or None)."""

    log_responsibilities: Tensor | None
    option_entropy: Tensor
    kappa: Tensor | None


def option_bound(
    policy: HierarchicalPolicy, context: Tensor, theta: Tensor, kappa_rel: float | None
) -> OptionBound:
    """Responsibilities of the sampling policy and each member's entropy bound.

    context ([S,] N, C), theta ([S,] N, D); kappa_rel: fraction of the mean entropy, or None.
    """
    if policy.n_options < 2 or not bool((several := policy.active.sum(-1) >= 2).any()):
        return OptionBound(None, context.new_zeros(policy.batch_shape), None)
    lr = policy.log_responsibilities(context, theta)
    p = lr.exp()
    per_sample = torch.where(p > 0, p * lr, 0.0).sum(-1)
    entropy = torch.where(several, -reduce_each(per_sample, "mean", -1), 0.0)
    kappa = None if kappa_rel is None else torch.where(several, kappa_rel * entropy, math.inf)
    return OptionBound(lr, entropy, kappa)


UNIFORM_RTOL = 1e-6
"""Weights within this relative tolerance of q_i p~_io carry no information."""


def informed_members(
    weights: Tensor, eta: Tensor, bound: OptionBound, active: Tensor, kl: float = 0.0
) -> Tensor:
    """([S,]) bool: whether each member's dual weights carry information about the returns.

    False where eta is inf or every entry of ``weights`` ([S,] N, O) is within
    :data:`UNIFORM_RTOL` of p~_io / N. ``active``: ([S,] O) options not pruned; ``kl``: the
    smallest realised KL (above 2 * UNIFORM_RTOL**2 the entries are not compared).
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
    """A planned update: new ``values`` (None: no member informed), ([S,]) bool ``informed``,
    the dual's ``sol``, the samples' ``bound`` and the dual ``block`` (time-indexed step)."""

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
    """The refit of ``policy`` to block ``block`` of ``sol.weights`` (S, K, N, O), without
    changing it; context ([S,] N, C), theta ([S,] N, D). ValueError: non-finite weights or a
    failing refit."""
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
    """Set the planned values, prune informed members, return the diagnostics (a list of S
    per entry for a population). context: ([S,] N, C); prune_threshold 0: never prune."""
    lead = policy.batch_shape
    pruned: Any = [[] for _ in range(lead[0])] if lead else []
    if refit.values is not None:
        policy.set_checked(refit.values)
        if policy.n_options > 1 and prune_threshold > 0:
            pruned = policy.prune(context, prune_threshold, members=refit.informed)
    sol, bound, k = refit.sol, refit.bound, refit.block
    subs = policy.sub_policies
    if policy.n_options > 1:
        prior = reduce_each(policy.gating.probs(policy.gating_features(context)), "mean", -2)
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
    else:  # S rows of 12: block k's 5 numbers, the problem's 2, the policy's 5
        block = [sol.eta, sol.xi, sol.kl, sol.cross_entropy, sol.effective_sample_size]
        whole = [sol.converged.to(sol.feature_error), sol.feature_error]
        parts = [torch.stack(block, -1)[:, k], torch.stack(whole, -1), policy_numbers]
        rows = torch.cat(parts, -1).tolist()
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
        "dual_iterations": sol.iterations.reshape(lead).tolist(),
        "feature_error": error,
    }


def each(values: Any, fn: Any) -> Any:
    """``fn`` of one number, or of each entry of a member list."""
    return [fn(v) for v in values] if isinstance(values, list) else fn(values)


def per_member(value: Any, lead: tuple[int, ...]) -> Any:
    """``value`` for one run (lead ()), a list of it for each of S members (lead (S,))."""
    return [value] * lead[0] if lead else value


def option_bounds(
    policies: Sequence[HierarchicalPolicy], states: Tensor, theta: Tensor, kappa_rel: float | None
) -> tuple[list[OptionBound], Tensor, Tensor | None]:
    """Each step's :func:`option_bound` for states ([S,] N, K, C) and theta ([S,] N, K, D) of K
    steps' policies, and the dual's (S, N, K, O) floored log responsibilities ((S, N, K, 1) zeros
    when no step has an option term) and (S, K) entropy bounds (inf: none), or None."""
    bounds = [
        option_bound(pol, states[..., k, :], theta[..., k, :], kappa_rel)
        for k, pol in enumerate(policies)
    ]
    K, S, N = len(bounds), math.prod(policies[0].batch_shape), theta.shape[-3]
    if all(b.log_responsibilities is None for b in bounds):
        return bounds, theta.new_zeros(S, N, K, 1), None
    O = max(p.n_options for p in policies)
    log_resp = theta.new_full((S, N, K, O), -math.inf)
    for k, (b, pol) in enumerate(zip(bounds, policies, strict=True)):
        lr = b.log_responsibilities
        if lr is None:  # one active option in each member: log 1 on it
            lr = torch.where(pol.active, 0.0, -math.inf)[..., None, :].expand(
                *pol.batch_shape, N, -1
            )
        log_resp[:, :, k, : lr.shape[-1]] = lr.reshape(S, N, -1)
    if all(b.kappa is None for b in bounds):
        return bounds, log_resp.clamp_min(LOG_RESP_FLOOR), None
    kappa = torch.stack(
        [theta.new_full((S,), math.inf) if b.kappa is None else b.kappa.reshape(S) for b in bounds],
        -1,
    )
    return bounds, log_resp.clamp_min(LOG_RESP_FLOOR), kappa.to(torch.float64)
