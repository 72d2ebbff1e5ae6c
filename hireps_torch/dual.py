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

Numerics: everything in float64 whatever the input dtype. Before solving, v is written as
v0 + scale * T u: v0 is the small-epsilon solution (a least-squares fit of the returns on the
features, block-weighted by 1/eta; 0 when the dual has a linear term c), the returns become
the Bellman errors at v0, centred per block and divided by their common spread ``scale``, and
T whitens the features (per-block centred, block-weighted). The weights are invariant to all
of it; eta, xi and v are mapped back to the caller's units. This keeps the problem well
conditioned when the features explain most of the returns (a converging policy) and when they
are nearly collinear. eta and xi live in log space; log-sum-exp subtracts the max. The entropy
bound is handled by its KKT conditions: the dual is solved with xi free, then re-solved with
xi = 0 exactly for blocks whose xi ended ~0 with the bound slack; a block whose xi collapsed
with the bound still violated (the log-space gradient vanishes there) restarts from the xi
that meets it, and ``converged`` checks the bound itself. When no distribution within the KL
bound meets the feature constraints (few samples against many features, common in the
infinite-horizon dual) the dual is unbounded below; the solver detects it, warns
(:class:`InfeasibleConstraintsWarning`) and re-solves with a ridge on the standardised u, which
turns the feature constraints into a quadratic penalty and keeps the KL bound
(``feature_error`` then reports the remaining violation).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "DegenerateWeightsWarning",
    "DualSolution",
    "InfeasibleConstraintsWarning",
    "RepsDualSolution",
    "TimeIndexedDualSolution",
    "solve_episodic_dual",
    "solve_infinite_horizon_dual",
    "solve_reps_dual",
    "solve_time_indexed_dual",
]

_LOG_RESP_FLOOR = -1.0e4  # stands in for log(0) of pruned options; exp() of it is exactly 0
_LOG_ETA_MIN = -30.0  # eta >= e^-30 (standardised units): past this the weights are one-hot
_LOG_ETA_MAX = 30.0
_V_MAX = 1.0e8  # |v| (standardised) past this means the dual ran off to -infinity
_CONFLICT_RIDGE = 1.0e-2  # ridge on the standardised v when the feature constraints conflict


class DegenerateWeightsWarning(RuntimeWarning):
    """The weights collapsed (or will collapse) onto very few samples."""


class InfeasibleConstraintsWarning(RuntimeWarning):
    """No distribution within the KL bound satisfies the feature constraints."""


@dataclass(frozen=True)
class RepsDualSolution:
    """Solution of the generic K-block dual (:func:`solve_reps_dual`).

    Attributes:
        eta: (K,) temperatures, in the caller's return units.
        xi: (K,) entropy-bound multipliers (0 where the bound is inactive or absent).
        v: (P,) value-function / feature multipliers in the caller's feature units.
        weights: (K, N, O) new sample-option distribution per block, each block sums to 1.
        kl: (K,) realised KL(P_k || q p~_k).
        cross_entropy: (K,) realised E_P[-log p~].
        effective_sample_size: (K,) 1 / sum_i w_ki^2 with w_ki = sum_o P_kio.
        feature_error: max abs violation of the feature constraints, caller's units.
        dual_value: value of the dual at the optimum, caller's units.
        converged: whether LBFGS met its gradient tolerance (False, with an
            :class:`InfeasibleConstraintsWarning`, when the feature constraints cannot be met
            within the KL bound and were relaxed to a penalty).
        iterations: LBFGS iterations over all phases.
    """

    eta: Tensor
    xi: Tensor
    v: Tensor
    weights: Tensor
    kl: Tensor
    cross_entropy: Tensor
    effective_sample_size: Tensor
    feature_error: float
    dual_value: float
    converged: bool
    iterations: int


@dataclass(frozen=True)
class DualSolution:
    """Solution of the episodic HiREPS dual (:func:`solve_episodic_dual`).

    Attributes:
        eta: temperature of the KL bound (inf when the returns carry no information).
        xi: multiplier of the entropy bound; 0 when inactive or when no bound was given.
        v: (F,) context-feature multipliers (empty without context features).
        weights: (N, O) new distribution over samples and options; sums to 1.
        sample_weights: (N,) weights.sum(-1), the weights for a flat policy.
        kl: realised KL(P || q p~); equals epsilon when the bound is active.
        cross_entropy: realised E_P[-log p~(o|s,theta)]; equals kappa when that bound is active.
        effective_sample_size: 1 / sum_i sample_weights_i^2, between 1 and N.
        feature_error: max |sum_i w_i phi_i - phi_hat| (0 without context features).
        dual_value: dual objective at the optimum.
        converged: whether the solver met its gradient tolerance.
        iterations: LBFGS iterations.
    """

    eta: float
    xi: float
    v: Tensor
    weights: Tensor
    sample_weights: Tensor
    kl: float
    cross_entropy: float
    effective_sample_size: float
    feature_error: float
    dual_value: float
    converged: bool
    iterations: int


@dataclass(frozen=True)
class TimeIndexedDualSolution:
    """Solution of the time-indexed HiREPS dual (:func:`solve_time_indexed_dual`).

    Steps are indexed k = 0..K-1 here (1..K in the equations).

    Attributes:
        eta: (K,) temperatures of the per-step KL bounds (all inf when the rewards carry no
            information).
        xi: (K,) multipliers of the per-step entropy bounds (0 where inactive or absent).
        v: (K, F) value-function weights: V_k(s) = v[k]^T phi(s).
        weights: (K, N, O) new distribution over samples and options per step; each step
            sums to 1.
        sample_weights: (K, N) weights.sum(-1), the weights of a flat policy per step.
        kl: (K,) realised KL(P_k || q p~_k); equals epsilon_k at the optimum.
        cross_entropy: (K,) realised E_P_k[-log p~_k]; <= kappa_k.
        effective_sample_size: (K,) 1 / sum_i w_ki^2 per step.
        feature_error: max abs violation of the chained feature constraints.
        dual_value: dual objective at the optimum.
        converged: whether the solver met its gradient tolerance.
        iterations: LBFGS iterations.
    """

    eta: Tensor
    xi: Tensor
    v: Tensor
    weights: Tensor
    sample_weights: Tensor
    kl: Tensor
    cross_entropy: Tensor
    effective_sample_size: Tensor
    feature_error: float
    dual_value: float
    converged: bool
    iterations: int

    def step(self, k: int) -> DualSolution:
        """Step k as a :class:`DualSolution` (weights (N, O), v = v[k]); ``feature_error``,
        ``dual_value``, ``converged`` and ``iterations`` are those of the whole problem."""
        K = self.eta.shape[0]
        if not 0 <= k < K:
            raise ValueError(f"step must be in [0, {K}), got {k}")
        return _block(self, k, self.v[k])


# --------------------------------------------------------------------------------------------
# input checks


def _as_f64(name: str, x: Tensor | object) -> Tensor:
    if not isinstance(x, Tensor):
        try:
            x = torch.as_tensor(x)
        except Exception as exc:  # pragma: no cover - message only
            raise TypeError(f"{name} must be a tensor, got {type(x).__name__}") from exc
    return x.detach().to(torch.float64)


def _check_finite(name: str, x: Tensor) -> None:
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{name} contains {int(bad.sum())} non-finite value(s) (first at index {idx}: "
            f"{x[idx].item()}); remove or fix those samples before the update"
        )


def _check_positive(name: str, value: Tensor) -> None:
    if not bool(torch.isfinite(value).all()) or bool((value <= 0).any()):
        raise ValueError(f"{name} must be finite and > 0, got {value.tolist()}")


def _check_log_resp(log_resp: Tensor, name: str = "log_responsibilities") -> Tensor:
    if bool(torch.isnan(log_resp).any()) or bool((log_resp == math.inf).any()):
        raise ValueError(f"{name} contains NaN or +inf")
    if bool((log_resp > 1e-6).any()):
        raise ValueError(f"{name} must be log-probabilities (<= 0), max is {log_resp.max().item()}")
    norm = torch.logsumexp(log_resp, dim=-1)
    worst = (norm.abs()).max().item()
    if worst > 1e-4:
        raise ValueError(
            f"{name} must be normalised over options (logsumexp over the last dim = 0); "
            f"worst row is off by {worst:.3g}"
        )
    return log_resp.clamp_min(_LOG_RESP_FLOOR)


# --------------------------------------------------------------------------------------------
# the generic K-block dual


class _Problem:
    """Standardised K-block dual with its analytic gradient over x = [log eta, log xi, v].

    Gradient (P = softmax of A / eta over (i, o) per block, w = P summed over options):
        dg/d eta_k = eps_k - KL_k = eps_k + lse_k - sum_io P (delta + xi log p~) / eta
        dg/d xi_k  = kappa_k - CE_k = kappa_k + sum_io P log p~
        dg/d v     = c + sum_k w_k^T D_k
    chained to log eta and log xi (zero where eta is clamped or xi is switched off).
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
        self.ridge = 0.0  # (ridge / 2) |v|^2 added to the dual when the constraints conflict

    def unpack(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        K = self.K
        a = x[:K]
        eta = a.clamp(_LOG_ETA_MIN, _LOG_ETA_MAX).exp()
        xi = torch.where(self.xi_on, x[K : 2 * K].clamp(max=_LOG_ETA_MAX).exp(), 0.0)
        return a, eta, xi, x[2 * K :]

    def weights(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(P (K, N, O), lse (K,), delta (K, N)) at x."""
        _, eta, xi, v = self.unpack(x)
        return self._weights(eta, xi, v)

    def _weights(self, eta: Tensor, xi: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
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

    def curvature(self, x: Tensor) -> Tensor:
        """Positive semi-definite part of the Hessian in x, used as a preconditioner.

        In y = (eta, xi, v) the Hessian of block k is exactly (1 / eta_k) Cov_P(z) with
        z = [-h / eta_k, log p~, D] and h = delta + xi log p~ (the linear terms of the dual add
        no curvature); the log-parametrisation scales it by diag(eta, xi, 1) on both sides
        (its first-order term, which vanishes at the optimum, is left out).
        """
        K, n = self.K, x.shape[0]
        _, eta, xi, v = self.unpack(x)
        P, _, delta = self._weights(eta, xi, v)
        M = torch.zeros(n, n, dtype=x.dtype)
        for k in range(K):
            h = delta[k].unsqueeze(-1) + xi[k] * self.lr[k]  # (N, O)
            cols = [k]
            zs = [-h]  # d u / d log eta = -h / eta, times eta
            if self.multi and bool(self.xi_on[k]):
                cols.append(K + k)
                zs.append(self.lr[k] * xi[k])
            if self.P:
                assert self.D is not None
                cols.extend(range(2 * K, n))
                zs.extend(self.D[k].unsqueeze(1).expand(-1, self.O, -1).unbind(-1))
            Z = torch.stack([z.expand(self.N, self.O) for z in zs], -1).reshape(-1, len(cols))
            p = P[k].reshape(-1, 1)
            Zc = Z - (p * Z).sum(0)
            idx = torch.tensor(cols)
            M[idx[:, None], idx[None, :]] += (Zc * p).T @ Zc / eta[k]
        d = M.diagonal()
        d[2 * K :] += self.ridge
        top = float(d.max()) if n else 1.0
        # unused or flat directions (xi switched off, O = 1, a constant feature): identity
        d.copy_(torch.where(d > 1e-10 * top, d, torch.ones_like(d)) + 1e-10 * top)
        return M

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Dual value and its gradient in x."""
        g, grad, _ = self.evaluate(x)
        return g, grad

    def evaluate(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Dual value, gradient in x and the weights P (K, N, O), from one pass."""
        a, eta, xi, v = self.unpack(x)
        P, lse, delta = self._weights(eta, xi, v)
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
        inside = (a > _LOG_ETA_MIN) & (a < _LOG_ETA_MAX)
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
    """Solve the K-block HiREPS dual (see the module docstring).

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
        A :class:`RepsDualSolution` in the caller's units.
    """
    R = _as_f64("R", R)
    K, N = R.shape
    O = log_resp.shape[-1]
    log_resp = log_resp.to(torch.float64)
    if O > 1 and (kappa is None or not bool(torch.isfinite(kappa).any())):
        # Without an entropy bound (xi = 0) the options enter the dual only through
        # sum_o p~_io: P_io = w_i p~_io, with w the one-option solution. Solving that is exact
        # and O times cheaper (e.g. 100 hard-gated options).
        row = torch.logsumexp(log_resp, dim=-1, keepdim=True)
        one = solve_reps_dual(
            R,
            row,
            epsilon,
            D=D,
            c=c,
            max_iter=max_iter,
            tolerance_grad=tolerance_grad,
            converged_grad=converged_grad,
        )
        w = one.weights * torch.exp(log_resp - row)
        return _finish(
            w / w.sum(dim=(1, 2), keepdim=True),
            log_resp,
            one.eta,
            one.xi,
            one.v,
            D,
            c,
            one.dual_value,
            one.converged,
            one.iterations,
        )

    # Standardise (the weights are invariant to all of it; eta, xi and v are mapped back).
    # Returns: centred per block and divided by one common spread (the blocks are coupled
    # through v). Value multipliers: the dual is invariant to writing v = v0 + scale * T u
    # while the returns become the Bellman errors R + D v0, so solve for u with
    #   R_s = (R + D v0 - block means) / scale,   D_s = D T.
    # v0 is the small-epsilon solution (without c; see _value_start) and T whitens the
    # curvature of the dual in v at the start, sum_k Cov(D_k) / eta_k. Both matter once the
    # features explain most of the returns (a converging policy): scaled by the returns, eta
    # is ~1e-5 and the v-curvature ~1/eta, and collinear features (phi = [s, s^2] with s in a
    # narrow range) or blocks with very different eta make it ill-conditioned besides; LBFGS
    # then stalls or runs off.
    eps = epsilon.to(torch.float64)
    resid = R - R.mean(dim=1, keepdim=True)
    T = None  # v = v0 + scale * T u (v0 and T in the caller's feature units)
    Ds = cs = None
    v0 = torch.zeros(0 if D is None else D.shape[-1], dtype=torch.float64)
    floor = 1e-12 * max(1.0, float(R.abs().max()))
    if D is not None and D.shape[-1] > 0:
        D = D.to(torch.float64)
        col = D.reshape(K * N, -1).std(dim=0)
        col = torch.where(col > 1e-12, col, torch.ones_like(col))
        Dc = (D - D.mean(dim=1, keepdim=True)) / col  # per-block centred, unit columns
        if c is None:
            v0 = _value_start(resid, Dc, eps, floor) / col
            resid = resid + D @ v0
        # block weights 1 / eta_k at the start (KL ≈ Var(delta_k) / (2 eta_k^2) = eps_k)
        spread = (resid - resid.mean(dim=1, keepdim=True)).std(dim=1).clamp_min(floor)
        weight = (2.0 * eps).sqrt() / spread
        T = _whitening(Dc, weight / weight.max()) / col[:, None]
        Ds = D @ T
        cs = None if c is None else T.T @ c.to(torch.float64)
    offset = resid.mean(dim=1, keepdim=True)
    resid = resid - offset
    scale = float(resid.std()) if resid.numel() > 1 else 1.0
    if not scale > 1e-10 * max(1.0, float(R.abs().max())):
        # No return information (beyond what the features fix): every distribution that keeps
        # the features is optimal; keep the old one.
        w = log_resp.exp() / N
        w = w / w.sum(dim=(1, 2), keepdim=True)
        return _finish(
            w,
            log_resp,
            torch.full((K,), math.inf, dtype=torch.float64),
            torch.zeros(K, dtype=torch.float64),
            torch.zeros(0 if D is None else D.shape[-1], dtype=torch.float64),
            D,
            c,
            math.nan,
            True,
            0,
        )
    Rs = resid / scale
    kap = torch.full((K,), math.inf, dtype=torch.float64)
    if kappa is not None:
        kap = kappa.to(torch.float64)
    bounded = torch.isfinite(kap)  # blocks with an entropy bound
    kap = torch.where(bounded, kap, 0.0)
    prob = _Problem(Rs, Ds, cs, log_resp, eps, kap)

    # Start at u = 0 with eta from KL ≈ Var(delta) / (2 eta^2) (the small-epsilon solution).
    # Good starts save LBFGS iterations, which dominate the cost.
    x = torch.zeros(2 * K + prob.P, dtype=torch.float64)
    spread = Rs.std(dim=1).clamp_min(1e-6)
    x[:K] = torch.log(spread) - 0.5 * torch.log(2.0 * eps.clamp_min(1e-12))
    x[K : 2 * K] = math.log(0.1)
    total_iter = 0

    def run_phase() -> tuple[bool, Tensor, Tensor]:
        """One LBFGS solve from x; returns (converged, dual value, weights) at its end."""
        # With options, LBFGS runs in whitened coordinates x = x0 + L^-T z, L L^T the
        # curvature at x0: there the Hessian is ~I, which saves LBFGS iterations (the xi
        # direction is badly scaled against eta and v otherwise).
        nonlocal total_iter, x
        x0 = x.clone()
        L: Tensor | None = None
        if prob.multi:  # measured: with one option the plain problem is as well scaled
            try:
                L = torch.linalg.cholesky(prob.curvature(x0))
            except RuntimeError:
                pass
        z = torch.zeros_like(x0)
        opt = torch.optim.LBFGS(
            [z],
            lr=1.0,
            max_iter=max_iter,
            tolerance_grad=tolerance_grad,
            tolerance_change=1e-15,
            history_size=20,
            line_search_fn="strong_wolfe",
        )

        def to_x(zz: Tensor) -> Tensor:
            if L is None:
                return x0 + zz
            return x0 + torch.linalg.solve_triangular(L.T, zz[:, None], upper=True)[:, 0]

        def closure() -> Tensor:
            g, grad = prob.value_and_grad(to_x(z))
            if L is not None:
                grad = torch.linalg.solve_triangular(L, grad[:, None], upper=False)[:, 0]
            z.grad = grad
            return g

        opt.step(closure)
        total_iter += int(opt.state[z].get("n_iter", 0))
        x = to_x(z)
        g, grad, P = prob.evaluate(x)
        return float(grad.abs().max()) <= converged_grad, g, P

    def solve() -> tuple[bool, Tensor, Tensor]:
        nonlocal x
        entropy_bound = O > 1 and bool(bounded.any())
        if entropy_bound:
            # KKT for xi >= 0: solve with xi free; where xi ends ~0 with the bound slack,
            # switch it off and re-solve (then xi = 0 exactly and the bound holds as inequality).
            prob.xi_on[:] = bounded
            converged, g, w = run_phase()
            for _ in range(3):
                # In log space the dual is nearly flat in xi below the xi that meets the bound
                # (the xi-gradient xi (kappa - CE) vanishes with xi): a line search can jump
                # there and LBFGS stops with xi ~0 and the bound violated. Restart from the
                # xi that meets the bound with the rest held fixed.
                ce = -(w * log_resp).sum(dim=(1, 2))
                stuck = prob.xi_on & (ce > kap + 1e-6)
                if not bool(stuck.any()):
                    break
                x[K : 2 * K] = torch.where(stuck, _xi_meeting_bound(prob, x), x[K : 2 * K])
                converged, g, w = run_phase()
            ce = -(w * log_resp).sum(dim=(1, 2))
            slack = (x[K : 2 * K].exp() < 1e-6) & (ce <= kap + 1e-9)
            if bool(slack.any()):
                prob.xi_on &= ~slack
                converged, g, w = run_phase()
        else:
            converged, g, w = run_phase()
        for _ in range(2):
            # a stalled LBFGS (its preconditioner, the curvature at the phase's start, gone
            # stale) resumes with the curvature where it stopped
            if converged or not bool(torch.isfinite(x).all()):
                break
            converged, g, w = run_phase()
        if entropy_bound:
            # the log-space gradient hides a violated bound when xi ~0: check it directly
            ce = -(w * log_resp).sum(dim=(1, 2))
            converged = converged and bool((ce[bounded] <= kap[bounded] + 1e-6).all())
        return converged, g, w

    x_start = x.clone()
    converged, g, w = solve()
    # An unconverged solve that broke the KL bound ran off the same way, only more slowly.
    ran_off = not converged and bool((_block_kl(w, log_resp) > 1.01 * eps + 1e-3).any())
    conflict = bool(prob.P) and _conflicting(prob, x, g)
    if prob.P and (ran_off or conflict):
        # No distribution within the KL bound meets the feature constraints: either none at
        # all does (c lies outside the convex hull of the rows of -D, typical of few samples
        # against many features) or only ones with KL > epsilon do. The dual is then unbounded
        # below (eta or v run off). A ridge on v bounds it again: the feature constraints
        # become a quadratic penalty while the KL bound, the point of REPS, still holds (the
        # alternative, the closest distribution that meets them, can collapse onto a single
        # sample and wreck the policy).
        for factor in (1.0, 10.0, 100.0, 1e3, 1e4):
            # a stronger penalty where the weaker one still let the solve run off
            prob.ridge = factor * _CONFLICT_RIDGE
            x = x_start.clone()
            _, g, w = solve()
            kl_kept = not bool((_block_kl(w, log_resp) > 1.01 * eps + 1e-3).any())
            if kl_kept:
                break
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
        warnings.warn(
            f"{why} epsilon = {eps.tolist()} (too few samples for the {prob.P} features?): "
            f"they are relaxed to a quadratic penalty (ridge {prob.ridge:g} on the "
            f"standardised value weights) and {kept}; see feature_error and kl",
            InfeasibleConstraintsWarning,
            stacklevel=2,
        )
        converged = False

    _, eta_s, xi_s, u = prob.unpack(x)
    v_out = v0 + scale * (T @ u) if T is not None else u.clone()
    # every term scales with the return scale; the centring adds back the block means
    dual_value = float(g) * scale + float(R.mean(dim=1).sum() + offset.sum())
    return _finish(
        w, log_resp, eta_s * scale, xi_s * scale, v_out, D, c, dual_value, converged, total_iter
    )


def _xi_meeting_bound(prob: _Problem, x: Tensor, steps: int = 60) -> Tensor:
    """(K,) log xi per block at which the cross-entropy meets kappa, eta and v held at x.

    The cross-entropy falls as xi grows (dCE/dxi = -Var_P(log p~) / eta), so bisect log xi
    between log eta - 30 and log eta + 10; a block whose bound cannot be met gets the top.
    """
    K = prob.K
    lo, hi = x[:K] - 30.0, x[:K] + 10.0
    y = x.clone()
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        y[K : 2 * K] = mid
        P, _, _ = prob.weights(y)
        above = -(P * prob.lr).sum(dim=(1, 2)) > prob.kappa
        lo = torch.where(above, mid, lo)
        hi = torch.where(above, hi, mid)
    return hi


def _value_start(Rc: Tensor, Dc: Tensor, eps: Tensor, floor: float, rounds: int = 30) -> Tensor:
    """Small-epsilon value multipliers (the solver's start when c = 0).

    Args:
        Rc: (K, N) returns centred per block.
        Dc: (K, N, P) features centred per block.
        eps: (K,) KL bounds.
        floor: smallest residual spread taken seriously.

    For small epsilon w_ki ≈ (1 + (delta_ki - mean_i delta_k) / eta_k) / N, so the feature
    constraint sum_k w_k^T D_k = 0 (met by uniform weights when c = 0) makes v the weighted
    least-squares fit of -R on the centred D with block weights 1 / eta_k, and
    KL_k ≈ Var(delta_k) / (2 eta_k^2) = eps_k ties each eta_k to its block's residual spread.
    One block: plain least squares. Several: iterate the weights (a block that the features fit
    closely gets a small eta and dominates its part of v; an unweighted fit spoils it and leaves
    the optimum far from the start).
    """
    K, N, P = Dc.shape
    weight = torch.ones(K, dtype=torch.float64)
    v = torch.zeros(P, dtype=torch.float64)
    for _ in range(rounds if K > 1 else 1):
        root = weight.sqrt()[:, None]
        A = (root[:, :, None] * Dc).reshape(K * N, P)
        b = (root * Rc).reshape(K * N, 1)
        v = -torch.linalg.lstsq(A, b, driver="gelsd").solution.squeeze(1)
        spread = (Rc + Dc @ v).std(dim=1).clamp_min(floor)
        new = (2.0 * eps).sqrt() / spread
        new = new / new.max()
        if bool(((new - weight).abs() <= 1e-3 * weight).all()):
            break
        weight = new
    return v


def _whitening(Dc: Tensor, weight: Tensor) -> Tensor:
    """(P, P) map T with T^T (sum_k weight_k Dc_k^T Dc_k / N) T = I on the identified
    directions, from (K, N, P) centred features and (K,) block weights. Directions without
    spread (a constant feature, collinear columns) keep the largest direction's scale."""
    K, N, P = Dc.shape
    A = (weight.sqrt()[:, None, None] * Dc).reshape(K * N, P) / math.sqrt(N)
    _, S, Vh = torch.linalg.svd(A, full_matrices=False)
    top = float(S.max()) if S.numel() else 1.0
    inv = torch.where(S > 1e-8 * top, 1.0 / S.clamp_min(1e-300), 1.0 / top)
    T = torch.eye(P, dtype=torch.float64)
    T[:, : S.shape[0]] = Vh.T * inv
    if S.shape[0] < P:  # fewer rows than features: complete the basis
        Q = torch.linalg.qr(torch.cat([Vh.T, torch.eye(P, dtype=torch.float64)], 1)).Q
        T[:, S.shape[0] :] = Q[:, S.shape[0] : P] / top
    return T


def _conflicting(prob: _Problem, x: Tensor, g: Tensor) -> bool:
    """Whether a solve shows that no distribution within the KL bound meets the features.

    The dual is then unbounded below and the solve runs off: non-finite values, eta at its
    upper clamp, eta at its lower clamp with the constraint residual (the v-gradient) still
    large, or |v| past ``_V_MAX``.
    """
    K = prob.K
    if not (bool(torch.isfinite(x).all()) and bool(torch.isfinite(g))):
        return True
    if bool((x[:K] >= _LOG_ETA_MAX).any()):
        return True
    if bool((x[:K] <= _LOG_ETA_MIN).any()):  # v grows as eta shrinks: the residual tells
        return float(prob.evaluate(x)[1][2 * K :].abs().max()) > 1e-3
    return float(x[2 * K :].abs().max()) >= _V_MAX


def _block_kl(w: Tensor, log_resp: Tensor) -> Tensor:
    """(K,) KL(P_k || q p~_k) of weights (K, N, O) against the old distribution."""
    logq = log_resp - math.log(w.shape[1])
    logw = torch.log(w.clamp_min(1e-300))
    return torch.where(w > 0, w * (logw - logq), torch.zeros_like(w)).sum(dim=(1, 2))


def _finish(
    w: Tensor,
    log_resp: Tensor,
    eta: Tensor,
    xi: Tensor,
    v: Tensor,
    D: Tensor | None,
    c: Tensor | None,
    dual_value: float,
    converged: bool,
    iterations: int,
) -> RepsDualSolution:
    K, N, O = w.shape
    kl = _block_kl(w, log_resp)
    ce = -(w * log_resp).sum(dim=(1, 2))
    ws = w.sum(-1)  # (K, N)
    ess = 1.0 / (ws**2).sum(dim=1)
    feat_err = 0.0
    if D is not None and D.shape[-1] > 0:
        grad_v = torch.einsum("kn,knp->p", ws, D.to(torch.float64))
        if c is not None:
            grad_v = grad_v + c.to(torch.float64)
        feat_err = float(grad_v.abs().max())
    return RepsDualSolution(
        eta=eta,
        xi=xi,
        v=v,
        weights=w,
        kl=kl,
        cross_entropy=ce,
        effective_sample_size=ess,
        feature_error=feat_err,
        dual_value=dual_value,
        converged=converged,
        iterations=iterations,
    )


# --------------------------------------------------------------------------------------------
# inputs and outputs shared by the episodic, infinite-horizon and time-indexed wrappers


def _per_block(name: str, value: float | Tensor, K: int) -> Tensor:
    """A bound given as one float or one value per block (K,), as a (K,) float64 tensor."""
    t = _as_f64(name, value)
    if t.dim() == 0:
        return t.expand(K).clone()
    if t.shape != (K,):
        raise ValueError(
            f"{name} must be a float or have shape ({K},) (one per decision step), got "
            f"{tuple(t.shape)}"
        )
    return t


def _shape_text(lead: tuple[int, ...], last: str) -> str:
    """'(N, K, F) = (60, 3, F)' for lead (60, 3) and last 'F'."""
    names = ["N", "K"][: len(lead)] + [last]
    return f"({', '.join(names)}) = ({', '.join([*map(str, lead), last])})"


def _common_inputs(
    returns: Tensor,
    epsilon: float | Tensor,
    log_responsibilities: Tensor | None,
    kappa: float | Tensor | None,
    name: str = "returns",
    *,
    per_step: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Validate the inputs every wrapper shares and return them block-major for the solver.

    Args:
        returns: (N,) returns, or (N, K) rewards of K decision steps when ``per_step``.
        epsilon: KL bound, > 0: a float or (K,).
        log_responsibilities: (N, O), or (N, K, O) when ``per_step``; None means one option.
        kappa: entropy bound, >= 0 (inf: no bound on that block): None, a float or (K,).
        name: what the error messages call ``returns``.
        per_step: whether the returns are per decision step (the time-indexed dual).

    Returns:
        R (K, N), epsilon (K,), log p~ (K, N, O) with log 0 floored, kappa (K,) or None.
    """
    R = _as_f64(name, returns)
    if R.dim() != (2 if per_step else 1):
        raise ValueError(
            f"{name} must have shape ({'N, K' if per_step else 'N,'}), got {tuple(R.shape)}"
        )
    N = R.shape[0]
    if N < 2:
        raise ValueError(f"the dual needs at least 2 samples, got N = {N}")
    if R.numel() == 0:
        raise ValueError(
            f"{name} must hold at least one decision step (K >= 1), got shape {tuple(R.shape)}"
        )
    _check_finite(name, R)
    R = R.reshape(N, -1).T.contiguous()
    K = R.shape[0]
    eps = _per_block("epsilon", epsilon, K)
    _check_positive("epsilon", eps)
    big = [(k, float(e)) for k, e in enumerate(eps) if e >= math.log(N)]
    if big:
        which = ", ".join(
            f"epsilon = {e:.4g}" if K == 1 else f"epsilon[{k}] = {e:.4g}" for k, e in big
        )
        warnings.warn(
            f"{which} >= log N = {math.log(N):.4g} (N = {N}): the KL bound cannot bind and the "
            "weights collapse onto the best sample(s); use a smaller epsilon or more samples",
            DegenerateWeightsWarning,
            stacklevel=3,
        )
    lead = (N, K) if per_step else (N,)
    if log_responsibilities is None:
        lr = torch.zeros(K, N, 1, dtype=torch.float64)
    else:
        lr = _as_f64("log_responsibilities", log_responsibilities)
        if lr.dim() != len(lead) + 1 or tuple(lr.shape[:-1]) != lead:
            raise ValueError(
                f"log_responsibilities must have shape {_shape_text(lead, 'O')}, got "
                f"{tuple(lr.shape)}"
            )
        lr = _check_log_resp(lr).reshape(N, K, -1).transpose(0, 1).contiguous()
    kap = None
    if kappa is not None:
        kap = _per_block("kappa", kappa, K)
        if bool(torch.isnan(kap).any()) or bool((kap < 0).any()):
            raise ValueError(f"kappa must be >= 0 (inf: no bound), got {kap.tolist()}")
    return R, eps, lr, kap


def _features(name: str, x: Tensor, *lead: int) -> Tensor:
    """Check features of shape (*lead, F): (N, F), or (N, K, F) per decision step."""
    phi = _as_f64(name, x)
    if phi.dim() != len(lead) + 1 or tuple(phi.shape[:-1]) != lead:
        raise ValueError(f"{name} must have shape {_shape_text(lead, 'F')}, got {tuple(phi.shape)}")
    _check_finite(name, phi)
    return phi


def _feature_vector(name: str, x: Tensor, F: int) -> Tensor:
    """Check a mean feature vector (F,) such as phi_hat_0."""
    phi = _as_f64(name, x).reshape(-1)
    if phi.shape != (F,):
        raise ValueError(f"{name} must have shape ({F},), got {tuple(phi.shape)}")
    _check_finite(name, phi)
    return phi


def _warn_if_collapsed(sol: RepsDualSolution, epsilon: Tensor) -> None:
    """Warn (at the wrapper's caller) when a block's weights sit on ~one sample."""
    K, N, _ = sol.weights.shape
    ess = sol.effective_sample_size
    bad = ((ess < 1.5) & sol.eta.isfinite()).nonzero().flatten().tolist()
    if bad:
        which = ", ".join(
            ("" if K == 1 else f"step {k}: ")
            + f"~{float(ess[k]):.2f} effective samples (epsilon = {float(epsilon[k]):.4g})"
            for k in bad
        )
        warnings.warn(
            f"the weights collapsed onto {which} with N = {N}; the refit will rely on its "
            "variance floor",
            DegenerateWeightsWarning,
            stacklevel=3,
        )


def _block(sol: RepsDualSolution | TimeIndexedDualSolution, k: int, v: Tensor) -> DualSolution:
    """Block k of a K-block solution as a :class:`DualSolution` with value weights ``v``."""
    w = sol.weights[k]
    return DualSolution(
        eta=float(sol.eta[k]),
        xi=float(sol.xi[k]),
        v=v,
        weights=w,
        sample_weights=w.sum(-1),
        kl=float(sol.kl[k]),
        cross_entropy=float(sol.cross_entropy[k]),
        effective_sample_size=float(sol.effective_sample_size[k]),
        feature_error=sol.feature_error,
        dual_value=sol.dual_value,
        converged=sol.converged,
        iterations=sol.iterations,
    )


# --------------------------------------------------------------------------------------------
# episodic / contextual HiREPS


def solve_episodic_dual(
    returns: Tensor,
    *,
    epsilon: float,
    log_responsibilities: Tensor | None = None,
    context_features: Tensor | None = None,
    kappa: float | None = None,
    max_iter: int = 300,
) -> DualSolution:
    """Solve the episodic / contextual HiREPS dual and return the new sample weights.

    Args:
        returns: (N,) return of each sample, N >= 2.
        epsilon: KL bound, > 0. Values >= log N let the weights collapse onto one sample
            (a :class:`DegenerateWeightsWarning` is issued).
        log_responsibilities: (N, O) log p~(o | s_i, theta_i) of the old policy, rows
            normalised over options; None means one option (REPS).
        context_features: (N, F) context features phi(s_i) whose mean must be kept; None means
            no context (plain episodic). A constant column is harmless (its multiplier is 0).
        kappa: absolute bound on the expected option cross-entropy E_P[-log p~], >= 0;
            None (or inf) means no entropy bound (xi = 0).
        max_iter: LBFGS iterations per phase.

    Returns:
        :class:`DualSolution` with weights (N, O) summing to 1.

    Raises:
        ValueError: on non-finite returns or features, shape mismatches, N < 2, epsilon <= 0 or
            a negative kappa; each message names the offending value.
    """
    R, eps, lr, kap = _common_inputs(returns, epsilon, log_responsibilities, kappa)
    N = R.shape[1]
    D = None
    if context_features is not None:
        phi = _features("context_features", context_features, N)
        # Centred features: v^T phi_hat - v^T phi_i = -v^T (phi_i - phi_hat); c = 0.
        D = -(phi - phi.mean(dim=0, keepdim=True)).unsqueeze(0)
    sol = solve_reps_dual(R, lr, eps, D=D, kappa=kap, max_iter=max_iter)
    _warn_if_collapsed(sol, eps)
    return _block(sol, 0, sol.v)


# --------------------------------------------------------------------------------------------
# infinite-horizon HiREPS


def solve_infinite_horizon_dual(
    rewards: Tensor,
    features: Tensor,
    next_features: Tensor,
    initial_features: Tensor,
    *,
    gamma: float,
    epsilon: float,
    log_responsibilities: Tensor | None = None,
    kappa: float | None = None,
    max_iter: int = 300,
) -> DualSolution:
    """Solve the stationary (infinite-horizon) HiREPS dual with restart probability 1 - gamma.

    Samples are transitions (s_i, a_i, r_i, s'_i) of the restart process. The new
    distribution P_io ∝ p~_io^(1 + xi/eta) exp(delta_i / eta) uses the Bellman error

        delta_i = r_i + gamma v^T phi(s'_i) - v^T phi(s_i),

    and the dual is ``eta eps + xi kappa + (1 - gamma) v^T phi_hat_0 + eta log mean exp``.
    At the optimum the state distribution is stationary under restarts:

        sum_i w_i (phi(s_i) - gamma phi(s'_i)) = (1 - gamma) phi_hat_0   (``feature_error``).

    Args:
        rewards: (N,) reward of each transition (one decision).
        features: (N, F) value features phi(s_i).
        next_features: (N, F) value features phi(s'_i) of the state reached.
        initial_features: (F,) mean value features of the start distribution, phi_hat_0.
        gamma: 1 - restart probability, in (0, 1).
        epsilon: KL bound, > 0.
        log_responsibilities: (N, O) log p~(o | s_i, a_i) or None (one option).
        kappa: absolute bound on the option cross-entropy or None.
        max_iter: LBFGS iterations per phase.

    Returns:
        :class:`DualSolution`; ``v`` holds the value-function weights (F,).
    """
    R, eps, lr, kap = _common_inputs(rewards, epsilon, log_responsibilities, kappa, "rewards")
    N = R.shape[1]
    g = float(gamma)
    if not (math.isfinite(g) and 0.0 < g < 1.0):
        raise ValueError(f"gamma must be in (0, 1), got {gamma}")
    phi = _features("features", features, N)
    phi_next = _features("next_features", next_features, N)
    if phi_next.shape != phi.shape:
        raise ValueError(
            f"next_features must have the shape of features {tuple(phi.shape)}, got "
            f"{tuple(phi_next.shape)}"
        )
    phi0 = _feature_vector("initial_features", initial_features, phi.shape[1])
    D = (g * phi_next - phi).unsqueeze(0)
    c = (1.0 - g) * phi0
    sol = solve_reps_dual(R, lr, eps, D=D, c=c, kappa=kap, max_iter=max_iter)
    _warn_if_collapsed(sol, eps)
    return _block(sol, 0, sol.v)


# --------------------------------------------------------------------------------------------
# time-indexed HiREPS


def solve_time_indexed_dual(
    rewards: Tensor,
    features: Tensor,
    *,
    epsilon: float | Tensor,
    log_responsibilities: Tensor | None = None,
    kappa: float | Tensor | None = None,
    initial_features: Tensor | None = None,
    max_iter: int = 300,
) -> TimeIndexedDualSolution:
    """Solve the time-indexed HiREPS dual: one distribution per decision step k = 1..K.

    Sample i is an episode of K decisions: states s_k,i, parameters theta_k,i, rewards R_k,i.
    Step k's distribution P_k,io ∝ p~_k,io^(1 + xi_k/eta_k) exp(delta_k,i / eta_k) uses the
    Bellman error with per-step value functions V_k(s) = v_k^T phi(s),

        delta_k,i = R_k,i + v_{k+1}^T phi(s_{k+1,i}) - v_k^T phi(s_k,i),    V_{K+1} = 0,

    and (eta, xi, v) minimise

        g = v_1^T phi_hat_1 + sum_k [eta_k eps_k + xi_k kappa_k
                                     + eta_k log((1/N) sum_io exp(A_k,io / eta_k))],
        A_k,io = delta_k,i + (eta_k + xi_k) log p~_k,io.

    At the optimum KL_k = eps_k, E_P_k[-log p~_k] <= kappa_k and the state distributions are
    chained (``feature_error`` is the largest violation):

        sum_i w_1i phi(s_1i) = phi_hat_1,
        sum_i w_ki phi(s_ki) = sum_i w_{k-1,i} phi(s_ki)   (k >= 2; s_ki follows s_{k-1,i}).

    This is :func:`solve_reps_dual` with the stacked v = [v_1 .. v_K], c = [phi_hat_1, 0, ..]
    and D_k mapping v to v_{k+1}^T phi(s_{k+1}) - v_k^T phi(s_k). The term v_1^T phi_hat_1 is
    folded into step 1's log-sum-exp (D_1 = -(phi(s_1) - phi_hat_1) in slot 1, c = 0), as in the
    episodic dual: the same dual value, weights and residuals.

    Args:
        rewards: (N, K) reward of each episode at each decision step, N >= 2, K >= 1.
        features: (N, K, F) value features phi(s_k,i) of the state where step k's decision
            was taken.
        epsilon: KL bound per step, > 0: one float or (K,). Values >= log N let that step's
            weights collapse onto one sample (a :class:`DegenerateWeightsWarning` is issued).
        log_responsibilities: (N, K, O) log p~_k(o | s_k,i, theta_k,i) of each step's old
            policy, normalised over options (-inf for options a step does not have); None
            means one option per step.
        kappa: absolute bound on each step's option cross-entropy, >= 0: one float or (K,);
            inf leaves that step unbounded; None means no bound (xi = 0).
        initial_features: (F,) mean features of the start distribution, phi_hat_1; by default
            the sample mean of ``features[:, 0]`` (then uniform weights are feasible).
        max_iter: LBFGS iterations per phase.

    Returns:
        :class:`TimeIndexedDualSolution`; ``weights`` (K, N, O), each step summing to 1.

    Raises:
        ValueError: on non-finite rewards or features, shape mismatches, N < 2, K < 1,
            epsilon <= 0 or a negative kappa; each message names the offending value.
    """
    R, eps, lr, kap = _common_inputs(
        rewards, epsilon, log_responsibilities, kappa, "rewards", per_step=True
    )
    K, N = R.shape
    phi = _features("features", features, N, K).transpose(0, 1)  # (K, N, F)
    F = phi.shape[-1]
    phi1 = (
        phi[0].mean(dim=0)
        if initial_features is None
        else _feature_vector("initial_features", initial_features, F)
    )
    # D[k, i] holds -phi(s_k,i) in slot k and phi(s_{k+1},i) in slot k + 1.
    D = torch.zeros(K, N, K, F, dtype=torch.float64)
    steps = torch.arange(K)
    D[steps, :, steps] = -phi
    D[steps[:-1], :, steps[1:]] = phi[1:]
    D[0, :, 0] += phi1
    sol = solve_reps_dual(R, lr, eps, D=D.reshape(K, N, K * F), kappa=kap, max_iter=max_iter)
    _warn_if_collapsed(sol, eps)
    return TimeIndexedDualSolution(
        eta=sol.eta,
        xi=sol.xi,
        v=sol.v.reshape(K, F),
        weights=sol.weights,
        sample_weights=sol.weights.sum(-1),
        kl=sol.kl,
        cross_entropy=sol.cross_entropy,
        effective_sample_size=sol.effective_sample_size,
        feature_error=sol.feature_error,
        dual_value=sol.dual_value,
        converged=sol.converged,
        iterations=sol.iterations,
    )
