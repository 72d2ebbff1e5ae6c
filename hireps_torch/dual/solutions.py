"""What the duals return: the solution type, its diagnostics and the dual's warnings.

Every solution keeps the KL bound; ``converged`` is True only when every constraint holds to its
tolerance (:mod:`~hireps_torch.dual.safeguards`) and the solver met its gradient tolerance;
otherwise one :class:`InfeasibleConstraintsWarning` (a constraint cannot be met) or
:class:`DualConvergenceWarning` says what failed.

Returns without information (constant, or fixed by the features) give eta = inf (xi = inf where the
entropy bound tilts), the old distribution q p~ or the closest one meeting the constraints, and the
mean return as the dual value.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace

import torch
from torch import Tensor

__all__ = [
    "TENSORS",
    "DegenerateWeightsWarning",
    "DualConvergenceWarning",
    "DualSolution",
    "InfeasibleConstraintsWarning",
    "block_cross_entropy",
    "block_kl",
    "feature_error",
    "finish",
    "member_name",
    "public",
    "warn_if_collapsed",
]


class DegenerateWeightsWarning(RuntimeWarning):
    """The weights collapsed (or will collapse) onto very few samples."""


class InfeasibleConstraintsWarning(RuntimeWarning):
    """No distribution within the KL bound meets the feature constraints or the entropy bound; the
    message says which and what was done instead."""


class DualConvergenceWarning(RuntimeWarning):
    """The solve ended without meeting a constraint or its gradient tolerance; the message names
    what failed and by how much."""


@dataclass(frozen=True)
class DualSolution:
    """The solution of a dual for a batch of independent problems, every field led by the batch
    shape: () for one problem, (S,) for a population. Duals with several blocks (time-indexed, the
    generic solver) add a block dimension K after it.

    Attributes:
        eta: (*batch, [K]) temperatures of the KL bounds, in the caller's return units (inf
            without return information, see the module docstring).
        xi: (*batch, [K]) entropy-bound multipliers (0 where the bound is inactive or absent).
        v: (*batch, [K,] F) value-function / context-feature multipliers in the caller's
            feature units (one row per time-indexed step; the generic solver's stacked v:
            (*batch, P)).
        weights: (*batch, [K,] N, O) new distribution over samples and options; each block
            sums to 1.
        kl: (*batch, [K]) realised KL(P || q p~); epsilon where the bound is active, at most
            epsilon (1 + 1e-6).
        cross_entropy: (*batch, [K]) realised E_P[-log p~]; at most kappa where converged.
        effective_sample_size: (*batch, [K]) 1 / sum_i w_i^2 with w_i = sum_o P_io.
        feature_error: (*batch) largest violation of the feature constraints (caller's units;
            0 without features).
        dual_value: (*batch) dual objective at the optimum (finite).
        converged: (*batch) bool: every constraint holds to its tolerance and the solver met
            its gradient tolerance; if not, a warning said what failed.
        iterations: (*batch) int64 iterations of all phases (Newton steps and LBFGS).
    """

    eta: Tensor
    xi: Tensor
    v: Tensor
    weights: Tensor
    kl: Tensor
    cross_entropy: Tensor
    effective_sample_size: Tensor
    feature_error: Tensor
    dual_value: Tensor
    converged: Tensor
    iterations: Tensor
    numbers: tuple[float, ...] | None = field(default=None, repr=False, compare=False)
    """One problem, one block: (eta, xi, kl, cross_entropy, effective_sample_size, feature_error,
    dual_value) as floats, where the solver has them."""

    @property
    def sample_weights(self) -> Tensor:
        """(*batch, [K,] N) weights summed over options (the weights of a flat policy)."""
        return self.weights.sum(-1)

    def problem(self, s: int) -> DualSolution:
        """Problem s of a population (the first batch dimension)."""
        if self.converged.dim() == 0:
            raise ValueError("problem(s) indexes a population's solution; this one holds one")
        S = self.converged.shape[0]
        if not -S <= s < S:
            raise ValueError(f"problem must be in [0, {S}), got {s}")
        return replace(self, numbers=None, **{f.name: getattr(self, f.name)[s] for f in TENSORS})

    def step(self, k: int) -> DualSolution:
        """Block k as a one-block solution (its v the step's own where v has a block dimension;
        ``feature_error``, ``dual_value``, ``converged`` and ``iterations`` the whole problem's)."""
        batch = self.converged.dim()
        if self.eta.dim() == batch:
            raise ValueError("step(k) indexes the blocks of a dual with several; this one has one")
        K = self.eta.shape[batch]
        if not 0 <= k < K:
            raise ValueError(f"step must be in [0, {K}), got {k}")
        blocked = self.v.dim() == self.eta.dim() + 1
        return replace(
            self,
            **{name: getattr(self, name).select(batch, k) for name in _BLOCKED},
            v=self.v.select(batch, k) if blocked else self.v,
            numbers=None,
        )


TENSORS = [f for f in fields(DualSolution) if f.name != "numbers"]  # DualSolution's tensors
_BLOCKED = ("eta", "xi", "weights", "kl", "cross_entropy", "effective_sample_size")


def public(sol: DualSolution, population: bool, blocks: bool) -> DualSolution:
    """A solver's (S, K) solution shaped as its caller asked: (S,) kept for a ``population``
    (else problem 0), the block dimension kept where ``blocks`` (else block 0)."""
    out = sol if population else sol.problem(0)
    return out if blocks else out.step(0)


def block_kl(w: Tensor, log_resp: Tensor) -> Tensor:
    """(..., K) KL(P_k || q p~_k) of weights (..., K, N, O) against the old distribution."""
    logq = log_resp - math.log(w.shape[-2])
    logw = torch.log(w.clamp_min(1e-300))
    return torch.where(w > 0, w * (logw - logq), torch.zeros_like(w)).sum(dim=(-2, -1))


def block_cross_entropy(w: Tensor, log_resp: Tensor) -> Tensor:
    """(..., K) E_P_k[-log p~_k] of weights (..., K, N, O)."""
    return -(w * log_resp).sum(dim=(-2, -1))


def feature_error(w: Tensor, D: Tensor | None, c: Tensor | None) -> Tensor:
    """(S,) largest |c + sum_k w_k^T D_k| (the feature constraints' violation) of weights w (S, K,
    N, O), features D (S, K, N, P) or None (0) and c (S, P) or None."""
    if D is None:
        return w.new_zeros(w.shape[0])
    resid = torch.einsum("skn,sknp->sp", w.sum(-1), D)
    return (resid if c is None else resid + c).abs().amax(-1)


def finish(
    w: Tensor,
    log_resp: Tensor,
    eta: Tensor,
    xi: Tensor,
    v: Tensor,
    D: Tensor | None,
    c: Tensor | None,
    dual_value: Tensor,
    converged: Tensor,
    iterations: Tensor,
) -> DualSolution:
    """The (S, K) :class:`DualSolution` of weights w (S, K, N, O) with its diagnostics; float64
    inputs with a leading S (D (S, K, N, P), c (S, P))."""
    ws = w.sum(-1)  # (S, K, N)
    return DualSolution(
        eta=eta,
        xi=xi,
        v=v,
        weights=w,
        kl=block_kl(w, log_resp),
        cross_entropy=block_cross_entropy(w, log_resp),
        effective_sample_size=1.0 / (ws**2).sum(dim=-1),
        feature_error=feature_error(w, D, c),
        dual_value=dual_value,
        converged=converged,
        iterations=iterations,
    )


def member_name(s: int, seeds: Sequence[int] | None) -> str:
    """How warnings name problem s of a population: "member s", with its seed when given."""
    return f"member {s}" if seeds is None else f"member {s} (seed {seeds[s]})"


def warn_if_collapsed(
    sol: DualSolution, epsilon: Tensor, stacklevel: int = 2, seeds: Sequence[int] | None = None
) -> None:
    """Warn (``stacklevel`` frames above the caller) where a block's weights sit on ~one sample
    (epsilon (S, K); problems named by :func:`member_name`)."""
    S, K, N, _ = sol.weights.shape
    ess = sol.effective_sample_size
    if sol.numbers is not None:  # one block, its numbers at hand
        bad = [[0, 0]] if sol.numbers[4] < 1.5 and sol.numbers[0] < math.inf else []
    else:
        bad = ((ess < 1.5) & (sol.eta < math.inf)).nonzero().tolist()
    if bad:
        which = ", ".join(
            ("" if S == 1 else f"{member_name(s, seeds)}, ")
            + ("" if K == 1 else f"step {k}: ")
            + f"~{float(ess[s, k]):.2f} effective samples (epsilon = {float(epsilon[s, k]):.4g})"
            for s, k in bad
        )
        warnings.warn(
            f"the weights collapsed onto {which} with N = {N}; the refit will rely on its "
            "variance floor",
            DegenerateWeightsWarning,
            stacklevel=stacklevel + 1,
        )
