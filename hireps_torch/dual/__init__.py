"""The REPS / HiREPS duals as pure functions, solved in float64 with ``torch.optim.LBFGS``.

Episodic / contextual HiREPS (Daniel, Neumann, Peters). Samples i = 1..N carry a return R_i,
context features phi_i and, for a hierarchical policy with options o = 1..O, the old policy's
responsibilities p~_io = pi_old(o | s_i, theta_i). The new sample distribution

    P_io  ∝  p~_io^(1 + xi/eta) · exp((R_i - v^T phi_i) / eta)

maximises the expected return subject to

    KL(P || q p~) <= epsilon                      (q = uniform over samples)
    E_P[-log p~(o | s, theta)] <= kappa           (option cross-entropy: options separate)
    sum_io P_io phi_i = phi_hat                   (context distribution kept)

and (eta > 0, xi >= 0, v) minimise the dual

    g(eta, xi, v) = eta epsilon + xi kappa + v^T phi_hat
                    + eta log[(1/N) sum_i sum_o exp(A_io / eta)],
    A_io = R_i - v^T phi_i + (eta + xi) log p~_io.

One option and xi = 0 give contextual REPS; no features give plain episodic REPS.

All duals of this package share one shape: K blocks (decision steps), each with an
"advantage" linear in one stacked value vector v,

    delta_k = R_k + D_k v,    g = c^T v + sum_k [eta_k eps_k + xi_k kappa_k
                                  + eta_k log((1/N) sum_io exp(A_kio / eta_k))],

so the episodic (K = 1, D = -(phi - phi_hat)), infinite-horizon (D = gamma phi' - phi,
c = (1 - gamma) phi_hat_0) and time-indexed (one block per decision step, D_k v =
v_{k+1}^T phi(s_{k+1}) - v_k^T phi(s_k), c = [phi_hat_1, 0, ..]; see
:func:`solve_time_indexed_dual`) duals reuse one solver, :func:`solve_reps_dual`.

A population of S independent duals (``population=True`` in the wrappers: every input with a
leading S) is solved problem by problem, each scaled, standardised, safeguarded and judged on
its own, so each answer is the one it gets alone. Every solver returns one type,
:class:`DualSolution`, whose fields lead with the batch shape (() for one problem, (S,) for a
population).

Modules, in reading order:

- :mod:`~hireps_torch.dual.episodic`, :mod:`~hireps_torch.dual.infinite_horizon`,
  :mod:`~hireps_torch.dual.time_indexed`: one public wrapper each (mirroring
  :mod:`hireps_torch.algorithms`): check the inputs, build (R, D, c), solve, report.
- :mod:`~hireps_torch.dual.solutions`: the solution type, its diagnostics, the warnings
  (and what ``converged`` promises).
- :mod:`~hireps_torch.dual.inputs`: the wrappers' and the generic solver's input checks.
- :mod:`~hireps_torch.dual.solver`: :func:`solve_reps_dual`: exact power-of-2 scaling, the
  solve, the safeguards, one warning (its docstring: the numerics).
- :mod:`~hireps_torch.dual.temperature`: plain REPS (one block, no features, one option
  column, no entropy bound): Newton on the temperature alone from the returns' moments.
- :mod:`~hireps_torch.dual.block_solver`: Newton steps with the exact curvature, then LBFGS in
  coordinates whitened by it, with the entropy bound's KKT phases (active sets), the fallback
  for infeasible feature constraints (recognised by weak duality), the projection solve for
  returns without information and the eta floor.
- :mod:`~hireps_torch.dual.safeguards`: the KL bound by construction (a final search on eta),
  the entropy bound's reachability, and the check of every constraint with its tolerance.
- :mod:`~hireps_torch.dual.conditioning`: value start, whitening and scaling of the problem.
- :mod:`~hireps_torch.dual.problem`: :class:`~hireps_torch.dual.problem.DualProblem`, the
  standardised K-block dual with its analytic gradient and curvature.
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
