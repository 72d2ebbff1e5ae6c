"""Episodic / contextual HiREPS: :func:`solve_episodic_dual` (the dual in
:mod:`hireps_torch.dual`'s docstring, one block)."""

from __future__ import annotations

from torch import Tensor

from hireps_torch.dual.inputs import centred, check_features, common_inputs
from hireps_torch.dual.solutions import DualSolution, public, warn_if_collapsed
from hireps_torch.dual.solver import LbfgsSettings, checked_settings, solve_blocks

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
        epsilon: KL bound, > 0. Values >= log N let the weights collapse onto one sample
            (a :class:`~hireps_torch.dual.DegenerateWeightsWarning` is issued).
        log_responsibilities: (N, O) log p~(o | s_i, theta_i) of the old policy, rows
            normalised over options ((S, N, O) with ``population``); None means one option
            (REPS).
        context_features: (N, F) context features phi(s_i) whose mean must be kept ((S, N, F)
            with ``population``); None means no context (plain episodic). Directions without
            spread in the samples (a constant column, all contexts equal, all-zero features;
            spread below 1e-14 of the column's magnitude) carry a constraint every
            distribution meets: they are dropped from the solve (v is unidentifiable along
            them).
        kappa: absolute bound on the expected option cross-entropy E_P[-log p~], >= 0;
            None (or inf) means no entropy bound (xi = 0); with ``population`` one float for
            all problems or an (S,) tensor, one per problem. A bound that no distribution within
            the KL bound meets (kappa = 0 with soft responsibilities, say) is relaxed to what
            half the KL budget reaches, with an
            :class:`~hireps_torch.dual.InfeasibleConstraintsWarning`.
        max_iter: LBFGS iterations per phase, an integer >= 1.
        population: the inputs hold S independent problems along a leading dimension; they
            are solved each as it is alone (side by side on idle cores; conditioned, judged and
            warned about on its own), and every field of the solution leads with S.

    Returns:
        :class:`~hireps_torch.dual.DualSolution`: eta, xi, kl, ... 0-d tensors, v (F,),
        weights (N, O) summing to 1 (with ``population``: (S,), (S, F), (S, N, O)) and
        ``kl <= epsilon (1 + 1e-6)``; ``converged`` False comes with a warning naming what
        failed (tolerances: :mod:`hireps_torch.dual.solutions`). Returns scaled by any positive
        factor give the same weights; constant returns give the old distribution (uniform
        sample weights), eta = inf and the return as the dual value.

    Raises:
        ValueError, TypeError: on non-finite returns or features, shape mismatches, N < 2,
            epsilon <= 0, a negative kappa or a bad max_iter; each message names the value.
    """
    opts = checked_settings(max_iter)
    R, eps, lr, kap = common_inputs(
        returns, epsilon, log_responsibilities, kappa, population=population
    )
    S, _, N = R.shape
    phi = None
    if context_features is not None:
        lead = (S, N) if population else (N,)
        phi = check_features(
            "context_features", context_features, *lead, population=population, device=R.device
        )
        phi = phi.reshape(S, N, -1)
    sol = episodic_solution(R[:, 0], lr[:, 0], eps, phi, kap, opts, stacklevel=3)
    return public(sol, population, blocks=False)


def episodic_solution(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    phi: Tensor | None,
    kappa: Tensor | None,
    settings: LbfgsSettings,
    stacklevel: int = 2,
) -> DualSolution:
    """:func:`solve_episodic_dual` of S problems (an (S, 1) solution) on inputs already
    checked: float64 returns R (S, N), log responsibilities (S, N, O) (normalised, log 0
    floored), epsilon (S, 1), context features phi (S, N, F) or None and kappa (S, 1) or
    None. Warnings are attributed
    ``stacklevel`` frames up (2: the caller of this function)."""
    S, N = R.shape
    D = None
    if phi is not None:
        # Centred features: v^T phi_hat - v^T phi_i = -v^T (phi_i - phi_hat); c = 0.
        D = -centred(phi).reshape(S, 1, N, -1)
    sol = solve_blocks(R[:, None], log_resp[:, None], eps, D, None, kappa, settings, stacklevel + 1)
    warn_if_collapsed(sol, eps, stacklevel)
    return sol
