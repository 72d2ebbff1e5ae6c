"""Gating networks: pi(o | s) over O options."""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import torch
from torch import Tensor, nn

__all__ = ["ConstantGating", "Gating", "SoftmaxGating"]


class Gating(nn.Module):
    """Base of the gatings: ``features (N, F) -> log pi(o | s) (N, O)`` over the active options.

    Holds ``in_features``, ``n_options`` and the ``active`` bool buffer (pruned options are
    masked, never removed, so ``state_dict`` shapes never change). Subclasses implement
    :meth:`log_probs` and :meth:`weighted_fit`.
    """

    active: Tensor

    def __init__(self, in_features: int, n_options: int) -> None:
        super().__init__()
        if n_options < 1:
            raise ValueError(f"n_options must be >= 1, got {n_options}")
        if in_features < 0:
            raise ValueError(f"in_features must be >= 0, got {in_features}")
        self.in_features = in_features
        self.n_options = n_options
        self.register_buffer("active", torch.ones(n_options, dtype=torch.bool))

    def _features(self, features: Tensor) -> Tensor:
        if features.dim() != 2 or features.shape[1] != self.in_features:
            raise ValueError(
                f"gating features must have shape (N, {self.in_features}), got "
                f"{tuple(features.shape)}"
            )
        return features.to(torch.float64)

    def log_probs(self, features: Tensor) -> Tensor:
        """features: (N, F) -> log pi(o | s): (N, O), -inf for pruned options."""
        raise NotImplementedError

    def probs(self, features: Tensor) -> Tensor:
        """features: (N, F) -> pi(o | s): (N, O)."""
        return self.log_probs(features).exp()

    def weighted_fit(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> None:
        """Fit to soft targets (N, O) with sample weights (N,)."""
        raise NotImplementedError


class SoftmaxGating(Gating):
    """Softmax gating ``pi(o | s) = softmax_o(weight @ phi(s) + bias)`` over the active options.

    Shapes: ``features: (N, F)`` -> ``(N, O)``. Pruned options are kept in the parameter
    tensors (so ``state_dict`` shapes never change) but masked by the ``active`` buffer; their
    probability is exactly 0.

    Args:
        in_features: F (0 gives a context-free prior over options).
        n_options: O.
        l2: L2 penalty on the weights in :meth:`weighted_fit` (keeps the logistic fit finite on
            separable data).
        dtype: parameter dtype.
    """

    def __init__(
        self, in_features: int, n_options: int, l2: float = 1e-4, dtype: torch.dtype = torch.float64
    ) -> None:
        super().__init__(in_features, n_options)
        self.l2 = float(l2)
        self.weight = nn.Parameter(torch.zeros(n_options, in_features, dtype=dtype), False)
        self.bias = nn.Parameter(torch.zeros(n_options, dtype=dtype), False)

    def _features(self, features: Tensor) -> Tensor:
        return super()._features(features).to(self.bias.dtype)

    def log_probs(self, features: Tensor) -> Tensor:
        """features: (N, F) -> log pi(o | s): (N, O), -inf for pruned options."""
        x = self._features(features)
        logits = x @ self.weight.T + self.bias
        logits = logits.masked_fill(~self.active, float("-inf"))
        return torch.log_softmax(logits, dim=-1)

    @torch.no_grad()
    def weighted_fit(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> None:
        """Weighted multinomial logistic regression onto soft targets.

        Minimises ``sum_i w_i sum_o t_io (-log pi(o | s_i)) / sum_i w_i + l2/2 ||weight||^2``
        over the active options. Without features (F = 0) this has the closed form
        ``pi(o) = sum_i w_i t_io / sum_i w_i``, which is used directly.

        Args:
            features: (N, F).
            targets: (N, O) rows are distributions over options (0 on pruned options).
            sample_weights: (N,) non-negative, not all zero.
        """
        x = self._features(features).to(torch.float64)
        N = x.shape[0]
        if targets.shape != (N, self.n_options):
            raise ValueError(
                f"targets must have shape ({N}, {self.n_options}), got {tuple(targets.shape)}"
            )
        w = sample_weights.to(torch.float64)
        if w.shape != (N,) or not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
            raise ValueError("sample_weights must be (N,), finite and non-negative")
        if float(w.sum()) <= 0:
            raise ValueError("sample_weights are all zero")
        w = w / w.sum()
        act = self.active
        t = targets.to(torch.float64)[:, act]
        if self.in_features == 0:
            prior = (w[:, None] * t).sum(0).clamp_min(1e-300)
            logp = torch.log(prior / prior.sum())
            self.bias[act] = (logp - logp.mean()).to(self.bias.dtype)
            return
        Wp = self.weight[act].to(torch.float64).clone().requires_grad_(True)
        bp = self.bias[act].to(torch.float64).clone().requires_grad_(True)
        opt = torch.optim.LBFGS(
            [Wp, bp],
            lr=1.0,
            max_iter=max_iter,
            tolerance_grad=1e-9,
            tolerance_change=1e-12,
            history_size=20,
            line_search_fn="strong_wolfe",
        )

        def closure() -> Tensor:
            opt.zero_grad()
            logp = torch.log_softmax(x @ Wp.T + bp, dim=-1)
            loss = -(w[:, None] * t * logp).sum() + 0.5 * self.l2 * (Wp**2).sum()
            torch.autograd.backward(loss)  # loss.backward(), typed
            return loss

        # LBFGS.step is unannotated in torch; it takes and returns the closure's loss
        step = cast(Callable[[Callable[[], Tensor]], Tensor], opt.step)
        with torch.enable_grad():
            step(closure)
        self.weight[act] = Wp.detach().to(self.weight.dtype)
        self.bias[act] = (bp.detach() - bp.detach().mean()).to(self.bias.dtype)


class ConstantGating(Gating):
    """Fixed hard gating: each state goes to the option of its nearest k-means centroid.

    The paper's constant-gating baseline (Fig. 17): the state space is divided by k-means and
    the division is never refitted (:meth:`weighted_fit` leaves it unchanged); only the
    options learn. ``pi(o | s) = 1`` for the nearest centroid, 0 (log = -inf) otherwise.

    Args:
        centroids: (O, F) centroids in the gating-feature space.
    """

    centroids: Tensor

    def __init__(self, centroids: Tensor) -> None:
        c = torch.as_tensor(centroids, dtype=torch.float64)
        if c.dim() != 2 or c.shape[0] < 1:
            raise ValueError(f"centroids must have shape (O, F), got {tuple(c.shape)}")
        super().__init__(c.shape[1], c.shape[0])
        self.register_buffer("centroids", c.clone())

    @classmethod
    def from_kmeans(cls, points: Tensor, n_options: int, seed: int = 0) -> ConstantGating:
        """k-means (scipy's ``kmeans2``, k-means++ start) of points (M, F) into O centroids."""
        from scipy.cluster.vq import kmeans2

        x = torch.as_tensor(points, dtype=torch.float64)
        if x.dim() != 2 or x.shape[0] < n_options:
            raise ValueError(
                f"need points of shape (M, F) with M >= n_options = {n_options}, got "
                f"{tuple(x.shape)}"
            )
        centroids, _ = kmeans2(x.numpy(), n_options, minit="++", seed=seed)
        return cls(torch.from_numpy(centroids))

    def log_probs(self, features: Tensor) -> Tensor:
        """features: (N, F) -> (N, O) with 0 at the nearest centroid and -inf elsewhere."""
        x = self._features(features)
        nearest = torch.cdist(x, self.centroids.to(x.dtype)).argmin(dim=-1)
        out = torch.full((x.shape[0], self.n_options), float("-inf"), dtype=x.dtype)
        out[torch.arange(x.shape[0]), nearest] = 0.0
        return out

    @torch.no_grad()
    def weighted_fit(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> None:
        """Constant gating: nothing to fit."""
