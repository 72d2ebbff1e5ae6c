"""Gating networks: pi(o | s) over O options."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from hireps_torch._linalg import log_softmax, matmul_each, reduce_each, softmax
from hireps_torch._parallel import member_chunks, side_by_side
from hireps_torch.checks import (
    as_checked,
    as_float_tensor,
    as_weights,
    check_count,
    check_finite,
    check_float_dtype,
    check_nonnegative_float,
)
from hireps_torch.policies._module import PolicyModule

__all__ = ["ConstantGating", "Gating", "SoftmaxGating"]


class Gating(PolicyModule):
    """Base of the gatings: ``features (N, F) -> log pi(o | s) (N, O)`` over the active options.

    Pruned options are masked by the ``active`` bool buffer, never removed. Subclasses
    implement :meth:`log_probs` and :meth:`fit_checked`.
    """

    active: Tensor
    _stacked: tuple[str, ...] = ("active",)
    _shared: tuple[str, ...] = ("in_features", "n_options")

    def __init__(self, in_features: int, n_options: int) -> None:
        super().__init__()
        self.n_options = check_count("n_options", n_options, 1)
        self.in_features = check_count("in_features", in_features, 0)
        self.register_buffer("active", torch.ones(self.n_options, dtype=torch.bool))

    def _features(self, features: Tensor) -> Tensor:
        shape = (*self.batch_shape, None, self.in_features)
        return as_checked("gating features", features, shape, device=self.active.device)

    def log_probs(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> log pi(o | s): ([S,] N, O), -inf for pruned options."""
        raise NotImplementedError

    def probs(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> pi(o | s): ([S,] N, O)."""
        return self.log_probs(features).exp()

    @torch.no_grad()
    def fit_parameters(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """The new parameters (name -> tensor) of :meth:`weighted_fit`, not set
        (:meth:`fit_checked` of the checked inputs).

        Args:
            features: ([S,] N, F).
            targets: ([S,] N, O) distributions over the active options where sample_weights > 0.
            sample_weights: ([S,] N) non-negative, not all zero (for each member).
        """
        x = self._features(features)
        lead = tuple(x.shape[:-1])
        t = as_checked("targets", targets, (*lead, self.n_options))
        negative = t < 0
        if bool(negative.any()):
            at = [int(j) for j in negative.nonzero()[0]]
            raise ValueError(
                f"targets must be finite and non-negative, got {t[tuple(at)].item()} at {at}"
            )
        w = as_weights("sample_weights", sample_weights, lead, self.population is not None)
        sums = torch.where(self.active.unsqueeze(-2), t, 0.0).sum(-1)
        off = (w > 0) & ((sums - 1.0).abs() > 1e-6)  # rows must sum to 1 on the active options
        if bool(off.any()):
            at = [int(j) for j in off.nonzero()[0]]
            row = at[-1] if self.population is None else tuple(at)
            mask = self.active if self.population is None else self.active[at[0]]
            pruned = [int(o) for o in (~mask).nonzero().flatten()]
            raise ValueError(
                f"targets must be distributions over the active options (rows summing to 1) "
                f"where sample_weights > 0: row {row} sums to {sums[tuple(at)].item():.6g} on "
                f"the active options" + (f" (pruned: {pruned})" if pruned else "")
            )
        w = w / reduce_each(w, "sum", -1, True)
        return self.fit_checked(x.to(torch.float64), t, w, check_count("max_iter", max_iter, 1))

    def fit_checked(
        self, x: Tensor, t: Tensor, w: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """:meth:`fit_parameters` on checked float64 x ([S,] N, F), t ([S,] N, O), w ([S,] N)
        (w summing to 1)."""
        raise NotImplementedError

    @torch.no_grad()
    def weighted_fit(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> None:
        """Fit to soft targets (N, O) with sample weights (N,); a failed fit changes nothing."""
        self.set_parameters(self.fit_parameters(features, targets, sample_weights, max_iter))

    def check_state(self, state: Mapping[str, Tensor]) -> None:
        """A loaded ``active`` mask must keep at least one option."""
        active = state.get("active")
        if active is not None and not bool(active.any(-1).all()):
            raise ValueError("active: a state with every option pruned cannot be loaded")


class SoftmaxGating(Gating):
    """Softmax gating ``pi(o | s) = softmax_o(weight @ phi(s) + bias)`` over the active options.

    Shapes: ``features: (N, F)`` -> ``(N, O)``; pruned options have probability exactly 0.

    Args:
        in_features: F (0 gives a context-free prior over options).
        n_options: O.
        l2: L2 penalty on the weights in :meth:`weighted_fit`.
        dtype: parameter dtype.
    """

    def __init__(
        self, in_features: int, n_options: int, l2: float = 1e-4, dtype: torch.dtype = torch.float64
    ) -> None:
        super().__init__(in_features, n_options)
        self.l2 = check_nonnegative_float("l2", l2)
        check_float_dtype(dtype)
        n_options, in_features = self.n_options, self.in_features
        self.weight = nn.Parameter(torch.zeros(n_options, in_features, dtype=dtype), False)
        self.bias = nn.Parameter(torch.zeros(n_options, dtype=dtype), False)

    _stacked = ("active", "weight", "bias")
    _shared = ("in_features", "n_options", "l2")

    def _features(self, features: Tensor) -> Tensor:
        return super()._features(features).to(self.bias.dtype)

    def log_probs(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> log pi(o | s): ([S,] N, O), -inf for pruned options."""
        x = self._features(features)
        logits = matmul_each(x, self.weight.mT) + self.bias.unsqueeze(-2)
        logits = logits.masked_fill(~self.active.unsqueeze(-2), float("-inf"))
        return log_softmax(logits)

    def fit_checked(
        self, x: Tensor, t: Tensor, w: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """Weighted multinomial logistic regression onto soft targets (:meth:`Gating.fit_checked`).

        Minimises ``sum_i w_i sum_o t_io (-log pi(o | s_i)) / sum_i w_i + l2/2 ||weight||^2``
        over the active options by Newton steps (:func:`_newton_fit`); an option without target
        mass gets :data:`DEAD_LOGIT`; F = 0: ``pi(o) = sum_i w_i t_io / sum_i w_i``. Returns
        ``{"weight": ([S,] O, F), "bias": ([S,] O)}`` (pruned options' rows kept).
        """
        act = self.active
        if self.in_features == 0:
            prior = torch.where(
                act, reduce_each(w[..., None] * t, "sum", -2).clamp_min(1e-300), 0.0
            )
            logp = torch.log(prior / prior.sum(-1, keepdim=True))
            centred = logp - _active_mean(torch.where(act, logp, 0.0), act)
            return {"bias": torch.where(act, centred.to(self.bias.dtype), self.bias)}
        # no target mass: minimiser at logit -inf, so left out and set to DEAD_LOGIT
        dead = act & (reduce_each(w[..., None] * t, "sum", -2) <= 0)
        fit = act & ~dead
        W0, b0 = self.weight.to(torch.float64), self.bias.to(torch.float64)
        if self.population is None:
            Wp, bp, failed = _newton_fit(x, t, w, W0, b0, fit, self.l2, max_iter)
        else:  # chunks of members side by side (each member's fit is its own)

            def chunk(m: slice) -> tuple[Tensor, Tensor, Tensor]:
                return _newton_fit(x[m], t[m], w[m], W0[m], b0[m], fit[m], self.l2, max_iter)

            size = t[0].numel() * (x.shape[-1] + 1)  # one member's (N, O, F + 1) products
            chunks = member_chunks(self.population, x.device, size)
            parts = side_by_side(chunk, chunks, x.device, size)
            Wp, bp, failed = (torch.cat(p) for p in zip(*parts, strict=True))
        bad = failed | ~(torch.isfinite(Wp).flatten(-2).all(-1) & torch.isfinite(bp).all(-1))
        if bool(bad.any()):
            who = "" if self.population is None else f"member {int(bad.nonzero()[0, 0])}: "
            raise ValueError(
                f"{who}the gating fit is not finite (gating features up to "
                f"{float(x.abs().max()):.3g}): rescale the gating features"
            )
        centred = bp - _active_mean(torch.where(fit, bp, 0.0), fit)
        centred = torch.where(dead, DEAD_LOGIT, centred)
        Wp = torch.where(dead[..., None], 0.0, Wp)
        return {
            "weight": torch.where(act[..., None], Wp.to(self.weight.dtype), self.weight),
            "bias": torch.where(act, centred.to(self.bias.dtype), self.bias),
        }


DEAD_LOGIT = -1000.0
"""The bias the gating fit gives an option without target mass (probability 0 in float64)."""

NEWTON_GTOL = 1e-12
"""The gating fit's Newton steps stop when the largest gradient entry is below this."""


def _cross_entropy(
    x: Tensor, t: Tensor, w: Tensor, W: Tensor, b: Tensor, active: Tensor, l2: float
) -> Tensor:
    """The gating fit's loss ([S]) over the active options (see :meth:`fit_parameters`)."""
    keep = active.unsqueeze(-2)
    logits = (x @ W.mT + b.unsqueeze(-2)).masked_fill(~keep, float("-inf"))
    logp = log_softmax(logits)
    fit = reduce_each(torch.where(keep, w[..., None] * t * logp, 0.0), "sum", (-2, -1))
    return -fit + 0.5 * l2 * torch.where(active[..., None], W**2, 0.0).sum((-2, -1))


def _newton_fit(
    x: Tensor,
    t: Tensor,
    w: Tensor,
    W: Tensor,
    b: Tensor,
    active: Tensor,
    l2: float,
    max_iter: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Damped Newton steps on :func:`_cross_entropy` from W (..., O, F), b (..., O) until the
    gradient is below :data:`NEWTON_GTOL`; pruned options fixed. Returns W, b, failed ([S])."""
    X = torch.cat([x.new_ones(*x.shape[:-1], 1, dtype=torch.float64), x], -1)  # (.., N, F+1)
    theta = torch.cat([b[..., None], W], -1)  # (..., O, F+1)
    O, F1 = theta.shape[-2:]
    pen = x.new_full((F1,), l2, dtype=torch.float64)
    pen[0] = 0.0  # no penalty on the biases (the softmax's shift is fixed by the damping)
    keep = active[..., None].expand_as(theta).flatten(-2)  # (..., P)
    XX, entry = _feature_pairs(X), _entries(O, F1, x.device)

    def loss_of(th: Tensor) -> Tensor:
        return _cross_entropy(x, t, w, th[..., 1:], th[..., 0], active, l2)

    loss = loss_of(theta)
    running = x.new_ones(theta.shape[:-2], dtype=torch.bool)
    failed = ~torch.isfinite(loss)
    for _ in range(max_iter):
        logits = (X @ theta.mT).masked_fill(~active.unsqueeze(-2), float("-inf"))
        p = softmax(logits)  # (..., N, O)
        g = matmul_each((w[..., None] * (p - t)).mT, X) + pen * theta  # (..., O, F+1)
        g = torch.where(active[..., None], g, 0.0).flatten(-2)
        running &= g.abs().amax(-1) > NEWTON_GTOL
        if not bool(running.any()):
            break
        H = _hessian(XX, w, p, entry)
        H = H + torch.diag_embed(pen.repeat(O)).view(O, F1, O, F1)
        H = H.reshape(*H.shape[:-4], O * F1, O * F1)
        H = torch.where(keep[..., :, None] & keep[..., None, :], H, 0.0)
        H = H + torch.diag_embed((~keep).to(torch.float64))
        damping = 1e-10 * torch.diagonal(H, dim1=-2, dim2=-1).mean(-1)
        H = H + damping[..., None, None] * torch.eye(O * F1, dtype=torch.float64, device=x.device)
        step, info = torch.linalg.solve_ex(H, g)
        solved = (info == 0) & torch.isfinite(step).all(-1) & torch.isfinite(g).all(-1)
        failed |= running & ~solved
        running &= solved
        step = torch.where(running[..., None], step, 0.0).view(theta.shape)
        moved = torch.zeros_like(running)
        for _halving in range(30):
            trial = theta - step
            new_loss = loss_of(trial)
            ok = running & ~moved & (new_loss <= loss + 1e-13 * (1.0 + loss.abs()))
            theta = torch.where(ok[..., None, None], trial, theta)
            loss = torch.where(ok, new_loss, loss)
            moved |= ok
            if bool((moved | ~running).all()):
                break
            step = 0.5 * step
        running &= moved
    return theta[..., 1:].contiguous(), theta[..., 0].contiguous(), failed


def _feature_pairs(X: Tensor) -> Tensor:
    """(..., N, F1 (F1 + 1) / 2) products x_ij x_ik of X (..., N, F1) for j <= k (row-major)."""
    F1 = X.shape[-1]
    return torch.cat([X[..., j : j + 1] * X[..., j:] for j in range(F1)], -1)


def _entries(O: int, F1: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """Index maps (O, 1, O, 1) and (1, F1, 1, F1) from the Hessian's entry (o, j, o', k) to its
    option pair (o <= o') and feature pair (j <= k), each in row-major upper-triangle order."""
    maps = []
    for n in (O, F1):
        iu = torch.triu_indices(n, n, device=device)
        m = torch.zeros(n, n, dtype=torch.long, device=device)
        m[iu[0], iu[1]] = m[iu[1], iu[0]] = torch.arange(iu.shape[1], device=device)
        maps.append(m)
    return maps[0][:, None, :, None], maps[1][None, :, None, :]


def _hessian(XX: Tensor, w: Tensor, p: Tensor, entry: tuple[Tensor, Tensor]) -> Tensor:
    """(..., O, F1, O, F1) Hessian of the weighted cross-entropy in theta = [b, W] (penalty left
    out): sum_i w_i (diag(p_i) - p_i p_i^T) (x) x_i x_i^T, each entry computed once per unordered
    option pair and feature pair. XX: :func:`_feature_pairs` of X; w (..., N); p (..., N, O)."""
    O = p.shape[-1]
    wp = w[..., None] * p
    c = []  # w_i p_io (delta_oo' - p_io') for o <= o'
    for o in range(O):
        q = -p[..., o:]
        q[..., 0] += 1.0
        c.append(wp[..., o : o + 1] * q)
    return matmul_each(torch.cat(c, -1).mT, XX)[(..., *entry)]


class ConstantGating(Gating):
    """Fixed hard gating (the paper's Fig. 17 baseline): ``pi(o | s) = 1`` for the nearest
    centroid, 0 otherwise; never refitted.

    Args:
        centroids: (O, F) centroids in the gating-feature space.
    """

    centroids: Tensor

    def __init__(self, centroids: Tensor) -> None:
        c = as_float_tensor("centroids", centroids).clone()
        if c.dim() != 2 or c.shape[0] < 1:
            raise ValueError(f"centroids must have shape (O, F), got {tuple(c.shape)}")
        check_finite("centroids", c, "")
        super().__init__(c.shape[1], c.shape[0])
        self.register_buffer("centroids", c)

    _stacked = ("active", "centroids")

    @classmethod
    def from_kmeans(cls, points: Tensor, n_options: int, seed: int = 0) -> ConstantGating:
        """k-means (scipy's ``kmeans2``, k-means++ start) of points (M, F) into O centroids."""
        from scipy.cluster.vq import kmeans2

        n_options = check_count("n_options", n_options, 1)
        x = as_float_tensor("points", points)
        if x.dim() != 2 or x.shape[0] < n_options:
            raise ValueError(
                f"need points of shape (M, F) with M >= n_options = {n_options}, got "
                f"{tuple(x.shape)}"
            )
        check_finite("points", x, "")
        centroids, _ = kmeans2(
            x.cpu().numpy(), n_options, minit="++", seed=check_count("seed", seed, 0)
        )
        return cls(torch.from_numpy(centroids))

    def log_probs(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> ([S,] N, O): 0 at the nearest centroid, -inf elsewhere."""
        x = self._features(features)
        nearest = torch.cdist(x, self.centroids.to(x.dtype)).argmin(dim=-1)
        out = x.new_full((*x.shape[:-1], self.n_options), float("-inf"))
        return out.scatter_(-1, nearest[..., None], 0.0)

    def fit_checked(
        self, x: Tensor, t: Tensor, w: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """Nothing to fit (:meth:`fit_parameters` checks the inputs)."""
        return {}


def _active_mean(values: Tensor, active: Tensor) -> Tensor:
    """Mean of ``values`` (S, O) over the active options: (S, 1)."""
    return values.sum(-1, keepdim=True) / active.sum(-1, keepdim=True)
