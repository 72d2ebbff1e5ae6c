"""Episodic / contextual HiREPS: :func:`solve_episodic_dual` (the dual in
:mod:`hireps_torch.dual`'s docstring, one block)."""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

from hireps_torch.dual.inputs import centred, common_inputs
from hireps_torch.dual.solutions import DualSolution, public
from hireps_torch.dual.solver import LbfgsSettings, solve_blocks

__all__ = ["episodic_solution", "solve_episodic_dual"]


def solve_episodic_dual(
    returns: Tensor,
    *,
    epsilon: float,
    log_responsibilities: Tensor | None = None,
    context_features: Tensor | None = None,
    kappa: float | Tensor | None = None,
    max_iter: int = 300,
    population: bool = False,
) -> DualSolution:
    """Solve the episodic / contextual HiREPS dual and return the new sample weights.

    Args:
        returns: (N,) return of each sample, N >= 2; (S, N) with ``population``.
        epsilon: KL bound, > 0; values >= log N collapse the weights onto one sample (a
            :class:`~hireps_torch.dual.DegenerateWeightsWarning`).
        log_responsibilities: (N, O) log p~(o | s_i, theta_i) of the old policy, rows
            normalised over options ((S, N, O) with ``population``); None means one option
            (REPS).
        context_features: (N, F) context features phi(s_i) whose mean must be kept ((S, N, F)
            with ``population``); None means no context. Directions without spread in the
            samples are dropped from the solve.
        kappa: absolute bound on the expected option cross-entropy E_P[-log p~], >= 0;
            None (or inf) means no entropy bound (xi = 0); with ``population`` also an (S,)
            tensor. A bound no distribution within the KL bound meets is relaxed to what half
            the KL budget reaches, with an :class:`~hireps_torch.dual.InfeasibleConstraintsWarning`.
        max_iter: LBFGS iterations per phase, an integer >= 1.
        population: the inputs hold S independent problems along a leading dimension, each
            solved as alone; every field of the solution leads with S.

    Returns:
        :class:`~hireps_torch.dual.DualSolution`: eta, xi, kl, ... 0-d tensors, v (F,),
        weights (N, O) summing to 1 (with ``population``: (S,), (S, F), (S, N, O)) and
        ``kl <= epsilon (1 + 1e-6)``; ``converged`` False comes with a warning. Constant
        returns give the old distribution, eta = inf and the return as the dual value.

    Raises:
        ValueError, TypeError: on non-finite returns or features, shape mismatches, N < 2,
            epsilon <= 0, a negative kappa or a bad max_iter; each message names the value.
    """
    x = common_inputs(
        returns, epsilon, log_responsibilities, kappa, max_iter, population=population
    )
    phi = None if context_features is None else x.features("context_features", context_features)
    sol = episodic_solution(x.R[:, 0], x.lr[:, 0], x.eps, phi, x.kappa, x.settings, stacklevel=3)
    return public(sol, population, blocks=False)


def episodic_solution(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    phi: Tensor | None,
    kappa: Tensor | None,
    settings: LbfgsSettings,
    stacklevel: int = 2,
    seeds: Sequence[int] | None = None,
) -> DualSolution:
    """:func:`solve_episodic_dual` of S checked float64 problems (an (S, 1) solution): R (S, N),
    log_resp (S, N, O), eps (S, 1), phi (S, N, F) or None, kappa (S, 1) or None; warnings
    ``stacklevel`` frames up (members named with their ``seeds``)."""
    S, N = R.shape
    D = None
    if phi is not None:
        # Centred features: v^T phi_hat - v^T phi_i = -v^T (phi_i - phi_hat); c = 0.
        D = -centred(phi).reshape(S, 1, N, -1)
    one_block = R[:, None], log_resp[:, None], eps
    return solve_blocks(*one_block, D, None, kappa, settings, stacklevel + 1, seeds=seeds)
