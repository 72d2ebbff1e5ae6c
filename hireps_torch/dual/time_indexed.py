"""Time-indexed HiREPS: :func:`solve_time_indexed_dual`, one distribution per decision step
k = 1..K, the steps chained by feature consistency.

Sample i is an episode of K decisions (states s_k,i, rewards R_k,i). Step k's
P_k,io ∝ p~_k,io^(1 + xi_k/eta_k) exp(delta_k,i / eta_k) uses per-step values V_k(s) = v_k^T phi(s):

    delta_k,i = R_k,i + v_{k+1}^T phi(s_{k+1,i}) - v_k^T phi(s_k,i),    V_{K+1} = 0,
    g = v_1^T phi_hat_1 + sum_k [eta_k eps_k + xi_k kappa_k
                                 + eta_k log((1/N) sum_io exp(A_k,io / eta_k))],
    A_k,io = delta_k,i + (eta_k + xi_k) log p~_k,io.

At the optimum KL_k = eps_k, E_P_k[-log p~_k] <= kappa_k and (``feature_error``: the largest
violation)

    sum_i w_1i phi(s_1i) = phi_hat_1,
    sum_i w_ki phi(s_ki) = sum_i w_{k-1,i} phi(s_ki)   (k >= 2; s_ki follows s_{k-1,i}).

Solved by :func:`~hireps_torch.dual.solve_reps_dual` with the stacked v = [v_1 .. v_K], v_1^T
phi_hat_1 folded into step 1 (D_1 = -(phi(s_1) - phi_hat_1) in slot 1, c = 0).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import torch
from torch import Tensor

from hireps_torch.dual.inputs import centred, common_inputs
from hireps_torch.dual.solutions import DualSolution, public
from hireps_torch.dual.solver import LbfgsSettings, solve_blocks

__all__ = ["solve_time_indexed_dual", "time_indexed_solution"]


def solve_time_indexed_dual(
    rewards: Tensor,
    features: Tensor,
    *,
    epsilon: float | Tensor,
    log_responsibilities: Tensor | None = None,
    kappa: float | Tensor | None = None,
    initial_features: Tensor | None = None,
    max_iter: int = 300,
    population: bool = False,
) -> DualSolution:
    """Solve the time-indexed HiREPS dual (see the module docstring).

    Args:
        rewards: (N, K) reward of each episode at each decision step, N >= 2, K >= 1.
        features: (N, K, F) value features phi(s_k,i) of the state where step k's decision
            was taken. Directions without spread within a step are dropped from the solve.
        epsilon: KL bound per step, > 0: one float or (K,); values >= log N collapse the
            weights (a :class:`~hireps_torch.dual.DegenerateWeightsWarning`).
        log_responsibilities: (N, K, O) log p~_k(o | s_k,i, theta_k,i) of each step's old
            policy, normalised over options (-inf for options a step does not have); None
            means one option per step.
        kappa: absolute bound on each step's option cross-entropy, >= 0: one float or (K,)
            (with ``population`` also (S, K)); inf leaves that step unbounded; None means no
            bound (xi = 0).
        initial_features: (F,) mean features of the start distribution, phi_hat_1; by default
            the sample mean of ``features[:, 0]``.
        max_iter: LBFGS iterations per phase, an integer >= 1.
        population: the inputs hold S independent problems along a leading dimension
            (rewards (S, N, K), features (S, N, K, F), initial_features (F,) or (S, F), ...).

    Returns:
        :class:`~hireps_torch.dual.DualSolution` with a step dimension: eta, xi, kl, ... (K,),
        v (K, F) (V_k(s) = v[k]^T phi(s)), ``weights`` (K, N, O), each step summing to 1
        (``step(k)``: step k alone), ``kl <= epsilon (1 + 1e-6)`` per step. A step whose KL
        bound is inactive has eta at its floor (e^-10 of the return spread) and KL below
        epsilon. ``converged`` False comes with a warning.

    Raises:
        ValueError, TypeError: on non-finite rewards or features, shape mismatches, N < 2,
            K < 1, epsilon <= 0, a negative kappa or a bad max_iter; each message names the
            offending value.
    """
    x = common_inputs(
        rewards,
        epsilon,
        log_responsibilities,
        kappa,
        max_iter,
        "rewards",
        per_step=True,
        population=population,
    )
    S, K, N = x.R.shape
    phi = x.features("features", features).transpose(1, 2)  # (S, K, N, F)
    F = phi.shape[-1]
    phi1 = None
    if initial_features is not None:
        phi1 = x.feature_vector("initial_features", initial_features, F)
    sol = time_indexed_solution(x.R, x.lr, x.eps, phi, phi1, x.kappa, x.settings, stacklevel=3)
    return public(replace(sol, v=sol.v.reshape(S, K, F)), population, blocks=True)


def time_indexed_solution(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    phi: Tensor,
    phi1: Tensor | None,
    kappa: Tensor | None,
    settings: LbfgsSettings,
    stacklevel: int = 2,
    seeds: Sequence[int] | None = None,
) -> DualSolution:
    """:func:`solve_time_indexed_dual` of S checked float64 problems (an (S, K) solution, v
    (S, K F)): R (S, K, N), log_resp (S, K, N, O), eps (S, K), phi (S, K, N, F), phi1 (S, F) or
    None (the sample mean), kappa (S, K) or None; warnings ``stacklevel`` frames up (members
    named with their ``seeds``). The map D (S, K, N, K F) chains the steps: block k holds
    -phi(s_k,i) in slot k, phi(s_k+1,i) in k + 1."""
    S, K, N, F = phi.shape
    D = torch.zeros(S, K, N, K, F, dtype=torch.float64, device=phi.device)
    steps = torch.arange(K, device=phi.device)
    D[:, steps, :, steps] = -phi.transpose(0, 1)
    D[:, steps[:-1], :, steps[1:]] = phi[:, 1:].transpose(0, 1)
    if phi1 is None:
        D[:, 0, :, 0] = -centred(phi[:, 0])  # = phi_hat_1 - phi(s_1)
    else:
        D[:, 0, :, 0] += phi1[:, None, :]
    D = D.reshape(S, K, N, K * F)
    return solve_blocks(R, log_resp, eps, D, None, kappa, settings, stacklevel + 1, seeds=seeds)
