"""The generic K-block solver :func:`solve_reps_dual` (Newton steps and LBFGS in float64).

Returns and feature columns are scaled by exact powers of 2 (magnitudes from 1e-300 to 1e300 are
fine) and standardised (:mod:`~hireps_torch.dual.conditioning`); plain REPS goes to
:func:`~hireps_torch.dual.temperature.solve_temperature`, the rest to
:class:`~hireps_torch.dual.block_solver.BlockSolver`, then :mod:`~hireps_torch.dual.safeguards`.
What ``converged`` promises: :mod:`~hireps_torch.dual.safeguards`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import replace

import torch
from torch import Tensor

from hireps_torch._linalg import logsumexp
from hireps_torch._parallel import side_by_side
from hireps_torch.dual.block_solver import BlockSolver, LbfgsSettings
from hireps_torch.dual.conditioning import Standardised, standardise
from hireps_torch.dual.inputs import check_blocks, check_settings
from hireps_torch.dual.safeguards import Verdict, enforce_kl, judge, reachable_kappa
from hireps_torch.dual.solutions import (
    TENSORS,
    DualConvergenceWarning,
    DualSolution,
    InfeasibleConstraintsWarning,
    finish,
    member_name,
    warn_if_collapsed,
)
from hireps_torch.dual.temperature import log_temperatures, solve_temperature

__all__ = ["LbfgsSettings", "solve_blocks", "solve_reps_dual"]


def solve_reps_dual(
    R: Tensor,
    log_resp: Tensor,
    epsilon: float | Tensor,
    *,
    D: Tensor | None = None,
    c: Tensor | None = None,
    kappa: float | Tensor | None = None,
    max_iter: int = 300,
    tolerance_grad: float = 1e-7,
    converged_grad: float = 1e-6,
) -> DualSolution:
    """Solve the K-block HiREPS dual (see :mod:`hireps_torch.dual`).

    Args:
        R: (K, N) returns / rewards per block, finite, N >= 2.
        log_resp: (K, N, O) log responsibilities of the old policy (rows normalised; -inf for
            pruned options).
        epsilon: KL bounds, > 0: one float or (K,).
        D: (K, N, P) linear map from the stacked value vector v to the advantage offsets, or
            None when there are no features. Directions of v along which every block's D is
            constant over samples are dropped from the solve (their constraint holds for every
            distribution or for none: then a warning).
        c: (P,) linear term of the dual in v, or None (zero); needs D.
        kappa: absolute bounds on the option cross-entropy, >= 0: one float or (K,), or None
            for no bound; an infinite entry means no bound on that block (its xi is 0).
        max_iter: LBFGS iterations per phase, an integer >= 1.
        tolerance_grad: LBFGS stops when every standardised gradient entry is below this
            (finite, > 0).
        converged_grad: the solve counts as converged when every standardised gradient entry
            (constraint residual) is below this at the end (finite, > 0).

    Returns:
        A :class:`~hireps_torch.dual.DualSolution` in the caller's units with a block
        dimension (eta, xi, kl, ... (K,), weights (K, N, O)) and the stacked v (P,); its KL is
        at most epsilon (1 + 1e-6) on every block.

    Raises:
        ValueError, TypeError: on bad shapes, non-finite values, unnormalised
            responsibilities, epsilon <= 0, kappa < 0 or nonsensical solver options; each
            message names the value.
    """
    opts = check_settings(max_iter, tolerance_grad, converged_grad)
    inputs = check_blocks(R, log_resp, epsilon, D, c, kappa)
    return solve_blocks(*inputs, opts, stacklevel=3, collapse=False).problem(0)


def solve_blocks(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    D: Tensor | None,
    c: Tensor | None,
    kappa: Tensor | None,
    settings: LbfgsSettings,
    stacklevel: int = 2,
    collapse: bool = True,
    seeds: Sequence[int] | None = None,
) -> DualSolution:
    """:func:`solve_reps_dual` on S checked float64 problems: R (S, K, N), log_resp (S, K, N, O),
    eps (S, K), D (S, K, N, P), c (S, P), kappa (S, K). Each is solved alone (why:
    benchmarks/README.md, "One path"), side by side on idle cores; warnings (first
    :func:`member_name` of ``seeds``, the members' seeds, when S > 1) in order, then
    (``collapse``) where weights collapsed, ``stacklevel`` frames up."""
    S = R.shape[0]

    def one(x: Tensor, s: int) -> Tensor:  # a copy of its own: MKL rounds by alignment
        return x[s : s + 1].clone() if S > 1 else x

    def some(x: Tensor | None, s: int) -> Tensor | None:
        return None if x is None else one(x, s)

    def alone(s: int) -> tuple[DualSolution, list[_Warning]]:
        prefix = f"{member_name(s, seeds)}: " if S > 1 else ""
        Rs, lr, es = one(R, s), one(log_resp, s), one(eps, s)
        return _solve_one(Rs, lr, es, some(D, s), some(c, s), some(kappa, s), settings, prefix)

    size = log_resp[0].numel() + (0 if D is None else D[0].numel())  # one problem's
    solved = side_by_side(alone, range(S), R.device, size)
    for _, said in solved:
        for text, category in said:
            warnings.warn(text, category, stacklevel=stacklevel)
    sol = solved[0][0]
    if S > 1:  # the problems' (S = 1) solutions as one population's
        cat = {f.name: torch.cat([getattr(p, f.name) for p, _ in solved]) for f in TENSORS}
        sol = replace(sol, numbers=None, **cat)
    if collapse:
        warn_if_collapsed(sol, eps, stacklevel, seeds)
    return sol


_Warning = tuple[str, type[Warning]]


def _solve_one(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    D: Tensor | None,
    c: Tensor | None,
    kappa: Tensor | None,
    settings: LbfgsSettings,
    prefix: str,
) -> tuple[DualSolution, list[_Warning]]:
    """One problem (S = 1) of :func:`solve_blocks` and its warnings (text, category)."""
    S, K = R.shape[:2]
    if D is not None and D.shape[-1] == 0:  # zero-width features are no features
        D = c = None
    unbounded = kappa is None or not bool(torch.isfinite(kappa).any())
    if log_resp.shape[-1] > 1 and unbounded:
        return _factorised(R, log_resp, eps, D, c, settings, prefix)
    if K == 1 and D is None and unbounded:  # one option column: plain REPS
        sol = solve_temperature(R.view(-1), eps.item(), settings)
        if sol is not None:
            return sol, []
    r_scale = _pow2_scale(R.abs().amax(dim=(1, 2)))  # (S,)
    f_scale = _pow2_scale(R.new_zeros(S, 0) if D is None else D.abs().amax(dim=(1, 2)))  # (S, P)
    st = standardise(
        R * r_scale[:, None, None],
        None if D is None else D * f_scale[:, None, None, :],
        None if c is None else c * f_scale,
        eps,
    )
    kap = torch.full_like(eps, math.inf) if kappa is None else kappa
    kap_solve, unreachable, best = kap, torch.zeros_like(eps, dtype=torch.bool), kap
    if log_resp.shape[-1] > 1:
        kap_solve, unreachable, best = reachable_kappa(log_resp, eps, kap)
    # where the dual has no linear term each block's eta starts at its exact temperature at v0;
    # where it has one, at the small-epsilon eta (measured: benchmarks/README.md, dual_speed)
    start = log_temperatures(st.returns, eps) if c is None else None
    solver = BlockSolver(st, log_resp, eps, kap_solve, settings, start)
    end, relaxed = solver.run()
    prob = solver.prob
    _, eta_s, xi_s, u = prob.unpack(solver.x)
    eta_s, moved = enforce_kl(prob, eta_s, xi_s, u)
    P, g = end.weights, end.value
    if bool(moved.any()):
        P, g = prob.weights_at(eta_s, xi_s, u)[0], prob.value_at(eta_s, xi_s, u)
    failed = not bool(torch.isfinite(P).all() & torch.isfinite(g).all())
    if failed:  # never seen; should a solve fail numerically, keep the old one
        P = log_resp.exp() / R.shape[-1]
        P = P / P.sum(dim=(-2, -1), keepdim=True)
        st = replace(st, informative=torch.zeros_like(st.informative))
    optimal = end.converged & (not failed)
    verdict = judge(prob, P, kap, optimal, st.fixed_residual, settings.converged_grad)
    notes = [] if relaxed is None else [relaxed]
    if failed:
        notes.append("the solve failed numerically: the old distribution is kept")
    if bool(unreachable.any()):
        notes.append(_unreachable_text(kap[0], kap_solve[0], best[0], unreachable[0], eps[0]))
    if bool(moved.any()):
        notes.append(f"the KL bound was enforced after the solve on block(s) {_where(moved[0])}")
    infeasible = bool(unreachable.any()) or relaxed is not None
    said = _warning(verdict, notes, infeasible, prefix)
    eta, xi, v, dual = _caller_units(st, eta_s, xi_s, u, g)
    converged = torch.tensor([verdict.converged], device=R.device)
    sol = finish(
        P,
        log_resp,
        eta / r_scale[:, None],
        xi / r_scale[:, None],
        _times_pow2(v, f_scale, r_scale[:, None]),
        D,
        c,
        dual / r_scale,
        converged,
        torch.tensor([solver.iterations], device=R.device),
    )
    return sol, said


def _factorised(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    D: Tensor | None,
    c: Tensor | None,
    settings: LbfgsSettings,
    prefix: str,
) -> tuple[DualSolution, list[_Warning]]:
    """Without an entropy bound: P_io = w_i p~_io with w the one-option solution (exact;
    KL(P || q p~) = KL(w || q))."""
    row = logsumexp(log_resp)[..., None]
    one, said = _solve_one(R, row, eps, D, c, None, settings, prefix)
    w = one.weights * torch.exp(log_resp - row)
    w = w / w.sum(dim=(-2, -1), keepdim=True)
    sol = finish(
        w, log_resp, one.eta, one.xi, one.v, D, c, one.dual_value, one.converged, one.iterations
    )
    return sol, said


def _caller_units(
    st: Standardised, eta_s: Tensor, xi_s: Tensor, u: Tensor, g: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(eta, xi, v, dual value) in the (power-of-2 scaled) caller's units; without return
    information eta = inf, xi = inf where the entropy bound tilted, v = v0, dual = mean return."""
    if bool(st.informative):
        return eta_s * st.scale[:, None], xi_s * st.scale[:, None], st.value(u), st.dual_value(g)
    inf = torch.full_like(eta_s, math.inf)
    return inf, torch.where(xi_s > 0, inf, 0.0), st.v0, st.level


def _pow2_scale(m: Tensor) -> Tensor:
    """2^-e for m = f 2^e, f in [0.5, 1) (1 where m = 0), applied as two factors so it cannot
    overflow; at most 2^1022 (subnormal m: the scaled values stay below 0.5)."""
    _, e = torch.frexp(m.to(torch.float64))
    e = torch.where(m > 0, e, torch.zeros_like(e)).clamp_min(-1022).to(torch.float64)
    half = torch.floor(-e / 2)
    return torch.pow(2.0, half) * torch.pow(2.0, -e - half)


def _times_pow2(x: Tensor, num: Tensor, den: Tensor) -> Tensor:
    """x num / den for powers of 2 num and den, in two exact factors: no overflow on the way
    (num up to 2^1022 for subnormal features)."""
    k = torch.log2(num) - torch.log2(den)
    half = torch.floor(k / 2)
    return x * torch.pow(2.0, half) * torch.pow(2.0, k - half)


def _warning(verdict: Verdict, notes: list[str], infeasible: bool, prefix: str) -> list[_Warning]:
    """The one warning (text, category) for what a problem's solve could not deliver; none when it
    converged."""
    if verdict.converged and not infeasible:
        return []
    parts = list(notes) + list(verdict.parts)
    category: type[RuntimeWarning] = (
        InfeasibleConstraintsWarning if infeasible or verdict.infeasible else DualConvergenceWarning
    )
    return [(prefix + "the dual did not converge: " + "; ".join(parts), category)]


def _unreachable_text(
    kappa: Tensor, kap_solve: Tensor, best: Tensor, unreachable: Tensor, eps: Tensor
) -> str:
    """Why the entropy bound of some blocks was relaxed."""
    m = unreachable

    def text(x: Tensor) -> str:
        return ", ".join(f"{float(a):.6g}" for a in x[m])

    return (
        f"the entropy bound cannot be met within the KL bound on block(s) {_where(m)}: kappa "
        f"{text(kappa)}, but within epsilon {text(eps)} the cross-entropy reaches {text(best)} "
        f"at best; solved with kappa relaxed to {text(kap_solve)} (what half the KL budget "
        "reaches)"
    )


def _where(mask: Tensor) -> str:
    """'0, 2' for the True entries of a (K,) mask."""
    return ", ".join(str(int(k)) for k in mask.nonzero().flatten())
