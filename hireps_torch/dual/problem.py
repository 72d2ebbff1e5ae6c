"""The standardised K-block dual (see :mod:`hireps_torch.dual`) with its analytic gradient.

:class:`DualProblem` evaluates the dual, its gradient and a curvature preconditioner at
x = [log eta (K), log xi (K), v (P)]; the solver (:mod:`hireps_torch.dual.solver`) builds it on
standardised returns and features (:mod:`hireps_torch.dual.conditioning`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["LOG_ETA_MAX", "LOG_ETA_MIN", "V_MAX", "DualProblem"]

LOG_ETA_MIN = -30.0  # eta >= e^-30 (standardised units): past this the weights are one-hot
LOG_ETA_MAX = 30.0
V_MAX = 1.0e8  # |v| (standardised) past this means the dual ran off to -infinity


class DualProblem:
    """Standardised K-block dual with its analytic gradient over x = [log eta, log xi, v].

    Gradient (P = softmax of A / eta over (i, o) per block, w = P summed over options):
        dg/d eta_k = eps_k - KL_k = eps_k + lse_k - sum_io P (delta + xi log p~) / eta
        dg/d xi_k  = kappa_k - CE_k = kappa_k + sum_io P log p~
        dg/d v     = c + sum_k w_k^T D_k
    chained to log eta and log xi (zero where eta is clamped or xi is switched off).

    Args:
        R: (K, N) returns per block.
        D: (K, N, P) map from v to the advantage offsets, or None (no features).
        c: (P,) linear term of the dual in v, or None.
        log_resp: (K, N, O) log responsibilities (``lr``).
        eps: (K,) KL bounds.
        kappa: (K,) entropy bounds (any value where ``xi_on`` is False).

    ``xi_on`` (K,) switches each block's xi on (it is 0 and its gradient 0 while off);
    ``eta_on`` (K,) lets each block's eta move (held where off: the projection solve of
    returns without information, see :mod:`hireps_torch.dual.block_solver`);
    ``log_eta_min`` (K,) is the lower clamp of log eta per block (``LOG_ETA_MIN`` unless the
    solver sets it; see :meth:`~hireps_torch.dual.block_solver.BlockSolver.__init__`);
    ``ridge`` adds (ridge / 2) |v|^2 to the dual when the feature constraints conflict.
    """

    def __init__(
        self,
        R: Tensor,
        D: Tensor | None,
        c: Tensor | None,
        log_resp: Tensor,
        eps: Tensor,
        kappa: Tensor,
    ) -> None:
        self.R, self.D, self.c, self.lr, self.eps, self.kappa = R, D, c, log_resp, eps, kappa
        self.K, self.N, self.O = log_resp.shape
        self.P = 0 if D is None else D.shape[-1]
        self.multi = self.O > 1
        self.log_n = math.log(self.N)
        self.xi_on = torch.zeros(self.K, dtype=torch.bool)
        self.eta_on = torch.ones(self.K, dtype=torch.bool)
        self.log_eta_min = torch.full((self.K,), LOG_ETA_MIN, dtype=torch.float64)
        self.ridge = 0.0  # (ridge / 2) |v|^2 added to the dual when the constraints conflict

    def start(self) -> Tensor:
        """x at v = 0 with eta from KL ≈ Var(delta) / (2 eta^2) (the small-epsilon solution)
        and xi = 0.1; good starts save LBFGS iterations, which dominate the cost."""
        K = self.K
        x = torch.zeros(2 * K + self.P, dtype=torch.float64)
        spread = self.R.std(dim=1).clamp_min(1e-6)
        x[:K] = torch.log(spread) - 0.5 * torch.log(2.0 * self.eps.clamp_min(1e-12))
        x[:K] = torch.maximum(x[:K], self.log_eta_min + 1.0)  # inside the clamp: eta can move
        x[K : 2 * K] = math.log(0.1)
        return x

    def unpack(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(log eta unclamped, eta, xi, v) at x."""
        K = self.K
        a = x[:K]
        eta = torch.maximum(a, self.log_eta_min).clamp(max=LOG_ETA_MAX).exp()
        xi = torch.where(self.xi_on, x[K : 2 * K].clamp(max=LOG_ETA_MAX).exp(), 0.0)
        return a, eta, xi, x[2 * K :]

    def weights(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(P (K, N, O), lse (K,), delta (K, N)) at x."""
        _, eta, xi, v = self.unpack(x)
        return self.weights_at(eta, xi, v)

    def weights_at(self, eta: Tensor, xi: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(P (K, N, O), lse (K,), delta (K, N)) at eta (K,), xi (K,), v (P,), unclamped."""
        delta = self.R if self.D is None else self.R + self.D @ v
        if self.multi:
            z = (delta.unsqueeze(-1) + (eta + xi)[:, None, None] * self.lr) / eta[:, None, None]
        else:
            z = (delta / eta[:, None]).unsqueeze(-1)
        flat = z.reshape(self.K, -1)
        m = flat.max(dim=1, keepdim=True).values
        e = (flat - m).exp_()
        s = e.sum(dim=1, keepdim=True)
        lse = (m + s.log()).squeeze(1) - self.log_n
        return (e / s).reshape(z.shape), lse, delta

    def curvature(self, x: Tensor, raw: bool = False) -> Tensor:
        """Positive semi-definite part of the Hessian in x, used as a preconditioner (with
        identity on unused and flat directions) or, ``raw``, for Newton steps (as computed).

        In y = (eta, xi, v) the Hessian of block k is exactly (1 / eta_k) Cov_P(z) with
        z = [-h / eta_k, log p~, D] and h = delta + xi log p~ (the linear terms of the dual add
        no curvature); the log-parametrisation scales it by diag(eta, xi, 1) on both sides
        (its first-order term, which vanishes at the optimum, is left out).
        """
        K, n = self.K, x.shape[0]
        _, eta, xi, v = self.unpack(x)
        P, _, delta = self.weights_at(eta, xi, v)
        free = self.eta_free(x)
        M = torch.zeros(n, n, dtype=x.dtype)
        for k in range(K):
            h = delta[k].unsqueeze(-1) + xi[k] * self.lr[k]  # (N, O)
            cols, zs = ([k], [-h]) if bool(free[k]) else ([], [])  # d u / d log eta, * eta
            if self.multi and bool(self.xi_on[k]):
                cols.append(K + k)
                zs.append(self.lr[k] * xi[k])
            if self.P:
                assert self.D is not None
                cols.extend(range(2 * K, n))
                zs.extend(self.D[k].unsqueeze(1).expand(-1, self.O, -1).unbind(-1))
            if not cols:
                continue
            Z = torch.stack([z.expand(self.N, self.O) for z in zs], -1).reshape(-1, len(cols))
            p = P[k].reshape(-1, 1)
            Zc = Z - (p * Z).sum(0)
            idx = torch.tensor(cols)
            M[idx[:, None], idx[None, :]] += (Zc * p).T @ Zc / eta[k]
        d = M.diagonal()
        d[2 * K :] += self.ridge
        if raw:
            return M
        top = float(d.max()) if n else 1.0
        # unused or flat directions (xi switched off, O = 1, a constant feature): identity
        d.copy_(torch.where(d > 1e-10 * top, d, torch.ones_like(d)) + 1e-10 * top)
        return M

    def eta_free(self, x: Tensor) -> Tensor:
        """(K,) blocks whose eta moves at x: switched on and strictly inside its clamps (the
        gradient in log eta is 0 elsewhere, and the curvature leaves it out)."""
        a = x[: self.K]
        return (a > self.log_eta_min) & (a < LOG_ETA_MAX) & self.eta_on

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Dual value and its gradient in x."""
        g, grad, _ = self.evaluate(x)
        return g, grad

    def evaluate(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Dual value, gradient in x and the weights P (K, N, O), from one pass."""
        a, eta, xi, v = self.unpack(x)
        P, lse, delta = self.weights_at(eta, xi, v)
        w = P.sum(-1) if self.multi else P.squeeze(-1)  # (K, N)
        pd = (w * delta).sum(1)  # (K,)
        g = (eta * self.eps + eta * lse).sum()
        grad = torch.zeros_like(x)
        if self.multi:
            plr = (P * self.lr).sum((1, 2))  # -CE, (K,)
            g = g + (xi * self.kappa).sum()
            d_eta = self.eps + lse - (pd + xi * plr) / eta
            grad[self.K : 2 * self.K] = torch.where(self.xi_on, xi * (self.kappa + plr), 0.0)
        else:
            d_eta = self.eps + lse - pd / eta
        inside = self.eta_free(x)
        grad[: self.K] = torch.where(inside, eta * d_eta, 0.0)
        if self.P:
            assert self.D is not None
            gv = torch.einsum("kn,knp->p", w, self.D)
            if self.c is not None:
                g = g + self.c @ v
                gv = gv + self.c
            if self.ridge > 0:
                g = g + 0.5 * self.ridge * (v @ v)
                gv = gv + self.ridge * v
            grad[2 * self.K :] = gv
        return g, grad, P

    def value_at(self, eta: Tensor, xi: Tensor, v: Tensor) -> Tensor:
        """The dual at eta (K,), xi (K,), v (P,), unclamped (the value the solver reports
        where its KL safeguard moved eta past the clamps)."""
        _, lse, _ = self.weights_at(eta, xi, v)
        g = (eta * self.eps + eta * lse).sum() + (xi * self.kappa).sum()
        if self.P:
            if self.c is not None:
                g = g + self.c @ v
            g = g + 0.5 * self.ridge * (v @ v)
        return g

    def log_xi_meeting_bound(self, x: Tensor, steps: int = 60) -> Tensor:
        """(K,) log xi per block at which the cross-entropy meets kappa, eta and v held at x.

        The cross-entropy falls as xi grows (dCE/dxi = -Var_P(log p~) / eta), so bisect log xi
        between log eta - 30 and log eta + 10; a block whose bound cannot be met gets the top.
        """
        K = self.K
        a = torch.maximum(x[:K], self.log_eta_min).clamp(max=LOG_ETA_MAX)  # eta in use
        lo, hi = a - 30.0, a + 10.0
        y = x.clone()
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            y[K : 2 * K] = mid
            P, _, _ = self.weights(y)
            above = -(P * self.lr).sum(dim=(1, 2)) > self.kappa
            lo = torch.where(above, mid, lo)
            hi = torch.where(above, hi, mid)
        return hi

    def shows_conflict(self, x: Tensor, g: Tensor) -> bool:
        """Whether a solve ending at x (dual value g) shows that no distribution within the KL
        bound meets the features.

        The dual is then unbounded below and the solve runs off: non-finite values, eta at its
        upper clamp, eta at its lower clamp with the constraint residual (the v-gradient) still
        large, or |v| past ``V_MAX``.
        """
        K = self.K
        if not (bool(torch.isfinite(x).all()) and bool(torch.isfinite(g))):
            return True
        if bool((x[:K] >= LOG_ETA_MAX).any()):
            return True
        if bool((x[:K] <= self.log_eta_min).any()):  # v grows as eta shrinks: the residual tells
            return float(self.evaluate(x)[1][2 * K :].abs().max()) > 1e-3
        return float(x[2 * K :].abs().max()) >= V_MAX
