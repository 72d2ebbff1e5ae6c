"""The standardised K-block dual (see :mod:`hireps_torch.dual`) with its analytic gradient and
curvature, for S independent problems at x = [log eta (K), log xi (K), v (P)] (S, 2K + P)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["LOG_ETA_MAX", "LOG_ETA_MIN", "V_MAX", "DualProblem"]

LOG_ETA_MIN = -30.0  # eta >= e^-30 (standardised units): past this the weights are one-hot
LOG_ETA_MAX = 30.0
V_MAX = 1.0e8  # |v| (standardised) past this means the dual ran off to -infinity


class DualProblem:
    """S standardised K-block duals with their analytic gradients over x = [log eta, log xi, v].

    Gradient (P = softmax of A / eta over (i, o) per block, w = P summed over options):
        dg/d eta_k = eps_k - KL_k = eps_k + lse_k - sum_io P (delta + xi log p~) / eta
        dg/d xi_k  = kappa_k - CE_k = kappa_k + sum_io P log p~
        dg/d v     = c + sum_k w_k^T D_k
    chained to log eta and log xi (zero where eta is clamped or xi is switched off).

    Inputs R (S, K, N), D (S, K, N, P) or None, c (S, P) or None, log_resp (S, K, N, O) (``lr``),
    eps and kappa (S, K). Settable: ``xi_on`` (xi on), ``eta_on`` (eta moves), ``log_eta_min``
    (eta's floor), all (S, K), and ``ridge`` (S,) (adds (ridge / 2) |v|^2).
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
        self.DT = None if D is None else D.mT.contiguous()  # (S, K, P, N): D's columns as rows
        self.S, self.K, self.N, self.O = log_resp.shape
        self.P = 0 if D is None else D.shape[-1]
        self.multi = self.O > 1
        self.log_n = math.log(self.N)
        self.xi_on = torch.zeros(self.S, self.K, dtype=torch.bool, device=R.device)
        self.eta_on = torch.ones(self.S, self.K, dtype=torch.bool, device=R.device)
        self.log_eta_min = R.new_full((self.S, self.K), LOG_ETA_MIN)
        self.ridge = R.new_zeros(self.S)
        self._Dm: Tensor | None = None

    def start(self) -> Tensor:
        """x (S, n) at v = 0, xi = 0.1 and eta from KL ≈ Var(delta) / (2 eta^2) = eps."""
        K = self.K
        x = self.R.new_zeros(self.S, 2 * K + self.P)
        spread = self.R.std(dim=-1).clamp_min(1e-6)
        x[:, :K] = torch.log(spread) - 0.5 * torch.log(2.0 * self.eps.clamp_min(1e-12))
        x[:, :K] = torch.maximum(x[:, :K], self.log_eta_min + 1.0)  # inside the clamp
        x[:, K : 2 * K] = math.log(0.1)
        return x

    def unpack(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(log eta unclamped (S, K), eta (S, K), xi (S, K), v (S, P)) at x (S, n)."""
        K = self.K
        a = x[:, :K]
        eta = torch.maximum(a, self.log_eta_min).clamp(max=LOG_ETA_MAX).exp()
        xi = torch.where(self.xi_on, x[:, K : 2 * K].clamp(max=LOG_ETA_MAX).exp(), 0.0)
        return a, eta, xi, x[:, 2 * K :]

    def advantage(self, v: Tensor) -> Tensor:
        """(S, K, N) delta = R + D v at v (S, P)."""
        if self.DT is None:
            return self.R
        return self.R + (v[:, None, None, :] @ self.DT)[:, :, 0]

    def weights_at(self, eta: Tensor, xi: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(P (S, K, N, O), lse (S, K), delta (S, K, N)) at eta, xi (S, K), v (S, P), unclamped."""
        delta = self.advantage(v)
        P, lse = self._softmax(delta, eta, xi)
        return P, lse, delta

    def _softmax(self, delta: Tensor, eta: Tensor, xi: Tensor) -> tuple[Tensor, Tensor]:
        """(P (S, K, N, O), lse (S, K)) of advantages delta (S, K, N) at eta, xi (S, K)."""
        if self.multi:
            e3 = eta[..., None, None]
            z = (delta.unsqueeze(-1) + (eta + xi)[..., None, None] * self.lr) / e3
        else:
            z = (delta / eta[..., None]).unsqueeze(-1)
        flat = z.reshape(self.S, self.K, -1)
        m = flat.max(dim=-1, keepdim=True).values
        e = (flat - m).exp_()
        s = e.sum(dim=-1, keepdim=True)
        lse = (m + s.log()).squeeze(-1) - self.log_n
        return (e / s).reshape(z.shape), lse

    def curvature(self, x: Tensor, raw: bool = False, weights: Tensor | None = None) -> Tensor:
        """(S, n, n) PSD part of each problem's Hessian at x, as a preconditioner (identity on
        unused and flat directions) or, ``raw``, for Newton steps (``weights``: P at x, if at
        hand).

        In y = (eta, xi, v) block k's Hessian is (1 / eta_k) Cov_P(z), z = [-h / eta_k, log p~, D],
        h = delta + xi log p~; in log space scaled by diag(eta, xi, 1) on both sides (first-order
        term left out).
        """
        S, K = self.S, self.K
        n = x.shape[-1]
        _, eta, xi, v = self.unpack(x)
        if weights is None:
            P, _, delta = self.weights_at(eta, xi, v)
        else:
            P, delta = weights, self.advantage(v)
        free = self.eta_free(x)
        M = x.new_zeros(S, n, n)
        for k in range(K):
            # columns log eta_k, log xi_k (a (S, c, N, O), one contiguous (N, O) per column) and
            # v (D (S, N, P), not expanded over the options), centred under P: Cov = E[a a^T],
            # E[a D^T], E[D D^T]
            pk = P[:, k]  # (S, N, O)
            h = delta[:, k, :, None] + xi[:, k, None, None] * self.lr[:, k]  # (S, N, O)
            zs = [-h * free[:, k, None, None]]
            cols = [k]
            if self.multi:
                zs.append(self.lr[:, k] * (xi[:, k] * self.xi_on[:, k])[:, None, None])
                cols.append(K + k)
            a = torch.stack(zs, 1)  # (S, c, N, O)
            a = a - (pk[:, None] * a).sum((2, 3), keepdim=True)
            pa = pk[:, None] * a
            idx = torch.tensor(cols, device=x.device)
            aa = pa.flatten(2) @ a.flatten(2).mT  # (S, c, c)
            M[:, idx[:, None], idx[None, :]] += aa / eta[:, k, None, None]
            if self.P:
                # D^T (S, P, N) centred under P, from D^T centred once under uniform weights
                Dm = self._centred_features()[:, k]
                w = pk.sum(-1)  # (S, N)
                Dc = Dm - Dm @ w[..., None]
                ad = pa.sum(3) @ Dc.mT  # (S, c, P)
                dd = (Dc * w[:, None, :]) @ Dc.mT  # (S, P, P)
                vi = torch.arange(2 * K, n, device=x.device)
                M[:, idx[:, None], vi[None, :]] += ad / eta[:, k, None, None]
                M[:, vi[:, None], idx[None, :]] += ad.transpose(1, 2) / eta[:, k, None, None]
                M[:, 2 * K :, 2 * K :] += dd / eta[:, k, None, None]
        d = M.diagonal(dim1=1, dim2=2)
        d[:, 2 * K :] += self.ridge[:, None]
        if raw:
            return M
        top = d.amax(dim=1, keepdim=True)
        # unused or flat directions (xi switched off, O = 1, a constant feature): identity
        d.copy_(torch.where(d > 1e-10 * top, d, torch.ones_like(d)) + 1e-10 * top)
        return M

    def _centred_features(self) -> Tensor:
        """(S, K, P, N) D^T centred per block under uniform weights (computed once)."""
        if self._Dm is None:
            assert self.DT is not None
            self._Dm = self.DT - self.DT.mean(dim=-1, keepdim=True)
        return self._Dm

    def eta_free(self, x: Tensor) -> Tensor:
        """(S, K) blocks whose eta is switched on and strictly inside its clamps at x."""
        a = x[:, : self.K]
        free: Tensor = (a > self.log_eta_min) & (a < LOG_ETA_MAX) & self.eta_on
        return free

    def evaluate(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Dual values (S,), gradients (S, n) and weights P (S, K, N, O) at x, from one pass."""
        K = self.K
        a, eta, xi, v = self.unpack(x)
        P, lse, delta = self.weights_at(eta, xi, v)
        w = P.sum(-1) if self.multi else P.squeeze(-1)  # (S, K, N)
        pd = (w * delta).sum(-1)  # (S, K)
        g = (eta * self.eps + eta * lse).sum(-1)
        grad = torch.zeros_like(x)
        if self.multi:
            plr = (P * self.lr).sum((-2, -1))  # -CE, (S, K)
            g = g + (xi * self.kappa).sum(-1)
            d_eta = self.eps + lse - (pd + xi * plr) / eta
            grad[:, K : 2 * K] = torch.where(self.xi_on, xi * (self.kappa + plr), 0.0)
        else:
            d_eta = self.eps + lse - pd / eta
        grad[:, :K] = torch.where(self.eta_free(x), eta * d_eta, 0.0)
        if self.P:
            assert self.DT is not None
            gv = (self.DT @ w[..., None]).sum(1)[..., 0]
            if self.c is not None:
                g = g + (self.c * v).sum(-1)
                gv = gv + self.c
            g = g + 0.5 * self.ridge * (v * v).sum(-1)
            gv = gv + self.ridge[:, None] * v
            grad[:, 2 * K :] = gv
        return g, grad, P

    def value_at(self, eta: Tensor, xi: Tensor, v: Tensor) -> Tensor:
        """The duals (S,) at eta, xi (S, K), v (S, P), unclamped."""
        _, lse, _ = self.weights_at(eta, xi, v)
        g = (eta * self.eps + eta * lse).sum(-1) + (xi * self.kappa).sum(-1)
        if self.P:
            if self.c is not None:
                g = g + (self.c * v).sum(-1)
            g = g + 0.5 * self.ridge * (v * v).sum(-1)
        return g

    def log_xi_meeting_bound(self, x: Tensor, tol: float = 4e-8, steps: int = 60) -> Tensor:
        """(S, K) log xi at which each block's cross-entropy meets kappa, eta and v held at x (to
        ``tol``, on the side that meets it; the top of the bracket where none does), by Illinois
        regula falsi in [log eta - 30, log eta + 10]."""
        K = self.K
        a = torch.maximum(x[:, :K], self.log_eta_min).clamp(max=LOG_ETA_MAX)  # eta in use
        eta = a.exp()
        delta = self.advantage(x[:, 2 * K :])

        def excess(log_xi: Tensor) -> Tensor:  # CE - kappa, falling in log xi
            P, _ = self._softmax(delta, eta, log_xi.clamp(max=LOG_ETA_MAX).exp())
            return -(P * self.lr).sum(dim=(-2, -1)) - self.kappa

        lo, hi = a - 30.0, a + 10.0
        f_lo, f_hi = excess(lo), excess(hi)
        met, unmet = f_lo <= 0, f_hi > 0  # met at the bottom already / nowhere: no root inside
        lo, hi = torch.where(unmet, hi, lo), torch.where(met, lo, hi)
        kept = torch.zeros_like(f_lo)  # +1: lo kept by the last step, -1: hi kept
        for _ in range(steps):
            open_ = (hi - lo) > tol
            if not bool(open_.any()):
                break
            # the secant's point, kept tol / 2 inside the bracket
            t = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
            t = torch.where(torch.isfinite(t), t, 0.5 * (lo + hi))
            t = torch.minimum(torch.maximum(t, lo + 0.5 * tol), hi - 0.5 * tol)
            f = excess(t)
            up, down = open_ & (f > 0), open_ & ~(f > 0)
            lo, f_lo = torch.where(up, t, lo), torch.where(up, f, f_lo)
            hi, f_hi = torch.where(down, t, hi), torch.where(down, f, f_hi)
            lo = torch.where(down & (f == 0), t, lo)  # met exactly
            # Illinois: an end kept twice in a row has the other end's value halved
            f_hi = torch.where(up & (kept > 0), 0.5 * f_hi, f_hi)
            f_lo = torch.where(down & (kept < 0), 0.5 * f_lo, f_lo)
            kept = torch.where(up, 1.0, torch.where(down, -1.0, kept))
        return hi

    def shows_conflict(self, x: Tensor, g: Tensor) -> Tensor:
        """(S,) whether a solve ending at x (dual values g) ran off: non-finite, eta at its upper
        clamp, eta at its floor with a large v-gradient, or |v| past ``V_MAX`` (no distribution
        within the KL bound meets the features)."""
        K = self.K
        bad = ~(torch.isfinite(x).all(-1) & torch.isfinite(g))
        bad |= (x[:, :K] >= LOG_ETA_MAX).any(-1)
        low = (x[:, :K] <= self.log_eta_min).any(-1)
        # per problem: at its eta floor the residual tells (v grows as eta shrinks), else |v|
        resid = self.evaluate(torch.nan_to_num(x))[1][:, 2 * K :].abs().amax(-1)
        ran = (x[:, 2 * K :].abs() >= V_MAX).any(-1)
        flagged: Tensor = bad | torch.where(low, resid > 1e-3, ran)
        return flagged
