"""How many distinct solutions a policy holds, measured on its samples.

A task with several solution families labels each episode with ``solution_class(contexts,
theta)``: ``k`` in ``0 .. K-1`` when the episode solves the task by family ``k`` (a goal
reached, a winding side), ``-1`` when it solves nothing. From samples of a policy (which option
drew each, and its class)::

    theta, option = policy.sample(contexts, generator)          # ([S,] N, D), ([S,] N)
    classes = task.solution_class(contexts, theta)              # ([S,] N) in -1 .. K-1
    versatility(option, classes, policy_prior, n_classes=K)     # per member
    policy_versatility(policy, task, contexts, generator)       # the three lines above

* ``success_rate``: the share of samples with a class (>= 0).
* ``purity``: for each option whose prior is at least ``prior_floor`` and that drew samples,
  the share of its samples in its main class (failures count as a class of their own, so an
  option that mostly fails is pure in failure but holds no solution); averaged with the
  options' priors as weights.
* ``solutions_found``: the number of distinct classes that some such option holds: its main
  class, reached by more than half of its samples.
* ``behaviour_entropy``: the entropy of the classes of the successful samples over
  ``log K`` (1: the successes spread evenly over all K families; 0: one family or none).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from hireps_torch.policies import HierarchicalPolicy
from hireps_torch.policies._population import Generators

__all__ = ["PRIOR_FLOOR", "policy_versatility", "versatility"]

PRIOR_FLOOR = 0.05
"""Options with less prior mass are not counted as holding a solution (nor in ``purity``)."""


def versatility(
    option: Tensor,
    classes: Tensor,
    prior: Tensor,
    n_classes: int,
    prior_floor: float = PRIOR_FLOOR,
) -> dict[str, list[float]]:
    """Versatility of a policy from its samples (see the module docstring).

    Args:
        option: ([S,] N) int64, the option that drew each sample.
        classes: ([S,] N) int64, each sample's solution class in -1 .. n_classes - 1.
        prior: ([S,] O) the options' prior masses (mean gating probabilities; 0 for pruned).
        n_classes: K >= 1, the number of solution families of the task.
        prior_floor: options below this prior hold no solution and are left out of purity.

    Returns:
        ``success_rate, purity, solutions_found, behaviour_entropy``: one float per member
        (a list of length S; of length 1 without S). ``purity`` is NaN where no option
        above the floor drew a sample.
    """
    if option.shape != classes.shape or option.dim() not in (1, 2):
        raise ValueError(
            f"option and classes must both have shape ([S,] N), got {tuple(option.shape)} and "
            f"{tuple(classes.shape)}"
        )
    if isinstance(n_classes, bool) or not isinstance(n_classes, int) or n_classes < 1:
        raise ValueError(f"n_classes must be an integer >= 1, got {n_classes!r}")
    if classes.numel() and (int(classes.min()) < -1 or int(classes.max()) >= n_classes):
        raise ValueError(
            f"classes must lie in -1 .. {n_classes - 1}, got values from {int(classes.min())} "
            f"to {int(classes.max())}"
        )
    option, classes = option.reshape(-1, option.shape[-1]), classes.reshape(-1, classes.shape[-1])
    prior = prior.reshape(-1, prior.shape[-1]).to(torch.float64)
    if prior.shape[0] != option.shape[0]:
        raise ValueError(f"prior must have shape ([S,] O) for S = {option.shape[0]}")
    S, O = prior.shape
    # counts[s, o, k + 1]: samples of member s drawn by option o with class k (column 0: none)
    flat = (torch.arange(S)[:, None] * O + option.cpu()) * (n_classes + 1) + classes.cpu() + 1
    counts = torch.bincount(flat.reshape(-1), minlength=S * O * (n_classes + 1))
    counts = counts.reshape(S, O, n_classes + 1).to(torch.float64)
    drawn = counts.sum(-1)  # (S, O)
    main, main_class = counts.max(-1)  # ties: the lowest column
    share = main / drawn.clamp_min(1)
    kept = (prior.cpu() >= prior_floor) & (drawn > 0)
    weight = prior.cpu() * kept
    purity = (weight * share).sum(-1) / weight.sum(-1)
    holds = kept & (main_class > 0) & (share > 0.5)
    held = torch.zeros(S, n_classes + 1, dtype=torch.bool)
    s, o = holds.nonzero(as_tuple=True)
    held[s, main_class[s, o]] = True
    success = counts[..., 1:].sum(1)  # (S, K)
    p = success / success.sum(-1, keepdim=True).clamp_min(1)
    entropy = -(p * p.clamp_min(1e-300).log()).sum(-1) + 0.0  # + 0.0: no -0.0
    behaviour = entropy / math.log(n_classes) if n_classes > 1 else torch.zeros(S)
    return {
        "success_rate": (success.sum(-1) / drawn.sum(-1).clamp_min(1)).tolist(),
        "purity": purity.tolist(),
        "solutions_found": [float(v) for v in held[:, 1:].sum(-1)],
        "behaviour_entropy": behaviour.tolist(),
    }


@torch.no_grad()
def policy_versatility(
    policy: HierarchicalPolicy,
    task: Any,
    contexts: Tensor,
    generator: Generators = None,
    prior_floor: float = PRIOR_FLOOR,
) -> dict[str, list[float]]:
    """:func:`versatility` of ``policy`` from one sample per context.

    Args:
        policy: the (population's) hierarchical policy.
        task: has ``solution_class(contexts, theta) -> ([S,] N)`` and ``n_classes``.
        contexts: ([S,] N, C) (C = 0 for tasks without context), on the policy's device.
        generator: the sampling generator (S of them for a population).
        prior_floor: see :func:`versatility`.

    The options' prior is the gating's probabilities averaged over ``contexts``.
    """
    theta, option = policy.sample(contexts, generator)
    prior = policy.gating.probs(policy.gating_features(contexts)).mean(-2)
    classes = task.solution_class(contexts.cpu(), theta.cpu())
    return versatility(option.cpu(), classes, prior.cpu(), task.n_classes, prior_floor)
