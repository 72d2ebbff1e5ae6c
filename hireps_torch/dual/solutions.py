"""What the duals return: the solution types, their diagnostics and the dual's warnings.

Every solution keeps its KL bound: ``kl <= epsilon (1 + 1e-6)`` on every block, whatever the
solver went through. ``converged`` is True only when, besides, the entropy bound
(``cross_entropy <= kappa + 1e-6 max(kappa, 1)``) and the feature constraints (residual below
1e-6 of the features' spread) hold and the solver met its gradient tolerance; a solve that is
not converged issues one :class:`InfeasibleConstraintsWarning` (a constraint that cannot be met:
the message says which and what was done instead) or :class:`DualConvergenceWarning` (naming
what failed and by how much). See :mod:`hireps_torch.dual.safeguards`.

Returns without information (constant, or fixed entirely by the features) report eta = inf:
the weights are then the old distribution q p~, or the distribution closest to it (in KL) that
meets the entropy bound and the feature constraints (xi = inf where the entropy bound tilts
it), and the dual value is the mean return, the value of every such distribution.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "DegenerateWeightsWarning",
    "DualConvergenceWarning",
    "DualSolution",
    "InfeasibleConstraintsWarning",
    "PopulationDualSolution",
    "RepsDualSolution",
    "TimeIndexedDualSolution",
    "block_cross_entropy",
    "block_kl",
    "block_solution",
    "finish",
    "single_solution",
    "warn_if_collapsed",
]


class DegenerateWeightsWarning(RuntimeWarning):
    """The weights collapsed (or will collapse) onto very few samples."""


class InfeasibleConstraintsWarning(RuntimeWarning):
    """No distribution within the KL bound satisfies the constraints (the feature constraints
    or the entropy bound); the message says which and what was done instead."""


class DualConvergenceWarning(RuntimeWarning):
    """The solve ended without meeting a constraint or its gradient tolerance (feasible as far
    as the solver can tell); the message names what failed and by how much."""


@dataclass(frozen=True)
class RepsDualSolution:
    """Solution of the generic K-block dual (:func:`~hireps_torch.dual.solve_reps_dual`).

    Attributes:
        eta: (K,) temperatures, in the caller's return units (inf without return
            information, see the module docstring).
        xi: (K,) entropy-bound multipliers (0 where the bound is inactive or absent).
        v: (P,) value-function / feature multipliers in the caller's feature units.
        weights: (K, N, O) new sample-option distribution per block, each block sums to 1.
        kl: (K,) realised KL(P_k || q p~_k), at most epsilon_k (1 + 1e-6).
        cross_entropy: (K,) realised E_P[-log p~].
        effective_sample_size: (K,) 1 / sum_i w_ki^2 with w_ki = sum_o P_kio.
        feature_error: max abs violation of the feature constraints, caller's units.
        dual_value: value of the dual at the optimum, caller's units (finite).
        converged: whether every constraint holds to its tolerance and LBFGS met its gradient
            tolerance (see the module docstring); if not, a warning said what failed.
        iterations: LBFGS iterations over all phases.
    """

    eta: Tensor
    xi: Tensor
    v: Tensor
    weights: Tensor
    kl: Tensor
    cross_entropy: Tensor
    effective_sample_size: Tensor
    feature_error: float
    dual_value: float
    converged: bool
    iterations: int


@dataclass(frozen=True)
class PopulationDualSolution:
    """Solutions of S independent K-block duals, each solved as alone (the population form of
    :class:`RepsDualSolution`; every field has a leading S).

    Attributes:
        eta: (S, K) temperatures, caller's return units (inf without return information).
        xi: (S, K) entropy-bound multipliers.
        v: (S, P) value-function / feature multipliers, caller's feature units.
        weights: (S, K, N, O) new sample-option distributions; each block sums to 1.
        kl: (S, K) realised KL, at most epsilon (1 + 1e-6).
        cross_entropy: (S, K) realised E_P[-log p~].
        effective_sample_size: (S, K) 1 / sum_i w_ki^2.
        feature_error: (S,) max abs violation of each problem's feature constraints.
        dual_value: (S,) dual values at the optima.
        converged: (S,) bool, per problem as :attr:`RepsDualSolution.converged`.
        iterations: LBFGS iterations of all phases (Newton steps counted as iterations),
            the most of any problem.
        problem_iterations: each problem's iterations, where the problems were solved one by
            one (empty for one problem: ``iterations`` is its count).
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
    iterations: int
    numbers: tuple[float, ...] | None = None
    """Where S = K = 1 and the solver has them as floats: (eta, xi, kl, cross_entropy,
    effective_sample_size, feature_error, dual_value) (:func:`single_solution` reads them)."""
    problem_iterations: tuple[int, ...] = ()

    def iterations_of(self, s: int) -> int:
        """Problem s's iterations."""
        return self.problem_iterations[s] if self.problem_iterations else self.iterations

    @property
    def sample_weights(self) -> Tensor:
        """(S, K, N) weights summed over options (the weights of a flat policy)."""
        return self.weights.sum(-1)

    def problem(self, s: int) -> RepsDualSolution:
        """Problem s as a :class:`RepsDualSolution`."""
        S = self.eta.shape[0]
        if not -S <= s < S:
            raise ValueError(f"problem must be in [0, {S}), got {s}")
        return RepsDualSolution(
            eta=self.eta[s],
            xi=self.xi[s],
            v=self.v[s],
            weights=self.weights[s],
            kl=self.kl[s],
            cross_entropy=self.cross_entropy[s],
            effective_sample_size=self.effective_sample_size[s],
            feature_error=float(self.feature_error[s]),
            dual_value=float(self.dual_value[s]),
            converged=bool(self.converged[s]),
            iterations=self.iterations_of(s),
        )


@dataclass(frozen=True)
class DualSolution:
    """Solution of the episodic HiREPS dual (:func:`~hireps_torch.dual.solve_episodic_dual`).

    Attributes:
        eta: temperature of the KL bound (inf when the returns carry no information).
        xi: multiplier of the entropy bound; 0 when inactive or when no bound was given.
        v: (F,) context-feature multipliers (empty without context features).
        weights: (N, O) new distribution over samples and options; sums to 1.
        sample_weights: (N,) weights.sum(-1), the weights for a flat policy.
        kl: realised KL(P || q p~); equals epsilon when the bound is active, never exceeds
            epsilon (1 + 1e-6).
        cross_entropy: realised E_P[-log p~(o|s,theta)]; equals kappa when that bound is active.
        effective_sample_size: 1 / sum_i sample_weights_i^2, between 1 and N.
        feature_error: max |sum_i w_i phi_i - phi_hat| (0 without context features).
        dual_value: dual objective at the optimum (finite).
        converged: whether every constraint holds to its tolerance and the solver met its
            gradient tolerance (see the module docstring); if not, a warning said what failed.
        iterations: LBFGS iterations.
    """

    eta: float
    xi: float
    v: Tensor
    weights: Tensor
    sample_weights: Tensor
    kl: float
    cross_entropy: float
    effective_sample_size: float
    feature_error: float
    dual_value: float
    converged: bool
    iterations: int


@dataclass(frozen=True)
class TimeIndexedDualSolution:
    """Solution of the time-indexed HiREPS dual
    (:func:`~hireps_torch.dual.solve_time_indexed_dual`).

    Steps are indexed k = 0..K-1 here (1..K in the equations).

    Attributes:
        eta: (K,) temperatures of the per-step KL bounds (all inf when the rewards carry no
            information).
        xi: (K,) multipliers of the per-step entropy bounds (0 where inactive or absent).
        v: (K, F) value-function weights: V_k(s) = v[k]^T phi(s).
        weights: (K, N, O) new distribution over samples and options per step; each step
            sums to 1.
        sample_weights: (K, N) weights.sum(-1), the weights of a flat policy per step.
        kl: (K,) realised KL(P_k || q p~_k); equals epsilon_k where the bound is active, never
            exceeds epsilon_k (1 + 1e-6).
        cross_entropy: (K,) realised E_P_k[-log p~_k]; <= kappa_k.
        effective_sample_size: (K,) 1 / sum_i w_ki^2 per step.
        feature_error: max abs violation of the chained feature constraints.
        dual_value: dual objective at the optimum (finite).
        converged: whether every constraint holds to its tolerance and the solver met its
            gradient tolerance (see the module docstring); if not, a warning said what failed.
        iterations: LBFGS iterations.
    """

    eta: Tensor
    xi: Tensor
    v: Tensor
    weights: Tensor
    sample_weights: Tensor
    kl: Tensor
    cross_entropy: Tensor
    effective_sample_size: Tensor
    feature_error: float
    dual_value: float
    converged: bool
    iterations: int

    def step(self, k: int) -> DualSolution:
        """Step k as a :class:`DualSolution` (weights (N, O), v = v[k]); ``feature_error``,
        ``dual_value``, ``converged`` and ``iterations`` are those of the whole problem."""
        K = self.eta.shape[0]
        if not 0 <= k < K:
            raise ValueError(f"step must be in [0, {K}), got {k}")
        return block_solution(self, k, self.v[k])


def block_solution(
    sol: RepsDualSolution | TimeIndexedDualSolution, k: int, v: Tensor
) -> DualSolution:
    """Block k of a K-block solution as a :class:`DualSolution` with value weights ``v``."""
    w = sol.weights[k]
    return DualSolution(
        eta=float(sol.eta[k]),
        xi=float(sol.xi[k]),
        v=v,
        weights=w,
        sample_weights=w.sum(-1),
        kl=float(sol.kl[k]),
        cross_entropy=float(sol.cross_entropy[k]),
        effective_sample_size=float(sol.effective_sample_size[k]),
        feature_error=sol.feature_error,
        dual_value=sol.dual_value,
        converged=sol.converged,
        iterations=sol.iterations,
    )


def single_solution(sol: PopulationDualSolution) -> DualSolution:
    """The :class:`DualSolution` of a one-block population of one (S = K = 1), its numbers
    read in one transfer (none where the solver gave them as floats)."""
    numbers = (
        sol.numbers
        or torch.cat(
            [
                sol.eta[0],
                sol.xi[0],
                sol.kl[0],
                sol.cross_entropy[0],
                sol.effective_sample_size[0],
                sol.feature_error,
                sol.dual_value,
            ]
        ).tolist()
    )
    eta, xi, kl, ce, ess, feature_error, dual_value = numbers
    w = sol.weights[0, 0]
    return DualSolution(
        eta=eta,
        xi=xi,
        v=sol.v[0],
        weights=w,
        sample_weights=w.sum(-1),
        kl=kl,
        cross_entropy=ce,
        effective_sample_size=ess,
        feature_error=feature_error,
        dual_value=dual_value,
        converged=bool(sol.converged[0]),
        iterations=sol.iterations,
    )


def stack_solutions(parts: list[PopulationDualSolution]) -> PopulationDualSolution:
    """The solutions of problems solved one by one (each S = 1) as one population's."""
    if len(parts) == 1:
        return parts[0]

    def cat(name: str) -> Tensor:
        return torch.cat([getattr(p, name) for p in parts])

    counts = tuple(p.iterations for p in parts)
    return PopulationDualSolution(
        eta=cat("eta"),
        xi=cat("xi"),
        v=cat("v"),
        weights=cat("weights"),
        kl=cat("kl"),
        cross_entropy=cat("cross_entropy"),
        effective_sample_size=cat("effective_sample_size"),
        feature_error=torch.stack([p.feature_error.reshape(()) for p in parts]),
        dual_value=torch.stack([p.dual_value.reshape(()) for p in parts]),
        converged=cat("converged"),
        iterations=max(counts),
        problem_iterations=counts,
    )


def block_kl(w: Tensor, log_resp: Tensor) -> Tensor:
    """(..., K) KL(P_k || q p~_k) of weights (..., K, N, O) against the old distribution."""
    logq = log_resp - math.log(w.shape[-2])
    logw = torch.log(w.clamp_min(1e-300))
    return torch.where(w > 0, w * (logw - logq), torch.zeros_like(w)).sum(dim=(-2, -1))


def block_cross_entropy(w: Tensor, log_resp: Tensor) -> Tensor:
    """(..., K) E_P_k[-log p~_k] of weights (..., K, N, O)."""
    return -(w * log_resp).sum(dim=(-2, -1))


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
    iterations: int,
) -> PopulationDualSolution:
    """The :class:`PopulationDualSolution` of weights w (S, K, N, O) with its diagnostics (KL,
    cross-entropy, effective sample size, feature error); all inputs float64 with a leading
    S (D (S, K, N, P), c (S, P))."""
    ws = w.sum(-1)  # (S, K, N)
    feat_err = w.new_zeros(w.shape[0])
    if D is not None and D.shape[-1] > 0:
        grad_v = torch.einsum("skn,sknp->sp", ws, D)
        if c is not None:
            grad_v = grad_v + c
        feat_err = grad_v.abs().amax(-1)
    return PopulationDualSolution(
        eta=eta,
        xi=xi,
        v=v,
        weights=w,
        kl=block_kl(w, log_resp),
        cross_entropy=block_cross_entropy(w, log_resp),
        effective_sample_size=1.0 / (ws**2).sum(dim=-1),
        feature_error=feat_err,
        dual_value=dual_value,
        converged=converged,
        iterations=iterations,
    )


def warn_if_collapsed(sol: PopulationDualSolution, epsilon: Tensor, stacklevel: int = 2) -> None:
    """Warn (``stacklevel`` frames above the caller; 2: the wrapper's caller) when a block's
    weights sit on ~one sample (epsilon (S, K))."""
    S, K, N, _ = sol.weights.shape
    ess = sol.effective_sample_size
    if sol.numbers is not None:  # one block, its numbers at hand
        bad = [[0, 0]] if sol.numbers[4] < 1.5 and sol.numbers[0] < math.inf else []
    else:
        bad = ((ess < 1.5) & (sol.eta < math.inf)).nonzero().tolist()
    if bad:
        which = ", ".join(
            ("" if S == 1 else f"problem {s}, ")
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
