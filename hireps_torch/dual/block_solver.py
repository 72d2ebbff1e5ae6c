"""LBFGS on one standardised K-block dual: :class:`BlockSolver`.

The entropy bound is handled by its KKT conditions: the dual is solved with xi free, then
re-solved with xi = 0 exactly for blocks whose xi ended ~0 with the bound slack; a block whose xi
collapsed with the bound still violated (the log-space gradient vanishes there) restarts from the
xi that meets it. When no distribution within the KL bound meets the feature constraints the
dual is unbounded below; the solver detects it and re-solves with a ridge on the standardised u
(see :meth:`BlockSolver.relax`). Returns without information (``Standardised.informative``
False) are solved with eta held at 1 and R = 0: the dual then yields the closest distribution
(in KL) to the old one that meets the entropy and feature constraints, and the old one itself
when it meets them already.

A block whose KL bound is inactive (rewards that the features cancel, e.g. all 0 before a
contact) has its optimum at eta = 0, where v becomes ill-conditioned (curvature ~1/eta): eta is
held at a floor (:func:`eta_floor`), lifted off it at every phase start if the KL bound breaks
there (:meth:`BlockSolver.unstick`), and a solve that LBFGS leaves short of its tolerance gets
Newton steps with the exact curvature (:meth:`BlockSolver.polish`). None of this changes a solve
that LBFGS completes with every eta above its floor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from hireps_torch.dual.conditioning import Standardised
from hireps_torch.dual.problem import LOG_ETA_MIN, DualProblem
from hireps_torch.dual.safeguards import enforce_kl
from hireps_torch.dual.solutions import block_cross_entropy, block_kl

__all__ = ["BlockSolver", "LbfgsSettings"]

_CONFLICT_RIDGE = 1.0e-2  # ridge on the standardised v when the feature constraints conflict
_LOG_ETA_FLOOR = -10.0  # eta_k >= e^-10 of block k's return spread: see eta_floor


def eta_floor(st: Standardised) -> Tensor:
    """(K,) lower clamp of log eta per block (standardised units): e^-10 of the block's own
    return spread, or of the common spread for a block whose returns do not vary (all 0, say),
    and never below ``LOG_ETA_MIN``.

    An eta that falls this low belongs to a KL bound that is inactive (eta -> 0: rewards that
    the features cancel) or binds only at a temperature where that block's weights move its
    return by a negligible e^-10 of its spread; held there, the v-curvature ~1/eta stays
    within float64's reach (at e^-30 it did not: such solves stalled with the constraints
    off) and the block's KL stays below epsilon.
    """
    assert st.reward_spread is not None
    spread = st.reward_spread.clamp(max=1.0)
    rel = torch.where(spread > 1e-13, spread, torch.ones_like(spread))
    return (_LOG_ETA_FLOOR + rel.log()).clamp_min(LOG_ETA_MIN)


@dataclass(frozen=True)
class LbfgsSettings:
    """LBFGS iterations per phase and the two gradient tolerances of
    :func:`~hireps_torch.dual.solve_reps_dual` (checked by
    :func:`~hireps_torch.dual.inputs.check_settings`)."""

    max_iter: int = 300
    tolerance_grad: float = 1e-7
    converged_grad: float = 1e-6


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


class BlockSolver:
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
        self.prob.log_eta_min = eta_floor(st)
        self.x = self.prob.start()
        self.iterations = 0
        self.informative = st.informative
        if not st.informative:  # the projection solve: R = 0 and eta held at 1
            self.prob.eta_on[:] = False
            self.x[: self.prob.K] = 0.0

    def old_distribution(self) -> _End | None:
        """The old distribution q p~ (computed exactly) if it meets the entropy and feature
        constraints, else None."""
        prob, K = self.prob, self.prob.K
        w = prob.lr.exp() / prob.N
        w = w / w.sum(dim=(1, 2), keepdim=True)
        ce = block_cross_entropy(w, prob.lr)
        if bool((self.bounded & (ce > prob.kappa + 1e-6)).any()):
            return None
        g, grad, _ = prob.evaluate(self.x)  # x: v = 0, xi off
        if prob.P and float(grad[2 * K :].abs().max()) > self.settings.converged_grad:
            return None
        return _End(True, g, w)

    def run(self) -> tuple[_End, str | None]:
        """Solve; relax the feature constraints to a penalty where they cannot be met (the
        second item is then the warning text)."""
        prob = self.prob
        x_start = self.x.clone()
        old = None if self.informative else self.old_distribution()
        if old is not None:
            return old, None
        end = self.solve()
        # An unconverged solve that broke the KL bound ran off the same way, only more slowly
        # (the projection solve does not bound the KL: the safeguard after it does).
        ran_off = self.informative and not end.converged and self.breaks_kl(end.weights)
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
            else "the KL bound, still broken (far too few samples for the features?), is "
            "enforced by raising eta"
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
        resumes of a stalled LBFGS, then Newton steps if it still stopped short."""
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
        if not end.converged and bool(torch.isfinite(self.x).all()):
            end = self.polish(end)
        return end

    def polish(self, end: _End, steps: int = 8) -> _End:
        """Newton steps with the exact curvature (:meth:`DualProblem.curvature`, the Hessian
        near the optimum) on the moving coordinates, each halved until it shrinks the merit
        (largest gradient entry or entropy-bound excess). LBFGS stops where the dual is flat to
        round-off in value but not yet in gradient (v-curvature ~1/eta with a block at its eta
        floor, where xi is tiny too); Newton steps need only the gradient to be accurate. A
        bound left violated first gets the xi that meets it (eta, v held)."""
        prob, K = self.prob, self.prob.K
        x0, merit0 = self.x.clone(), self._merit(prob.evaluate(self.x)[1], end.weights)
        over = prob.xi_on & (self._excess(end.weights) > 0)
        if bool(over.any()):
            log_xi = prob.log_xi_meeting_bound(self.x)
            self.x[K : 2 * K] = torch.where(over, log_xi, self.x[K : 2 * K])
        # an eta still sinking just above its floor (KL below epsilon) belongs there: hold it
        _, grad, _ = prob.evaluate(self.x)
        sinking = prob.eta_free(self.x) & (grad[:K] > 0) & (self.x[:K] < prob.log_eta_min + 2.0)
        self.x[:K] = torch.where(sinking, prob.log_eta_min, self.x[:K])
        self.unstick()
        g, grad, P = prob.evaluate(self.x)
        best = self._merit(grad, P)
        for _ in range(steps):
            if best <= self.settings.converged_grad:
                break
            m = torch.cat([prob.eta_free(self.x), prob.xi_on & prob.multi, torch.ones(prob.P)])
            m = m.bool()
            H = prob.curvature(self.x, raw=True)
            # the exact Hessian in log eta, log xi adds the log-space gradient on the diagonal
            H.diagonal()[: 2 * K] += grad[: 2 * K]
            step = _newton_step(H[m][:, m], grad[m])
            if step is None:
                break
            for t in 0.5 ** torch.arange(10.0):
                x = self.x.clone()
                x[m] = x[m] + t * step
                g_t, grad_t, P_t = prob.evaluate(x)
                merit = self._merit(grad_t, P_t)
                if merit < best:
                    self.x, g, grad, P, best = x, g_t, grad_t, P_t, merit
                    break
            else:
                break
        if best > merit0:  # no better than LBFGS left it
            self.x = x0
            return end
        return _End(best <= self.settings.converged_grad, g, P)

    def _excess(self, P: Tensor) -> Tensor:
        """(K,) how far each bounded block's cross-entropy exceeds kappa (<= 0: met)."""
        ce = block_cross_entropy(P, self.prob.lr)
        return torch.where(self.bounded, ce - self.prob.kappa, -1.0)

    def _merit(self, grad: Tensor, P: Tensor) -> float:
        """Largest gradient entry, or entropy-bound excess where the bound is on."""
        excess = self._excess(P) if self.entropy_bound else grad.new_zeros(1)
        return max(float(grad.abs().max()), float(excess.max()))

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

    def unstick(self) -> None:
        """Lift each eta held at its floor whose KL bound is broken there (the dual falls as
        that eta grows, but the clamp hides its gradient) to where the KL meets epsilon."""
        prob, K = self.prob, self.prob.K
        low = (self.x[:K] <= prob.log_eta_min) & prob.eta_on
        if not bool(low.any()) or not bool(torch.isfinite(self.x).all()):
            return
        _, eta, xi, v = prob.unpack(self.x)
        lifted, moved = enforce_kl(prob, eta, xi, v)
        self.x[:K] = torch.where(low & moved, lifted.log(), self.x[:K])

    def phase(self) -> _End:
        """One LBFGS solve from x. With options, LBFGS runs in whitened coordinates (see
        :class:`_Whitened`), which saves iterations: the xi direction is badly scaled against
        eta and v otherwise (measured: with one option the plain problem is as well scaled)."""
        self.unstick()
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


def _newton_step(H: Tensor, grad: Tensor) -> Tensor | None:
    """-H^-1 grad with H scaled to unit diagonal first (the curvature of a block held near its
    eta floor is tiny, not flat); None where H is singular."""
    d = H.diagonal()
    scale = torch.where(d > 0, d, torch.ones_like(d)).rsqrt()
    Hs = scale[:, None] * H * scale[None, :]
    Hs = Hs + 1e-12 * torch.eye(Hs.shape[0], dtype=Hs.dtype)
    try:
        step: Tensor = -scale * torch.linalg.solve(Hs, scale * grad)
    except RuntimeError:
        return None
    return step
