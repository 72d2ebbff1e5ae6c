"""Newton steps and LBFGS on one standardised K-block dual: :class:`BlockSolver`.

Each phase takes damped Newton steps with the exact curvature (:meth:`BlockSolver.descend`), then
LBFGS in coordinates whitened by the curvature. The entropy bound is handled by KKT active sets
(:meth:`BlockSolver.entropy_kkt`), infeasible feature constraints by a ridge
(:meth:`BlockSolver.relax`), returns without information by a projection solve (eta held at 1,
R = 0), and an inactive KL bound by an eta floor (:func:`eta_floor`). One problem: tensors carry
:class:`~hireps_torch.dual.problem.DualProblem`'s leading S = 1 (see
:func:`~hireps_torch.dual.solver.solve_blocks`).
"""

from __future__ import annotations

import math
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
    """(S, K) lower clamp of log eta per block (standardised units): e^-10 of the block's own return
    spread (of the common spread where the block's returns do not vary), at least
    ``LOG_ETA_MIN``."""
    spread = st.reward_spread.clamp(max=1.0)
    rel = torch.where(spread > 1e-13, spread, torch.ones_like(spread))
    return (_LOG_ETA_FLOOR + rel.log()).clamp_min(LOG_ETA_MIN)


@dataclass(frozen=True)
class LbfgsSettings:
    """LBFGS iterations per phase and the two gradient tolerances of
    :func:`~hireps_torch.dual.solve_reps_dual`."""

    max_iter: int = 300
    tolerance_grad: float = 1e-7
    converged_grad: float = 1e-6


_POLISH_STEPS = 8  # Newton steps where LBFGS stopped short, at most
_CHUNK = 25  # LBFGS iterations between re-whitenings (see BlockSolver.phase)
_NEWTON_STEPS = 100  # Newton steps of a phase before LBFGS takes over (BlockSolver.descend)
_DAMPINGS = 16  # tries per Newton step: halvings, then a damping growing tenfold each
_LAM_MIN = 1e-4  # the damping a try starts from once halving the step did not help
_ARMIJO = 1e-4  # sufficient decrease of a Newton step
_FLAT = 1e-13  # relative change of the dual value within round-off
_KKT_LOOSE = 1e-3  # the merit at which the entropy bound's active set is first decided
_STALLS = 2  # steps in a row at the gradient's round-off floor that stop Newton (descend)
_MAX_LOG_STEP = 1.5  # largest change of a log eta or log xi in one Newton step
_FLAT_FLOOR = 1e-9  # round-off allowed below the weak-duality bound (BlockSolver.floor)


class _End(NamedTuple):
    """Where the solve ended: converged (1,), dual value (1,), weights (1, K, N, O)."""

    converged: Tensor
    value: Tensor
    weights: Tensor


class _Whitened:
    """LBFGS closure: the dual in z, x = x0 + L^-T z."""

    def __init__(self, prob: DualProblem, x0: Tensor, L: Tensor, floor: Tensor) -> None:
        self.prob, self.x0, self.L, self.floor = prob, x0, L, floor
        self.z = torch.zeros_like(x0)

    def x(self) -> Tensor:
        step: Tensor = torch.linalg.solve_triangular(
            self.L.transpose(1, 2), self.z[..., None], upper=True
        )
        return self.x0 + step[..., 0]

    def __call__(self) -> Tensor:
        g, grad, _ = self.prob.evaluate(self.x())
        # below its floor a dual running off counts only logarithmically (monotone, C1)
        below = (self.floor - g).clamp_min(0.0)
        g = torch.where(below > 0, self.floor - torch.log1p(below), g)
        grad = grad / (1.0 + below)[:, None]
        self.z.grad = torch.linalg.solve_triangular(self.L, grad[..., None], upper=False)[..., 0]
        return g.sum()


class BlockSolver:
    """Newton steps and LBFGS on one standardised problem (tensors with S = 1); ``x`` (1, n) holds
    the current point, ``end`` where the solve ended, ``iterations`` the LBFGS iterations and
    Newton steps of all phases so far."""

    def __init__(
        self,
        st: Standardised,
        log_resp: Tensor,
        eps: Tensor,
        kappa: Tensor,
        settings: LbfgsSettings,
        log_eta_start: Tensor | None = None,
    ) -> None:
        self.bounded = torch.isfinite(kappa)  # (1, K) blocks with an entropy bound
        kap = torch.where(self.bounded, kappa, 0.0)
        self.prob = DualProblem(st.returns, st.D, st.c, log_resp, eps, kap)
        self.entropy_bound = bool(self.bounded.any()) and self.prob.multi
        self.settings = settings
        self.prob.log_eta_min = eta_floor(st)
        self.x = self.prob.start()
        if log_eta_start is not None:  # (1, K), standardised; NaN: the default start
            K, floor = self.prob.K, self.prob.log_eta_min + 1.0
            given = torch.maximum(log_eta_start, floor)
            self.x[:, :K] = torch.where(log_eta_start.isnan(), self.x[:, :K], given)
        self.iterations = 0
        self.stalled = False  # the last descend's, see there
        self.informative = bool(st.informative)
        if not self.informative:  # the projection solve: R = 0 and eta held at 1
            self.prob.eta_on[:] = False
            self.x[:, : self.prob.K] = 0.0
        g, _, P = self.prob.evaluate(self.x)
        self.end = _End(torch.zeros_like(st.informative), g, P)
        # weak duality: a feasible P makes the dual >= sum_k min_i R_ki; below that (less
        # round-off) the feature constraints cannot be met within the KL bound
        low = self.prob.R.amin(-1).sum(-1)
        self.floor = low - _FLAT_FLOOR * (1.0 + low.abs() + g.abs())

    def old_distribution(self) -> bool:
        """Whether the old distribution q p~ meets the entropy and feature constraints (then the
        end is set to it)."""
        prob, K = self.prob, self.prob.K
        w = prob.lr.exp() / prob.N
        w = w / w.sum(dim=(-2, -1), keepdim=True)
        ce = block_cross_entropy(w, prob.lr)
        ok = ~(self.bounded & (ce > prob.kappa + 1e-6)).any(-1)
        g, grad, _ = prob.evaluate(self.x)  # x: v = 0, xi off
        if prob.P:
            ok &= grad[:, 2 * K :].abs().amax(-1) <= self.settings.converged_grad
        if bool(ok):
            self.end = _End(ok, g, w)
        return bool(ok)

    def run(self) -> tuple[_End, str | None]:
        """Solve; where the feature constraints cannot be met, relax them to a penalty (the second
        item: the warning text, or None)."""
        prob = self.prob
        x_start = self.x.clone()
        if not self.informative and self.old_distribution():
            return self.end, None
        self.solve()
        if not prob.P:
            return self.end, None
        # an unconverged solve that broke the KL bound ran off too, only more slowly
        short = not bool(self.end.converged)
        ran_off = self.informative and short and self.breaks_kl(self.end.weights)
        # a converged solve met every constraint: no conflict
        conflict = short and bool(prob.shows_conflict(self.x, self.end.value) | self._sunk())
        if not (conflict or ran_off):
            return self.end, None
        why = (
            "the feature constraints cannot be met within the KL bound"
            if conflict
            else "the solve broke the KL bound before converging"
        )
        how = (
            "the KL bound is kept"
            if self.relax(x_start)
            else "the KL bound, still broken (far too few samples for the features?), is "
            "enforced by raising eta"
        )
        self.end = self.end._replace(converged=torch.zeros_like(self.end.converged))
        return self.end, (
            f"{why} epsilon = {prob.eps[0].tolist()} (too few samples for the {prob.P} "
            f"features?): they are relaxed to a quadratic penalty (ridge "
            f"{float(prob.ridge[0]):g} on the standardised value weights) and {how}; see "
            "feature_error and kl"
        )

    def relax(self, x_start: Tensor) -> bool:
        """Re-solve from x_start with a ridge on v, stronger while the KL bound stays broken;
        returns whether the KL bound was kept. The feature constraints become a quadratic
        penalty; the KL bound still holds."""
        for factor in (1.0, 10.0, 100.0, 1e3, 1e4):
            self.prob.ridge = torch.full_like(self.prob.ridge, factor * _CONFLICT_RIDGE)
            self.x = x_start.clone()
            self.solve()
            if not self.breaks_kl(self.end.weights):
                return True
        return False

    def breaks_kl(self, w: Tensor) -> bool:
        """Whether weights (1, K, N, O) exceed some block's KL bound (beyond round-off)."""
        return bool((block_kl(w, self.prob.lr) > 1.01 * self.prob.eps + 1e-3).any())

    def solve(self) -> None:
        """KKT phases or one phase, up to two resumes, then :meth:`polish` where still short."""
        if self.entropy_bound:
            self.entropy_kkt()
        else:
            self.phase()
        for _ in range(2):
            if not self._short():
                break
            self.phase()  # a stalled LBFGS resumes with the curvature where it stopped
        if self.entropy_bound:
            # the log-space gradient hides a violated bound when xi ~0: check it directly
            ce = block_cross_entropy(self.end.weights, self.prob.lr)
            met = (~self.bounded | (ce <= self.prob.kappa + 1e-6)).all(-1)
            self.end = self.end._replace(converged=self.end.converged & met)
        if self._short():
            self.polish()

    def _sunk(self) -> Tensor:
        """(1,) whether the dual, without a ridge, fell below the weak-duality bound ``floor``."""
        return (self.prob.ridge == 0) & ~(self.end.value >= self.floor)

    def _short(self) -> bool:
        """Whether the solve has not converged but can go on: point and dual value finite, not
        :meth:`_sunk`."""
        finite = torch.isfinite(self.x).all(-1) & torch.isfinite(self.end.value)
        return bool(~self.end.converged & finite & ~self._sunk())

    def polish(self) -> None:
        """Newton steps where LBFGS stopped short (merit: largest gradient entry or entropy-bound
        excess); a violated bound first gets the xi that meets it. Ending no better puts the
        point back."""
        prob, K = self.prob, self.prob.K
        x0, end0 = self.x.clone(), self.end
        merit0 = self._merit(prob.evaluate(self.x)[1], self.end.weights)
        over = prob.xi_on & (self._excess(self.end.weights) > 0)
        if bool(over.any()):
            log_xi = prob.log_xi_meeting_bound(self.x)
            self.x[:, K : 2 * K] = torch.where(over, log_xi, self.x[:, K : 2 * K])
        # an eta still sinking just above its floor (KL below epsilon) belongs there: hold it
        _, grad, _ = prob.evaluate(self.x)
        low = self.x[:, :K] < prob.log_eta_min + 2.0
        sinking = prob.eta_free(self.x) & (grad[:, :K] > 0) & low
        self.x[:, :K] = torch.where(sinking, prob.log_eta_min, self.x[:, :K])
        self.unstick()
        best = self.descend(self.settings.converged_grad, _POLISH_STEPS, excess=True)
        if bool(best > merit0):  # no better than LBFGS left it
            self.x, self.end = x0, end0
        else:
            self.end = self.end._replace(converged=best <= self.settings.converged_grad)

    def _excess(self, P: Tensor) -> Tensor:
        """(1, K) how far each bounded block's cross-entropy exceeds kappa (<= 0: met)."""
        ce = block_cross_entropy(P, self.prob.lr)
        return torch.where(self.bounded, ce - self.prob.kappa, -1.0)

    def _merit(self, grad: Tensor, P: Tensor) -> Tensor:
        """(1,) largest gradient entry, or entropy-bound excess where the bound is on."""
        m = grad.abs().amax(-1)
        if not self.entropy_bound:
            return m
        return torch.maximum(m, self._excess(P).amax(-1))

    def entropy_kkt(self) -> None:
        """KKT for xi >= 0 by active sets: xi on where a block's bound is violated (from the xi
        that meets it), off where the weights without xi meet it; re-solve until no block
        changes."""
        prob, K = self.prob, self.prob.K
        prob.xi_on = torch.zeros_like(prob.xi_on)
        self.unstick()
        self.descend(_KKT_LOOSE)  # near enough to decide the active set
        fresh = True  # solved loosely: a phase finishes it where its active set stands
        for _ in range(2 * K + 3):
            ce = block_cross_entropy(self.end.weights, prob.lr)
            violated = self.bounded & (ce > prob.kappa + 1e-6)
            _, eta, _, v = prob.unpack(self.x)
            P0, _, _ = prob.weights_at(eta, torch.zeros_like(eta), v)
            slack = prob.xi_on & (block_cross_entropy(P0, prob.lr) <= prob.kappa)
            restart = violated & ~slack
            changed = bool((restart | slack).any())
            if not (changed or fresh):
                break
            if changed:
                prob.xi_on = (prob.xi_on | restart) & ~slack
                log_xi = prob.log_xi_meeting_bound(self.x)
                self.x[:, K : 2 * K] = torch.where(restart, log_xi, self.x[:, K : 2 * K])
            fresh = False
            self.phase()  # then checked again

    def unstick(self) -> None:
        """Lift each eta held at its floor whose KL bound is broken there to where the KL meets
        epsilon."""
        prob, K = self.prob, self.prob.K
        finite = torch.isfinite(self.x).all(-1, keepdim=True)
        low = finite & (self.x[:, :K] <= prob.log_eta_min) & prob.eta_on
        if not bool(low.any()):
            return
        _, eta, xi, v = prob.unpack(self.x)
        lifted, moved = enforce_kl(prob, eta, xi, v)
        self.x[:, :K] = torch.where(low & moved, lifted.log(), self.x[:, :K])

    def descend(
        self, target: float | None = None, steps: int = _NEWTON_STEPS, excess: bool = False
    ) -> Tensor:
        """Damped Newton steps (exact Hessian, else its PSD part, plus Levenberg-Marquardt damping;
        Armijo or, where flat, a smaller merit) until ``target`` (``tolerance_grad``), no damping
        helps, or ``_STALLS`` round-off-only steps (``stalled``, back at the best point). Returns
        the merit (1,); each step counts as an iteration."""
        prob = self.prob
        target = self.settings.tolerance_grad if target is None else target
        merits = self._merit if excess else lambda grad, _: grad.abs().amax(-1)
        g, grad, P = prob.evaluate(self.x)
        merit = merits(grad, P)
        finite = bool(torch.isfinite(self.x).all() & torch.isfinite(g).all())
        bounded = bool(prob.ridge > 0)  # a ridge bounds the dual: the weak-duality floor is off
        lam = torch.zeros_like(g)
        M: Tensor | None = None  # the curvature, kept for one more step after a full one
        # the best point so far, and the round-off-only steps in a row (see _STALLS)
        best, best_x, stalls = merit, self.x, 0
        for _ in range(steps if finite else 0):
            above = bounded or bool(g >= self.floor)
            if not (bool(merit > target) and above and stalls < _STALLS):
                break
            curvature = self._hessians(grad, P, M)
            taken = False
            t = torch.ones_like(g)
            base: Tensor | None = None  # the undamped-length step, recomputed when lam moves
            g_prev = g
            for _ in range(_DAMPINGS):
                if base is None:
                    base = self._damped_step(*curvature, grad, lam)
                step = t[:, None] * base
                slope = (grad * step).sum(-1)
                x = self.x + step
                g_t, grad_t, P_t = prob.evaluate(x)
                merit_t = merits(grad_t, P_t)
                flat = g_t <= g + _FLAT * (1.0 + g.abs())
                if bool((g_t <= g + _ARMIJO * slope) | (flat & (merit_t < merit))):
                    self.x, g, grad, P, merit = x, g_t, grad_t, P_t, merit_t
                    lam = torch.where(lam > _LAM_MIN, 0.1 * lam, 0.0)
                    taken = True
                    break
                # a failed try first halves the step, then (from the fourth) damps it
                if bool(t > 0.1):
                    t = 0.5 * t
                else:
                    lam = (10.0 * lam).clamp_min(_LAM_MIN)
                    base = None
            self.iterations += 1
            if not taken:
                break
            level = (g - g_prev).abs() <= _FLAT * (1.0 + g_prev.abs())
            stalls = stalls + 1 if bool(level & (merit > 0.5 * best)) else 0
            if bool(merit < best):
                best, best_x = merit, self.x
            M = curvature[1] if bool((t == 1.0) & (lam == 0.0)) and M is None else None
        self.stalled = stalls >= _STALLS
        if self.stalled and bool(best < merit):  # back to the best point
            self.x = best_x
            g, grad, P = prob.evaluate(self.x)
            merit = merits(grad, P)
        self.end = _End(merit <= self.settings.converged_grad, g, P)
        return merit

    def _hessians(
        self, grad: Tensor, P: Tensor, M: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """(exact Hessian (S, n, n), its PSD part (S, n, n), moving coordinates (S, n)) at x for
        gradients (S, n) and weights P; with M, that curvature instead of a new one."""
        K = self.prob.K
        M = self.prob.curvature(self.x, raw=True, weights=P) if M is None else M
        H = M.clone()
        H.diagonal(dim1=1, dim2=2)[:, : 2 * K] += grad[:, : 2 * K]
        return H, M, self._moving()

    def _damped_step(
        self, H: Tensor, M: Tensor, moving: Tensor, grad: Tensor, lam: Tensor
    ) -> Tensor:
        """(S, n) Newton steps with damping lam (S,) on the moving coordinates, within the log
        eta / log xi trust region."""
        step, ok = _newton_step(H, grad, moving, lam)
        if not bool(ok):
            step, _ = _newton_step(M, grad, moving, lam + 1e-8)
        # a block's temperature (and xi) changes by at most e^_MAX_LOG_STEP per step
        big = step[:, : 2 * self.prob.K].abs().amax(-1, keepdim=True)
        return step * (_MAX_LOG_STEP / big.clamp_min(_MAX_LOG_STEP))

    def _moving(self) -> Tensor:
        """(S, n) the coordinates a step may move: free eta, xi where on, every v."""
        prob = self.prob
        return torch.cat(
            [
                prob.eta_free(self.x),
                prob.xi_on & prob.multi,
                torch.ones(prob.S, prob.P, dtype=torch.bool, device=self.x.device),
            ],
            -1,
        )

    def phase(self) -> None:
        """One phase: :meth:`descend`, then up to ``max_iter`` LBFGS iterations in calls of
        ``_CHUNK``, each whitened where it starts; a call that stops on its own ends it."""
        self.unstick()
        self.descend()
        if self.stalled:  # LBFGS cannot take a gradient below its round-off floor either
            return
        left, evals = self.settings.max_iter, self.settings.max_iter * 5 // 4
        while self._short():  # torch's budgets for one call: max_iter iterations, 1.25 x evals
            used, spent, stalled = self._lbfgs(min(left, _CHUNK), min(evals, _CHUNK * 5 // 4))
            left, evals = left - used, evals - spent
            if left <= 0 or evals <= 0 or stalled:
                return

    def _lbfgs(self, max_iter: int, max_eval: int) -> tuple[int, int, bool]:
        """One whitened LBFGS call; returns (iterations, evaluations, stopped on its own)."""
        prob, x0 = self.prob, self.x.clone()
        L, info = torch.linalg.cholesky_ex(prob.curvature(x0))
        eye = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device)
        L = torch.where((info == 0)[:, None, None], L, eye)  # no whitening where it fails
        floor = torch.where(self.prob.ridge > 0, -math.inf, self.floor)  # see descend
        objective = _Whitened(prob, x0, L, floor)
        opt = torch.optim.LBFGS(
            [objective.z],
            lr=1.0,
            max_iter=max_iter,
            max_eval=max_eval,
            tolerance_grad=self.settings.tolerance_grad,
            tolerance_change=1e-15,
            history_size=20,
            line_search_fn="strong_wolfe",
        )
        try:
            opt.step(objective)  # type: ignore[no-untyped-call,unused-ignore]  # untyped in torch
        except IndexError:
            # torch's strong-Wolfe search, on duals turning non-finite; x is back at its start
            pass
        state = opt.state[objective.z]
        used, spent = int(state.get("n_iter", 0)), int(state.get("func_evals", 0))
        stalled = used < max_iter and spent < max_eval
        self.iterations += used
        x = objective.x()
        g, grad, P = prob.evaluate(x)
        self.x = x
        self.end = _End(grad.abs().amax(-1) <= self.settings.converged_grad, g, P)
        return used, spent, stalled


def _newton_step(H: Tensor, grad: Tensor, moving: Tensor, ridge: Tensor) -> tuple[Tensor, Tensor]:
    """(-(H + ridge I)^-1 grad on ``moving``, 0 elsewhere (S, n); H + ridge I positive definite
    (S,)) for H (S, n, n) scaled to unit diagonal first, ridge (S,)."""
    n = H.shape[-1]
    eye = torch.eye(n, dtype=H.dtype, device=H.device)
    both = moving[:, :, None] & moving[:, None, :]
    Hm = torch.where(both, H, eye)
    g = torch.where(moving, grad, 0.0)
    d = Hm.diagonal(dim1=1, dim2=2)
    scale = torch.where(d > 0, d, torch.ones_like(d)).rsqrt()
    Hs = scale[:, :, None] * Hm * scale[:, None, :] + (ridge[:, None, None] + 1e-12) * eye
    L, info = torch.linalg.cholesky_ex(Hs)
    sol = torch.cholesky_solve((scale * g)[..., None], L)
    ok = (info == 0) & torch.isfinite(sol).all(dim=(1, 2))
    step = torch.where(ok[:, None], -scale * sol[..., 0], 0.0)
    return torch.where(moving, step, 0.0), ok
