"""Gating networks: pi(o | s) over O options."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import cast

import torch
from torch import Tensor, nn

from hireps_torch.checks import (
    as_float,
    as_float_tensor,
    check_count,
    check_finite,
    check_float_dtype,
    check_weights,
)
from hireps_torch.policies._module import PolicyModule

__all__ = ["ConstantGating", "Gating", "SoftmaxGating"]


class Gating(PolicyModule):
    """Base of the gatings: ``features (N, F) -> log pi(o | s) (N, O)`` over the active options.

    Holds ``in_features``, ``n_options`` and the ``active`` bool buffer (pruned options are
    masked, never removed, so ``state_dict`` shapes never change). Subclasses implement
    :meth:`log_probs` and :meth:`fit_parameters` (the new parameter values of a weighted fit,
    computed without changing the gating; :meth:`weighted_fit` then sets them).
    """

    active: Tensor

    def __init__(self, in_features: int, n_options: int) -> None:
        super().__init__()
        self.n_options = check_count("n_options", n_options, 1)
        self.in_features = check_count("in_features", in_features, 0)
        self.register_buffer("active", torch.ones(self.n_options, dtype=torch.bool))

    def _features(self, features: Tensor) -> Tensor:
        x = as_float_tensor("gating features", features, device=self.active.device)
        if x.dim() != 2 or x.shape[1] != self.in_features:
            raise ValueError(
                f"gating features must have shape (N, {self.in_features}), got {tuple(x.shape)}"
            )
        check_finite("gating features", x, "")
        return x

    def _fit_inputs(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Checked float64 features (N, F), targets (N, O) and normalised weights (N,)."""
        x = self._features(features)
        N = x.shape[0]
        t = as_float_tensor("targets", targets)
        if t.shape != (N, self.n_options):
            raise ValueError(
                f"targets must have shape ({N}, {self.n_options}), got {tuple(t.shape)}"
            )
        bad = ~torch.isfinite(t) | (t < 0)
        if bool(bad.any()):
            i, o = (int(j) for j in bad.nonzero()[0])
            raise ValueError(
                f"targets must be finite and non-negative, got {t[i, o].item()} at [{i}, {o}]"
            )
        w = as_float_tensor("sample_weights", sample_weights)
        if w.shape != (N,):
            raise ValueError(f"sample_weights must have shape ({N},), got {tuple(w.shape)}")
        check_weights("sample_weights", w)
        self._check_target_rows(t, w)
        return x, t, w / w.sum()

    def _check_target_rows(self, t: Tensor, w: Tensor) -> None:
        """Each row with a positive sample weight must be a distribution over the active
        options (sum 1 to 1e-6; nothing on pruned options): another row sum would act as a
        hidden sample weight."""
        sums = t[:, self.active].sum(-1)
        off = (w > 0) & ((sums - 1.0).abs() > 1e-6)
        if bool(off.any()):
            i = int(off.nonzero()[0, 0])
            pruned = [int(o) for o in (~self.active).nonzero().flatten()]
            raise ValueError(
                f"targets must be distributions over the active options (rows summing to 1) "
                f"where sample_weights > 0: row {i} sums to {sums[i].item():.6g} on the active "
                f"options" + (f" (pruned: {pruned})" if pruned else "")
            )

    def log_probs(self, features: Tensor) -> Tensor:
        """features: (N, F) -> log pi(o | s): (N, O), -inf for pruned options."""
        raise NotImplementedError

    def probs(self, features: Tensor) -> Tensor:
        """features: (N, F) -> pi(o | s): (N, O)."""
        return self.log_probs(features).exp()

    def fit_parameters(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """The new parameter values (name -> tensor) of a fit to soft targets (N, O) with
        sample weights (N,); the gating is unchanged."""
        raise NotImplementedError

    @torch.no_grad()
    def weighted_fit(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> None:
        """Fit to soft targets (N, O) with sample weights (N,): everything is computed and
        checked before the first parameter changes (a failed fit changes nothing)."""
        self.set_parameters(self.fit_parameters(features, targets, sample_weights, max_iter))

    def check_state(self, state: Mapping[str, Tensor]) -> None:
        """A loaded ``active`` mask must keep at least one option."""
        active = state.get("active")
        if active is not None and not bool(active.any()):
            raise ValueError("active: a state with every option pruned cannot be loaded")


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
        self.l2 = as_float("l2", l2)
        if not (math.isfinite(self.l2) and self.l2 >= 0):
            raise ValueError(f"l2 must be finite and >= 0, got {l2}")
        check_float_dtype(dtype)
        n_options, in_features = self.n_options, self.in_features
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
    def fit_parameters(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """Weighted multinomial logistic regression onto soft targets (the gating unchanged).

        Minimises ``sum_i w_i sum_o t_io (-log pi(o | s_i)) / sum_i w_i + l2/2 ||weight||^2``
        over the active options. Without features (F = 0) this has the closed form
        ``pi(o) = sum_i w_i t_io / sum_i w_i``, which is used directly.

        Args:
            features: (N, F).
            targets: (N, O) rows are distributions over options (0 on pruned options; a row
                with positive sample weight that does not sum to 1 is refused).
            sample_weights: (N,) non-negative, not all zero.

        Returns:
            ``{"weight": (O, F), "bias": (O,)}``, the new values (pruned options' rows kept).
        """
        x, t_all, w = self._fit_inputs(features, targets, sample_weights)
        x = x.to(torch.float64)
        max_iter = check_count("max_iter", max_iter, 1)
        act = self.active
        t = t_all[:, act]
        weight, bias = self.weight.detach().clone(), self.bias.detach().clone()
        if self.in_features == 0:
            prior = (w[:, None] * t).sum(0).clamp_min(1e-300)
            logp = torch.log(prior / prior.sum())
            bias[act] = (logp - logp.mean()).to(self.bias.dtype)
            return {"bias": bias}
        Wp, bp = self._logistic_regression(x, t, w, max_iter)
        if not (bool(torch.isfinite(Wp).all()) and bool(torch.isfinite(bp).all())):
            raise ValueError(
                "the gating fit is not finite (gating features up to "
                f"{float(x.abs().max()):.3g}): rescale the gating features"
            )
        weight[act] = Wp.to(self.weight.dtype)
        bias[act] = (bp - bp.mean()).to(self.bias.dtype)
        return {"weight": weight, "bias": bias}

    def _logistic_regression(
        self, x: Tensor, t: Tensor, w: Tensor, max_iter: int
    ) -> tuple[Tensor, Tensor]:
        """LBFGS on the weighted cross-entropy from the current active parameters."""
        act = self.active
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
        return Wp.detach(), bp.detach()


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
        c = as_float_tensor("centroids", centroids).clone()
        if c.dim() != 2 or c.shape[0] < 1:
            raise ValueError(f"centroids must have shape (O, F), got {tuple(c.shape)}")
        check_finite("centroids", c, "")
        super().__init__(c.shape[1], c.shape[0])
        self.register_buffer("centroids", c)

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
        """features: (N, F) -> (N, O) with 0 at the nearest centroid and -inf elsewhere."""
        x = self._features(features)
        nearest = torch.cdist(x, self.centroids.to(x.dtype)).argmin(dim=-1)
        out = torch.full(
            (x.shape[0], self.n_options), float("-inf"), dtype=x.dtype, device=x.device
        )
        out[torch.arange(x.shape[0], device=x.device), nearest] = 0.0
        return out

    def fit_parameters(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """Constant gating: nothing to fit (the inputs are checked all the same)."""
        self._fit_inputs(features, targets, sample_weights)
        return {}
