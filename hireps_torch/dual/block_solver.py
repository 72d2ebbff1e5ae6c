"""Newton steps and LBFGS on one standardised K-block dual: :class:`BlockSolver`.

Each phase takes damped Newton steps with the exact curvature (:meth:`BlockSolver.descend`), then
LBFGS in coordinates whitened by the curvature. The entropy bound is handled by KKT active sets
(:meth:`BlockSolver.entropy_kkt`), infeasible feature constraints by a ridge
(:meth:`BlockSolver.relax`), returns without information by a projection solve (eta held at 1,
R = 0), and an inactive KL bound by an eta floor (:func:`eta_floor`). Tensors carry a leading S = 1
(see :func:`~hireps_torch.dual.solver.solve_blocks`).
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
    """Where the solves ended: converged (S,), dual values (S,), weights (S, K, N, O)."""

    converged: Tensor
    value: Tensor
    weights: Tensor


class _Whitened:
    """LBFGS closure: the sum of the S duals in z, x = x0 + L^-T z."""

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
    """Newton steps and LBFGS on one standardised problem (S = 1); ``x`` (S, n) holds the
    current point, ``iterations`` the LBFGS iterations and Newton steps of all phases so far."""

    def __init__(
        self,
        st: Standardised,
        log_resp: Tensor,
        eps: Tensor,
        kappa: Tensor,
        settings: LbfgsSettings,
        log_eta_start: Tensor | None = None,
    ) -> None:
        self.bounded = torch.isfinite(kappa)  # (S, K) blocks with an entropy bound
        kap = torch.where(self.bounded, kappa, 0.0)
        self.prob = DualProblem(st.returns, st.D, st.c, log_resp, eps, kap)
        self.entropy_bound = self.bounded.any(-1) & self.prob.multi  # (S,)
        self.settings = settings
        self.prob.log_eta_min = eta_floor(st)
        self.x = self.prob.start()
        if log_eta_start is not None:  # (S, K), standardised; NaN: the default start
            K, floor = self.prob.K, self.prob.log_eta_min + 1.0
            given = torch.maximum(log_eta_start, floor)
            self.x[:, :K] = torch.where(log_eta_start.isnan(), self.x[:, :K], given)
        self.iterations = 0
        self.stalled = torch.zeros_like(st.informative)  # (S,) the last descend's, see there
        self.informative = st.informative
        flat = ~st.informative  # the projection solve: R = 0 and eta held at 1
        self.prob.eta_on[flat] = False
        self.x[:, : self.prob.K] = torch.where(flat[:, None], 0.0, self.x[:, : self.prob.K])
        g, _, P = self.prob.evaluate(self.x)
        self.end = _End(torch.zeros_like(flat), g, P)
        # weak duality: a feasible P makes the dual >= sum_k min_i R_ki; below that (less
        # round-off) the feature constraints cannot be met within the KL bound
        low = self.prob.R.amin(-1).sum(-1)
        self.floor = low - _FLAT_FLOOR * (1.0 + low.abs() + g.abs())

    def _set(self, mask: Tensor, converged: Tensor, value: Tensor, weights: Tensor) -> None:
        """Overwrite the ends of the problems in ``mask`` (S,)."""
        e = self.end
        self.end = _End(
            torch.where(mask, converged, e.converged),
            torch.where(mask, value, e.value),
            torch.where(mask[:, None, None, None], weights, e.weights),
        )

    def old_distribution(self) -> Tensor:
        """(S,) the problems whose old distribution q p~ meets the entropy and feature constraints
        (their ends are set to it)."""
        prob, K = self.prob, self.prob.K
        w = prob.lr.exp() / prob.N
        w = w / w.sum(dim=(-2, -1), keepdim=True)
        ce = block_cross_entropy(w, prob.lr)
        ok = ~(self.bounded & (ce > prob.kappa + 1e-6)).any(-1)
        g, grad, _ = prob.evaluate(self.x)  # x: v = 0, xi off
        if prob.P:
            ok &= grad[:, 2 * K :].abs().amax(-1) <= self.settings.converged_grad
        self._set(ok, torch.ones_like(ok), g, w)
        return ok

    def run(self) -> tuple[_End, list[str | None]]:
        """Solve; where the feature constraints cannot be met, relax them to a penalty (the second
        item: each problem's warning text or None)."""
        prob = self.prob
        x_start = self.x.clone()
        texts: list[str | None] = [None] * prob.S
        todo = ~self.informative
        if bool(todo.any()):
            todo = ~(todo & self.old_distribution())
        else:
            todo = torch.ones_like(todo)
        if not bool(todo.any()):
            return self.end, texts
        if not prob.P:
            self.solve(todo)
            return self.end, texts
        self.x = torch.where(todo[:, None], x_start, self.x)
        self.solve(todo)
        # an unconverged solve that broke the KL bound ran off too, only more slowly
        ran_off = self.informative & ~self.end.converged & self.breaks_kl(self.end.weights)
        # a converged solve met every constraint: no conflict
        shows = prob.shows_conflict(self.x, self.end.value) | self._sunk()
        conflict = todo & ~self.end.converged & shows
        need = conflict | (todo & ran_off)
        if not bool(need.any()):
            return self.end, texts
        kept = self.relax(x_start, need)
        for s in need.nonzero().flatten().tolist():
            why = (
                "the feature constraints cannot be met within the KL bound"
                if bool(conflict[s])
                else "the solve broke the KL bound before converging"
            )
            how = (
                "the KL bound is kept"
                if bool(kept[s])
                else "the KL bound, still broken (far too few samples for the features?), is "
                "enforced by raising eta"
            )
            texts[s] = (
                f"{why} epsilon = {prob.eps[s].tolist()} (too few samples for the {prob.P} "
                f"features?): they are relaxed to a quadratic penalty (ridge "
                f"{float(prob.ridge[s]):g} on the standardised value weights) and {how}; see "
                "feature_error and kl"
            )
        self._set(need, torch.zeros_like(need), self.end.value, self.end.weights)
        return self.end, texts

    def relax(self, x_start: Tensor, need: Tensor) -> Tensor:
        """Re-solve ``need`` (S,) from x_start with a ridge on v, stronger while the KL bound stays
        broken; returns (S,) whether each kept the KL bound. The feature constraints become a
        quadratic penalty; the KL bound still holds."""
        kept = torch.zeros_like(need)
        for factor in (1.0, 10.0, 100.0, 1e3, 1e4):
            self.prob.ridge = torch.where(need, factor * _CONFLICT_RIDGE, self.prob.ridge)
            self.x = torch.where(need[:, None], x_start, self.x)
            self.solve(need)
            kept = need & ~self.breaks_kl(self.end.weights)
            if bool(kept[need].all()):
                break
        return kept

    def breaks_kl(self, w: Tensor) -> Tensor:
        """(S,) whether weights (S, K, N, O) exceed some block's KL bound (beyond round-off)."""
        return (block_kl(w, self.prob.lr) > 1.01 * self.prob.eps + 1e-3).any(-1)

    def solve(self, mask: Tensor) -> None:
        """Solve the problems in ``mask`` (S,): KKT phases or one phase, up to two resumes, then
        :meth:`polish` where still short."""
        kkt = mask & self.entropy_bound
        if bool(kkt.any()):
            self.entropy_kkt(kkt)
        if bool((mask & ~kkt).any()):
            self.phase(mask & ~kkt)
        for _ in range(2):
            # a stalled LBFGS resumes with the curvature where it stopped
            again = mask & ~self.end.converged & self._finite() & ~self._sunk()
            if not bool(again.any()):
                break
            self.phase(again)
        if bool(kkt.any()):
            # the log-space gradient hides a violated bound when xi ~0: check it directly
            ce = block_cross_entropy(self.end.weights, self.prob.lr)
            met = (~self.bounded | (ce <= self.prob.kappa + 1e-6)).all(-1)
            e = self.end
            self.end = e._replace(converged=torch.where(kkt, e.converged & met, e.converged))
        short = mask & ~self.end.converged & self._finite() & ~self._sunk()
        if bool(short.any()):
            self.polish(short)

    def _sunk(self) -> Tensor:
        """(S,) problems without a ridge whose dual fell below the weak-duality bound ``floor``."""
        return (self.prob.ridge == 0) & ~(self.end.value >= self.floor)

    def _finite(self) -> Tensor:
        """(S,) problems whose point and dual value are finite."""
        return torch.isfinite(self.x).all(-1) & torch.isfinite(self.end.value)

    def polish(self, mask: Tensor) -> None:
        """Newton steps on ``mask`` (S,) where LBFGS stopped short (merit: largest gradient entry or
        entropy-bound excess); a violated bound first gets the xi that meets it. A problem that ends
        no better is put back."""
        prob, K = self.prob, self.prob.K
        x0, end0 = self.x.clone(), self.end
        merit0 = self._merit(prob.evaluate(self.x)[1], self.end.weights)
        over = mask[:, None] & prob.xi_on & (self._excess(self.end.weights) > 0)
        if bool(over.any()):
            log_xi = prob.log_xi_meeting_bound(self.x)
            self.x[:, K : 2 * K] = torch.where(over, log_xi, self.x[:, K : 2 * K])
        # an eta still sinking just above its floor (KL below epsilon) belongs there: hold it
        _, grad, _ = prob.evaluate(self.x)
        low = self.x[:, :K] < prob.log_eta_min + 2.0
        sinking = mask[:, None] & prob.eta_free(self.x) & (grad[:, :K] > 0) & low
        self.x[:, :K] = torch.where(sinking, prob.log_eta_min, self.x[:, :K])
        self.unstick(mask)
        best = self.descend(mask, self.settings.converged_grad, _POLISH_STEPS, excess=True)
        worse = mask & (best > merit0)  # no better than LBFGS left it
        self.x = torch.where(worse[:, None], x0, self.x)
        e = self.end
        self._set(mask & ~worse, best <= self.settings.converged_grad, e.value, e.weights)
        self._set(worse, end0.converged, end0.value, end0.weights)

    def _excess(self, P: Tensor) -> Tensor:
        """(S, K) how far each bounded block's cross-entropy exceeds kappa (<= 0: met)."""
        ce = block_cross_entropy(P, self.prob.lr)
        return torch.where(self.bounded, ce - self.prob.kappa, -1.0)

    def _merit(self, grad: Tensor, P: Tensor) -> Tensor:
        """(S,) largest gradient entry, or entropy-bound excess where the bound is on."""
        m = grad.abs().amax(-1)
        if not self.prob.multi:
            return m
        excess = self._excess(P).amax(-1)
        return torch.where(self.entropy_bound, torch.maximum(m, excess), m)

    def entropy_kkt(self, mask: Tensor) -> None:
        """KKT for xi >= 0 on ``mask`` (S,) by active sets: xi on where a block's bound is violated
        (from the xi that meets it), off where the weights without xi meet it; re-solve until no
        block changes."""
        prob, K = self.prob, self.prob.K
        prob.xi_on = torch.where(mask[:, None], False, prob.xi_on)
        self.unstick(mask)
        self.descend(mask, _KKT_LOOSE)  # near enough to decide the active set
        fresh = mask  # solved loosely: a phase finishes those whose active set stands
        for _ in range(2 * K + 3):
            ce = block_cross_entropy(self.end.weights, prob.lr)
            violated = mask[:, None] & self.bounded & (ce > prob.kappa + 1e-6)
            _, eta, _, v = prob.unpack(self.x)
            P0, _, _ = prob.weights_at(eta, torch.zeros_like(eta), v)
            slack = mask[:, None] & prob.xi_on & (block_cross_entropy(P0, prob.lr) <= prob.kappa)
            restart = violated & ~slack
            changed = (restart | slack).any(-1)
            settled, fresh = fresh & ~changed, torch.zeros_like(mask)
            if bool(settled.any()):
                self.phase(settled)  # then checked again
            elif not bool(changed.any()):
                break
            if bool(changed.any()):
                prob.xi_on = (prob.xi_on | restart) & ~slack
                log_xi = prob.log_xi_meeting_bound(self.x)
                self.x[:, K : 2 * K] = torch.where(restart, log_xi, self.x[:, K : 2 * K])
                self.phase(changed)

    def unstick(self, mask: Tensor) -> None:
        """Lift each eta of ``mask`` held at its floor whose KL bound is broken there to where the
        KL meets epsilon."""
        prob, K = self.prob, self.prob.K
        finite = torch.isfinite(self.x).all(-1)
        low = (mask & finite)[:, None] & (self.x[:, :K] <= prob.log_eta_min) & prob.eta_on
        if not bool(low.any()):
            return
        _, eta, xi, v = prob.unpack(torch.where(finite[:, None], self.x, 0.0))
        lifted, moved = enforce_kl(prob, eta, xi, v)
        self.x[:, :K] = torch.where(low & moved, lifted.log(), self.x[:, :K])

    def descend(
        self,
        mask: Tensor,
        target: float | None = None,
        steps: int = _NEWTON_STEPS,
        excess: bool = False,
    ) -> Tensor:
        """Damped Newton steps (exact Hessian, else its PSD part, plus Levenberg-Marquardt damping;
        Armijo or, where flat, a smaller merit) on ``mask`` (S,) until ``target``
        (``tolerance_grad``), no damping helps, or ``_STALLS`` round-off-only steps (``stalled``,
        back at the best point). Returns the merit (S,); each step counts as an iteration."""
        prob = self.prob
        target = self.settings.tolerance_grad if target is None else target
        merits = self._merit if excess else lambda grad, _: grad.abs().amax(-1)
        g, grad, P = prob.evaluate(self.x)
        merit = merits(grad, P)
        active = mask & torch.isfinite(self.x).all(-1) & torch.isfinite(g)
        bounded = prob.ridge > 0  # a ridge bounds the dual: the weak-duality floor is off
        lam = torch.zeros_like(g)
        M: Tensor | None = None  # the curvature, kept for one more step after a full one
        # the best point so far, and the round-off-only steps in a row (see _STALLS)
        best, best_x, stalls = merit, self.x, torch.zeros_like(g)
        for _ in range(steps):
            active &= (merit > target) & (bounded | (g >= self.floor)) & (stalls < _STALLS)
            if not bool(active.any()):
                break
            curvature = self._hessians(grad, P, M)
            taken = torch.zeros_like(active)
            t = torch.ones_like(g)
            base: Tensor | None = None  # the undamped-length step, recomputed when lam moves
            g_prev = g
            for _ in range(_DAMPINGS):
                trying = active & ~taken
                if not bool(trying.any()):
                    break
                if base is None:
                    base = self._damped_step(*curvature, grad, lam)
                step = t[:, None] * base
                slope = (grad * step).sum(-1)
                x = torch.where(trying[:, None], self.x + step, self.x)
                g_t, grad_t, P_t = prob.evaluate(x)
                merit_t = merits(grad_t, P_t)
                flat = g_t <= g + _FLAT * (1.0 + g.abs())
                ok = trying & ((g_t <= g + _ARMIJO * slope) | (flat & (merit_t < merit)))
                self.x = torch.where(ok[:, None], x, self.x)
                g = torch.where(ok, g_t, g)
                grad = torch.where(ok[:, None], grad_t, grad)
                P = torch.where(ok[:, None, None, None], P_t, P)
                merit = torch.where(ok, merit_t, merit)
                taken |= ok
                # a failed try first halves the step, then (from the fourth) damps it
                halve = trying & ~ok & (t > 0.1)
                damp = trying & ~ok & ~halve
                t = torch.where(halve, 0.5 * t, t)
                lam = torch.where(damp, (10.0 * lam).clamp_min(_LAM_MIN), lam)
                lam = torch.where(ok, torch.where(lam > _LAM_MIN, 0.1 * lam, 0.0), lam)
                if bool((damp | ok).any()):
                    base = None
            active &= taken
            level = (g - g_prev).abs() <= _FLAT * (1.0 + g_prev.abs())
            stalls = torch.where(taken, (level & (merit > 0.5 * best)) * (stalls + 1), stalls)
            better = taken & (merit < best)
            best = torch.where(better, merit, best)
            best_x = torch.where(better[:, None], self.x, best_x)
            self.iterations += 1
            full = bool(((t == 1.0) & (lam == 0.0) | ~active).all())
            M = curvature[1] if full and M is None else None
        self.stalled = mask & (stalls >= _STALLS)
        back = self.stalled & (best < merit)  # back to the best point
        if bool(back.any()):
            self.x = torch.where(back[:, None], best_x, self.x)
            g_b, grad_b, P_b = prob.evaluate(self.x)
            g = torch.where(back, g_b, g)
            P = torch.where(back[:, None, None, None], P_b, P)
            merit = torch.where(back, merits(grad_b, P_b), merit)
        self._set(mask, merit <= self.settings.converged_grad, g, P)
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
        if not bool(ok.all()):
            psd, _ = _newton_step(M, grad, moving, lam + 1e-8)
            step = torch.where(ok[:, None], step, psd)
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

    def phase(self, mask: Tensor) -> None:
        """One phase over ``mask`` (S,): :meth:`descend`, then up to ``max_iter`` LBFGS iterations
        in calls of ``_CHUNK``, each whitened where it starts; a call that stops on its own ends
        it."""
        self.unstick(mask)
        self.descend(mask)
        # LBFGS cannot take a gradient below its round-off floor either
        todo = mask & ~self.end.converged & self._finite() & ~self._sunk() & ~self.stalled
        if not bool(todo.any()):
            return
        left, evals = self.settings.max_iter, self.settings.max_iter * 5 // 4
        while True:  # torch's budgets for one call: max_iter iterations, 1.25 x evaluations
            used, spent, stalled = self._lbfgs(todo, min(left, _CHUNK), min(evals, _CHUNK * 5 // 4))
            left, evals = left - used, evals - spent
            todo &= ~self.end.converged & self._finite() & ~self._sunk()
            if left <= 0 or evals <= 0 or not bool(todo.any()) or stalled:
                return

    def _lbfgs(self, mask: Tensor, max_iter: int, max_eval: int) -> tuple[int, int, bool]:
        """One whitened LBFGS call over ``mask`` (S,); returns (iterations, evaluations, stopped on
        its own)."""
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
        conv = grad.abs().amax(-1) <= self.settings.converged_grad
        self.x = x
        self._set(mask, conv, g, P)
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
