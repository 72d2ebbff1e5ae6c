"""The REPS / HiREPS duals as pure functions, solved in float64 by Newton steps and LBFGS.

Episodic / contextual HiREPS (Daniel, Neumann, Peters): samples i = 1..N carry a return R_i, context
features phi_i and the old policy's responsibilities p~_io = pi_old(o | s_i, theta_i) for options
o = 1..O. The new sample distribution

    P_io  ∝  p~_io^(1 + xi/eta) · exp((R_i - v^T phi_i) / eta)

maximises the expected return subject to

    KL(P || q p~) <= epsilon                      (q = uniform over samples)
    E_P[-log p~(o | s, theta)] <= kappa           (option cross-entropy: options separate)
    sum_io P_io phi_i = phi_hat                   (context distribution kept)

and (eta > 0, xi >= 0, v) minimise the dual

    g(eta, xi, v) = eta epsilon + xi kappa + v^T phi_hat
                    + eta log[(1/N) sum_i sum_o exp(A_io / eta)],
    A_io = R_i - v^T phi_i + (eta + xi) log p~_io.

One option and xi = 0 give contextual REPS; no features give plain episodic REPS. Each dual here is
a K-block dual (delta_k = R_k + D_k v, linear term c^T v) solved by :func:`solve_reps_dual`:
episodic (K = 1, D = -(phi - phi_hat)), infinite-horizon (D = gamma phi' - phi, c = (1 - gamma)
phi_hat_0), time-indexed (:func:`solve_time_indexed_dual`). ``population=True`` solves S independent
duals (inputs with a leading S), each as alone; every solver returns a :class:`DualSolution` led by
the batch shape.
"""

from hireps_torch.dual.episodic import solve_episodic_dual
from hireps_torch.dual.infinite_horizon import solve_infinite_horizon_dual
from hireps_torch.dual.solutions import (
    DegenerateWeightsWarning,
    DualConvergenceWarning,
    DualSolution,
    InfeasibleConstraintsWarning,
)
from hireps_torch.dual.solver import solve_reps_dual
from hireps_torch.dual.time_indexed import solve_time_indexed_dual

__all__ = [
    "DegenerateWeightsWarning",
    "DualConvergenceWarning",
    "DualSolution",
    "InfeasibleConstraintsWarning",
    "solve_episodic_dual",
    "solve_infinite_horizon_dual",
    "solve_reps_dual",
    "solve_time_indexed_dual",
]
