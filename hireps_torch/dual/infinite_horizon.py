"""Infinite-horizon HiREPS: :func:`solve_infinite_horizon_dual`, the stationary dual with
restart probability 1 - gamma."""

from __future__ import annotations

import math
from collections.abc import Sequence

from torch import Tensor

from hireps_torch.checks import as_float
from hireps_torch.dual.inputs import common_inputs
from hireps_torch.dual.solutions import DualSolution, public
from hireps_torch.dual.solver import LbfgsSettings, solve_blocks

__all__ = ["check_gamma", "infinite_horizon_solution", "solve_infinite_horizon_dual"]


def solve_infinite_horizon_dual(
    rewards: Tensor,
    features: Tensor,
    next_features: Tensor,
    initial_features: Tensor,
    *,
    gamma: float,
    epsilon: float,
    log_responsibilities: Tensor | None = None,
    kappa: float | Tensor | None = None,
    max_iter: int = 300,
    population: bool = False,
) -> DualSolution:
    """Solve the stationary (infinite-horizon) HiREPS dual with restart probability 1 - gamma.

    Samples are transitions (s_i, a_i, r_i, s'_i) of the restart process; P_io ∝ p~_io^(1 + xi/eta)
    exp(delta_i / eta) with the Bellman error

        delta_i = r_i + gamma v^T phi(s'_i) - v^T phi(s_i),

    the dual is ``eta eps + xi kappa + (1 - gamma) v^T phi_hat_0 + eta log mean exp``, and at the
    optimum

        sum_i w_i (phi(s_i) - gamma phi(s'_i)) = (1 - gamma) phi_hat_0   (``feature_error``).

    Args:
        rewards: (N,) reward of each transition (one decision).
        features: (N, F) value features phi(s_i). Directions along which phi - gamma phi' has
            no spread are dropped; their constraint holds for every distribution when the start
            features agree, else an :class:`~hireps_torch.dual.InfeasibleConstraintsWarning`.
        next_features: (N, F) value features phi(s'_i) of the state reached.
        initial_features: (F,) mean value features of the start distribution, phi_hat_0.
        gamma: 1 - restart probability, in (0, 1).
        epsilon: KL bound, > 0.
        log_responsibilities: (N, O) log p~(o | s_i, a_i) or None (one option).
        kappa: absolute bound on the option cross-entropy or None (see
            :func:`~hireps_torch.dual.solve_episodic_dual`); with ``population`` also (S,).
        max_iter: LBFGS iterations per phase, an integer >= 1.
        population: the inputs hold S independent problems along a leading dimension
            (rewards (S, N), features (S, N, F), initial_features (F,) or (S, F), ...).

    Returns:
        :class:`~hireps_torch.dual.DualSolution` shaped as
        :func:`~hireps_torch.dual.solve_episodic_dual`'s; ``v`` (F,) the value-function
        weights; ``kl <= epsilon (1 + 1e-6)``; ``converged`` False comes with a warning.

    Raises:
        ValueError, TypeError: on non-finite or mis-shaped input, gamma outside (0, 1),
            epsilon <= 0, a negative kappa or a bad max_iter; each message names the value.
    """
    x = common_inputs(
        rewards, epsilon, log_responsibilities, kappa, max_iter, "rewards", population=population
    )
    g = check_gamma(gamma)
    phi = x.features("features", features)
    phi_next = x.features("next_features", next_features)
    if phi_next.shape != phi.shape:  # as given: (*lead, F)
        raise ValueError(
            f"next_features must have the shape of features {(*x.lead, phi.shape[-1])}, got "
            f"{(*x.lead, phi_next.shape[-1])}"
        )
    phi0 = x.feature_vector("initial_features", initial_features, phi.shape[-1])
    sol = infinite_horizon_solution(
        x.R[:, 0], x.lr[:, 0], x.eps, phi, phi_next, phi0, g, x.kappa, x.settings, stacklevel=3
    )
    return public(sol, population, blocks=False)


def infinite_horizon_solution(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    phi: Tensor,
    phi_next: Tensor,
    phi0: Tensor,
    gamma: float,
    kappa: Tensor | None,
    settings: LbfgsSettings,
    stacklevel: int = 2,
    seeds: Sequence[int] | None = None,
) -> DualSolution:
    """:func:`solve_infinite_horizon_dual` of S checked float64 problems (an (S, 1) solution): R
    (S, N), log_resp (S, N, O), eps (S, 1), phi and phi_next (S, N, F), phi0 (S, F), kappa (S, 1) or
    None; warnings ``stacklevel`` frames up (members named with their ``seeds``)."""
    S, N, F = phi.shape
    D = (gamma * phi_next - phi).reshape(S, 1, N, F)
    c = (1.0 - gamma) * phi0
    return solve_blocks(
        R[:, None], log_resp[:, None], eps, D, c, kappa, settings, stacklevel + 1, seeds=seeds
    )


def check_gamma(gamma: float) -> float:
    """gamma in (0, 1) as a float."""
    g = as_float("gamma", gamma)
    if not (math.isfinite(g) and 0.0 < g < 1.0):
        raise ValueError(f"gamma must be in (0, 1), got {gamma}")
    return g
