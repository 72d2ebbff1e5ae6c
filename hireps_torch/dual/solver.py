"""The generic K-block solver :func:`solve_reps_dual` (LBFGS in float64).

Numerics: everything in float64 whatever the input dtype. The problem is first standardised
(:mod:`hireps_torch.dual.conditioning`); eta and xi live in log space; log-sum-exp subtracts the
max. The entropy bound is handled by its KKT conditions: the dual is solved with xi free, then
re-solved with xi = 0 exactly for blocks whose xi ended ~0 with the bound slack; a block whose xi
collapsed with the bound still violated (the log-space gradient vanishes there) restarts from the
xi that meets it, and ``converged`` checks the bound itself. When no distribution within the KL
bound meets the feature constraints (few samples against many features, common in the
infinite-horizon dual) the dual is unbounded below; the solver detects it, warns
(:class:`~hireps_torch.dual.InfeasibleConstraintsWarning`) and re-solves with a ridge on the
standardised u, which turns the feature constraints into a quadratic penalty and keeps the KL
bound (``feature_error`` then reports the remaining violation).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from hireps_torch.checks import as_f64
from hireps_torch.dual.conditioning import Standardised, standardise
from hireps_torch.dual.problem import DualProblem
from hireps_torch.dual.solutions import (
    InfeasibleConstraintsWarning,
    RepsDualSolution,
    block_cross_entropy,
    block_kl,
    finish,
)

__all__ = ["LbfgsSettings", "solve_blocks", "solve_reps_dual"]

_CONFLICT_RIDGE = 1.0e-2  # ridge on the standardised v when the feature constraints conflict


def solve_reps_dual(
    R: Tensor,
    log_resp: Tensor,
    epsilon: Tensor,
    *,
    D: Tensor | None = None,
    c: Tensor | None = None,
    kappa: Tensor | None = None,
    max_iter: int = 300,
    tolerance_grad: float = 1e-7,
    converged_grad: float = 1e-6,
) -> RepsDualSolution:
    """Solve the K-block HiREPS dual (see :mod:`hireps_torch.dual`).

    Args:
        R: (K, N) returns / rewards per block.
        log_resp: (K, N, O) log responsibilities of the old policy (rows normalised).
        epsilon: (K,) KL bounds, > 0.
        D: (K, N, P) linear map from the stacked value vector v to the advantage offsets, or
            None when there are no features.
        c: (P,) linear term of the dual in v, or None (zero).
        kappa: (K,) absolute bounds on the option cross-entropy, or None for no bound; an
            infinite entry means no bound on that block (its xi is 0).
        max_iter: LBFGS iterations per phase.
        tolerance_grad: LBFGS stops when every standardised gradient entry is below this.
        converged_grad: the solve counts as converged when every standardised gradient entry
            (constraint residual) is below this at the end.

    Returns:
        A :class:`~hireps_torch.dual.RepsDualSolution` in the caller's units.
    """
    return solve_blocks(
        as_f64("R", R),
        log_resp.to(torch.float64),
        epsilon.to(torch.float64),
        None if D is None else D.to(torch.float64),
        None if c is None else c.to(torch.float64),
        None if kappa is None else kappa.to(torch.float64),
        LbfgsSettings(max_iter, tolerance_grad, converged_grad),
        stacklevel=3,
    )


@dataclass(frozen=True)
class LbfgsSettings:
    """LBFGS iterations per phase and the two gradient tolerances of :func:`solve_reps_dual`."""

    max_iter: int = 300
    tolerance_grad: float = 1e-7
    converged_grad: float = 1e-6


def solve_blocks(
    R: Tensor,
    log_resp: Tensor,
    eps: Tensor,
    D: Tensor | None,
    c: Tensor | None,
    kappa: Tensor | None,
    settings: LbfgsSettings,
    stacklevel: int = 2,
) -> RepsDualSolution:
    """:func:`solve_reps_dual` on float64 inputs that the caller has already checked (the
    wrappers, :func:`solve_reps_dual`); an
    :class:`~hireps_torch.dual.InfeasibleConstraintsWarning` is attributed ``stacklevel``
    frames up (2: the caller of this function)."""
    K, N = R.shape
    if log_resp.shape[-1] > 1 and (kappa is None or not bool(torch.isfinite(kappa).any())):
        # Without an entropy bound (xi = 0) the options enter the dual only through
        # sum_o p~_io: P_io = w_i p~_io, with w the one-option solution. Solving that is exact
        # and O times cheaper (e.g. 100 hard-gated options).
        row = torch.logsumexp(log_resp, dim=-1, keepdim=True)
        one = solve_blocks(R, row, eps, D, c, None, settings, stacklevel + 1)
        w = one.weights * torch.exp(log_resp - row)
        w = w / w.sum(dim=(1, 2), keepdim=True)
        return finish(
            w, log_resp, one.eta, one.xi, one.v, D, c, one.dual_value, one.converged, one.iterations
        )
    st = standardise(R, D, c, eps)
    if not st.informative:
        # No return information (beyond what the features fix): every distribution that keeps
        # the features is optimal; keep the old one.
        w = log_resp.exp() / N
        w = w / w.sum(dim=(1, 2), keepdim=True)
        eta = torch.full((K,), math.inf, dtype=torch.float64)
        xi = torch.zeros(K, dtype=torch.float64)
        v = torch.zeros(0 if D is None else D.shape[-1], dtype=torch.float64)
        return finish(w, log_resp, eta, xi, v, D, c, math.nan, True, 0)
    kap = torch.full((K,), math.inf, dtype=torch.float64) if kappa is None else kappa
    solver = _BlockSolver(st, log_resp, eps, kap, settings)
    end, relaxed = solver.run()
    if relaxed is not None:
        warnings.warn(relaxed, InfeasibleConstraintsWarning, stacklevel=stacklevel)
    _, eta_s, xi_s, u = solver.prob.unpack(solver.x)
    eta, xi, v = eta_s * st.scale, xi_s * st.scale, st.value(u)
    dual_value = st.dual_value(end.value)
    return finish(
        end.weights, log_resp, eta, xi, v, D, c, dual_value, end.converged, solver.iterations
    )


class _End(NamedTuple):
    """Where a solve ended: gradient tolerance met, dual value, weights (K, N, O)."""

    converged: bool
    value: Tensor
    weights: Tensor


class _Whitened:
    """The dual in the coordinates z of x = x0 + L^-T z (x = x0 + z when L is None), as the
    closure LBFGS evaluates: with L L^T the curvature at x0 the Hessian in z is ~I there."""

    def __init__(self, prob: DualProblem, x0: Tensor, L: Tensor | None) -> None:
        self.prob, self.x0, self.L = prob, x0, L
        self.z = torch.zeros_like(x0)

    def x(self) -> Tensor:
        if self.L is None:
            return self.x0 + self.z
        step: Tensor = torch.linalg.solve_triangular(self.L.T, self.z[:, None], upper=True)
        return self.x0 + step[:, 0]

    def __call__(self) -> Tensor:
        g, grad = self.prob.value_and_grad(self.x())
        if self.L is not None:
            grad = torch.linalg.solve_triangular(self.L, grad[:, None], upper=False)[:, 0]
        self.z.grad = grad
        return g


class _BlockSolver:
    """LBFGS on one standardised problem; ``x`` holds the current point, ``iterations`` the
    LBFGS iterations of all phases so far."""

    def __init__(
        self,
        st: Standardised,
        log_resp: Tensor,
        eps: Tensor,
        kappa: Tensor,
        settings: LbfgsSettings,
    ) -> None:
        self.bounded = torch.isfinite(kappa)  # blocks with an entropy bound
        kap = torch.where(self.bounded, kappa, 0.0)
        self.prob = DualProblem(st.returns, st.D, st.c, log_resp, eps, kap)
        self.entropy_bound = self.prob.multi and bool(self.bounded.any())
        self.settings = settings
        self.x = self.prob.start()
        self.iterations = 0

    def run(self) -> tuple[_End, str | None]:
        """Solve; relax the feature constraints to a penalty where they cannot be met (the
        second item is then the warning text)."""
        prob = self.prob
        x_start = self.x.clone()
        end = self.solve()
        # An unconverged solve that broke the KL bound ran off the same way, only more slowly.
        ran_off = not end.converged and self.breaks_kl(end.weights)
        conflict = bool(prob.P) and prob.shows_conflict(self.x, end.value)
        if not (prob.P and (ran_off or conflict)):
            return end, None
        end, kl_kept = self.relax(x_start)
        why = (
            "the feature constraints cannot be met within the KL bound"
            if conflict
            else "the solve broke the KL bound before converging"
        )
        kept = (
            "the KL bound is kept"
            if kl_kept
            else "the KL bound is STILL broken (far too few samples for the features)"
        )
        text = (
            f"{why} epsilon = {prob.eps.tolist()} (too few samples for the {prob.P} features?): "
            f"they are relaxed to a quadratic penalty (ridge {prob.ridge:g} on the "
            f"standardised value weights) and {kept}; see feature_error and kl"
        )
        return end._replace(converged=False), text

    def relax(self, x_start: Tensor) -> tuple[_End, bool]:
        """Re-solve from x_start with a ridge on v, stronger while the KL bound stays broken;
        returns the last solve and whether it kept the KL bound.

        No distribution within the KL bound meets the feature constraints: either none at all
        does (c lies outside the convex hull of the rows of -D, typical of few samples against
        many features) or only ones with KL > epsilon do. The dual is then unbounded below (eta
        or v run off). A ridge on v bounds it again: the feature constraints become a quadratic
        penalty while the KL bound, the point of REPS, still holds (the alternative, the
        closest distribution that meets them, can collapse onto a single sample and wreck the
        policy).
        """
        for factor in (1.0, 10.0, 100.0, 1e3, 1e4):
            self.prob.ridge = factor * _CONFLICT_RIDGE
            self.x = x_start.clone()
            end = self.solve()
            if not self.breaks_kl(end.weights):
                return end, True
        return end, False

    def breaks_kl(self, w: Tensor) -> bool:
        """Whether weights (K, N, O) exceed some block's KL bound (beyond round-off)."""
        return bool((block_kl(w, self.prob.lr) > 1.01 * self.prob.eps + 1e-3).any())

    def solve(self) -> _End:
        """The LBFGS phases of one solve: the entropy bound's KKT phases, then up to two
        resumes of a stalled LBFGS."""
        end = self.entropy_kkt() if self.entropy_bound else self.phase()
        for _ in range(2):
            # a stalled LBFGS (its preconditioner, the curvature at the phase's start, gone
            # stale) resumes with the curvature where it stopped
            if end.converged or not bool(torch.isfinite(self.x).all()):
                break
            end = self.phase()
        if self.entropy_bound:
            # the log-space gradient hides a violated bound when xi ~0: check it directly
            ce = block_cross_entropy(end.weights, self.prob.lr)
            kap, bounded = self.prob.kappa, self.bounded
            met = bool((ce[bounded] <= kap[bounded] + 1e-6).all())
            end = end._replace(converged=end.converged and met)
        return end

    def entropy_kkt(self) -> _End:
        """KKT for xi >= 0: solve with xi free; where xi ends ~0 with the bound slack, switch
        it off and re-solve (then xi = 0 exactly and the bound holds as inequality)."""
        prob, K = self.prob, self.prob.K
        prob.xi_on[:] = self.bounded
        end = self.phase()
        for _ in range(3):
            # In log space the dual is nearly flat in xi below the xi that meets the bound (the
            # xi-gradient xi (kappa - CE) vanishes with xi): a line search can jump there and
            # LBFGS stops with xi ~0 and the bound violated. Restart from the xi that meets the
            # bound with the rest held fixed.
            ce = block_cross_entropy(end.weights, prob.lr)
            stuck = prob.xi_on & (ce > prob.kappa + 1e-6)
            if not bool(stuck.any()):
                break
            log_xi = prob.log_xi_meeting_bound(self.x)
            self.x[K : 2 * K] = torch.where(stuck, log_xi, self.x[K : 2 * K])
            end = self.phase()
        ce = block_cross_entropy(end.weights, prob.lr)
        slack = (self.x[K : 2 * K].exp() < 1e-6) & (ce <= prob.kappa + 1e-9)
        if bool(slack.any()):
            prob.xi_on &= ~slack
            end = self.phase()
        return end

    def phase(self) -> _End:
        """One LBFGS solve from x. With options, LBFGS runs in whitened coordinates (see
        :class:`_Whitened`), which saves iterations: the xi direction is badly scaled against
        eta and v otherwise (measured: with one option the plain problem is as well scaled)."""
        x0 = self.x.clone()
        L: Tensor | None = None
        if self.prob.multi:
            try:
                L = torch.linalg.cholesky(self.prob.curvature(x0))
            except RuntimeError:
                pass
        objective = _Whitened(self.prob, x0, L)
        opt = torch.optim.LBFGS(
            [objective.z],
            lr=1.0,
            max_iter=self.settings.max_iter,
            tolerance_grad=self.settings.tolerance_grad,
            tolerance_change=1e-15,
            history_size=20,
            line_search_fn="strong_wolfe",
        )
        opt.step(objective)  # type: ignore[no-untyped-call,unused-ignore]  # untyped in torch
        self.iterations += int(opt.state[objective.z].get("n_iter", 0))
        self.x = objective.x()
        g, grad, P = self.prob.evaluate(self.x)
        return _End(float(grad.abs().max()) <= self.settings.converged_grad, g, P)
