"""Gating networks: pi(o | s) over O options."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

from hireps_torch._linalg import log_softmax, softmax
from hireps_torch._parallel import member_chunks, side_by_side
from hireps_torch.checks import (
    as_float,
    as_float_tensor,
    check_count,
    check_finite,
    check_float_dtype,
    check_weights,
)
from hireps_torch.policies._module import PolicyModule
from hireps_torch.policies._population import batch_text, check_members

__all__ = ["ConstantGating", "Gating", "SoftmaxGating"]


class Gating(PolicyModule):
    """Base of the gatings: ``features (N, F) -> log pi(o | s) (N, O)`` over the active options.

    Holds ``in_features``, ``n_options`` and the ``active`` bool buffer (pruned options are
    masked, never removed, so ``state_dict`` shapes never change). Subclasses implement
    :meth:`log_probs` and :meth:`fit_parameters` (the new parameter values of a weighted fit,
    computed without changing the gating; :meth:`weighted_fit` then sets them).
    """

    active: Tensor
    population: int | None = None
    """S for a population of S gatings stacked by :meth:`stack`; None for one gating."""

    def __init__(self, in_features: int, n_options: int) -> None:
        super().__init__()
        self.n_options = check_count("n_options", n_options, 1)
        self.in_features = check_count("in_features", in_features, 0)
        self.register_buffer("active", torch.ones(self.n_options, dtype=torch.bool))

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """() for one gating, (S,) for a population."""
        return () if self.population is None else (self.population,)

    _stacked: tuple[str, ...] = ("active",)
    """The parameters and buffers that a population stacks along its leading S."""

    @classmethod
    def stack(cls, members: Sequence[Gating]) -> Gating:
        """A population of S gatings of the same kind (the members' parameters and ``active``
        masks stacked along a leading S; inputs and outputs then carry it too: features
        (S, N, F) -> (S, N, O)). The members must share the kind, ``in_features``,
        ``n_options`` and their settings; they are copied, not shared."""
        items: list[Gating] = check_members("members", members, Gating)
        first = items[0]
        for s, m in enumerate(items[1:], 1):
            if type(m) is not type(first):
                raise TypeError(
                    f"members[{s}] is a {type(m).__name__} but members[0] a "
                    f"{type(first).__name__}: a population holds one kind"
                )
            for what in ("in_features", "n_options", *first._settings()):
                if getattr(m, what) != getattr(first, what):
                    raise ValueError(
                        f"members[{s}].{what} = {getattr(m, what)} but members[0].{what} = "
                        f"{getattr(first, what)}: a population shares it"
                    )
        out = copy.deepcopy(first)
        out.population = len(items)
        with torch.no_grad():
            for name in first._stacked:
                value = torch.stack([getattr(m, name) for m in items])
                _replace(out, name, value)
        return out

    def member(self, s: int) -> Gating:
        """Member ``s`` of a population as an ordinary gating (a copy)."""
        if self.population is None:
            raise ValueError("member() takes a member of a population; this is one gating")
        index = check_count("s", s, 0)
        if index >= self.population:
            raise ValueError(f"member s must be in [0, {self.population}), got {index}")
        out = copy.deepcopy(self)
        out.population = None
        with torch.no_grad():
            for name in self._stacked:
                _replace(out, name, getattr(self, name)[index].clone())
        return out

    def _settings(self) -> tuple[str, ...]:
        """Attributes the members of a population must share."""
        return ()

    def _features(self, features: Tensor) -> Tensor:
        x = as_float_tensor("gating features", features, device=self.active.device)
        lead = self.batch_shape
        if x.dim() != 2 + len(lead) or x.shape[:-2] != lead or x.shape[-1] != self.in_features:
            raise ValueError(
                f"gating features must have shape ({batch_text(self.population)}N, "
                f"{self.in_features}), got {tuple(x.shape)}"
            )
        check_finite("gating features", x, "")
        return x

    def _fit_inputs(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Checked float64 features ([S,] N, F), targets ([S,] N, O) and weights ([S,] N)
        normalised to sum 1 (for each member)."""
        x = self._features(features)
        N = x.shape[-2]
        lead = self.batch_shape
        t = as_float_tensor("targets", targets)
        if t.shape != (*lead, N, self.n_options):
            raise ValueError(
                f"targets must have shape {(*lead, N, self.n_options)}, got {tuple(t.shape)}"
            )
        bad = ~torch.isfinite(t) | (t < 0)
        if bool(bad.any()):
            at = [int(j) for j in bad.nonzero()[0]]
            raise ValueError(
                f"targets must be finite and non-negative, got {t[tuple(at)].item()} at {at}"
            )
        w = as_float_tensor("sample_weights", sample_weights)
        if w.shape != (*lead, N):
            raise ValueError(f"sample_weights must have shape {(*lead, N)}, got {tuple(w.shape)}")
        check_weights("sample_weights", w)
        empty = ~(w > 0).any(-1)
        if bool(empty.any()):
            s = int(empty.nonzero()[0, 0])
            raise ValueError(f"sample_weights[{s}] are all zero (member {s} of the population)")
        self._check_target_rows(t, w)
        return x, t, w / w.sum(-1, keepdim=True)

    def _check_target_rows(self, t: Tensor, w: Tensor) -> None:
        """Each row with a positive sample weight must be a distribution over the active
        options (sum 1 to 1e-6; nothing on pruned options): another row sum would act as a
        hidden sample weight."""
        active = self.active.unsqueeze(-2)
        sums = torch.where(active, t, 0.0).sum(-1)
        off = (w > 0) & ((sums - 1.0).abs() > 1e-6)
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

    def log_probs(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> log pi(o | s): ([S,] N, O), -inf for pruned options."""
        raise NotImplementedError

    def probs(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> pi(o | s): ([S,] N, O)."""
        return self.log_probs(features).exp()

    def fit_parameters(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """The new parameter values (name -> tensor) of a fit to soft targets (N, O) with
        sample weights (N,); the gating is unchanged."""
        raise NotImplementedError

    def fit_checked(
        self, x: Tensor, t: Tensor, w: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """:meth:`fit_parameters` on inputs already checked: float64 features x ([S,] N, F),
        targets t ([S,] N, O) and sample weights w ([S,] N) summing to 1."""
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
        if active is not None and not bool(active.any(-1).all()):
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

    _stacked = ("active", "weight", "bias")

    def _settings(self) -> tuple[str, ...]:
        return ("l2",)

    def _features(self, features: Tensor) -> Tensor:
        return super()._features(features).to(self.bias.dtype)

    def log_probs(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> log pi(o | s): ([S,] N, O), -inf for pruned options."""
        x = self._features(features)
        logits = x @ self.weight.mT + self.bias.unsqueeze(-2)
        logits = logits.masked_fill(~self.active.unsqueeze(-2), float("-inf"))
        return log_softmax(logits)

    @torch.no_grad()
    def fit_parameters(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """Weighted multinomial logistic regression onto soft targets (the gating unchanged).

        Minimises ``sum_i w_i sum_o t_io (-log pi(o | s_i)) / sum_i w_i + l2/2 ||weight||^2``
        over the active options by Newton's method from the current parameters, to its
        minimiser at round-off (:data:`NEWTON_GTOL`), each member of a population on its own
        in one batched call. An option without target mass gets probability 0
        (:data:`DEAD_LOGIT`). Without features (F = 0) this has the closed form
        ``pi(o) = sum_i w_i t_io / sum_i w_i``, which is used directly.

        Args:
            features: (N, F).
            targets: (N, O) rows are distributions over options (0 on pruned options; a row
                with positive sample weight that does not sum to 1 is refused).
            sample_weights: (N,) non-negative, not all zero.

        Returns:
            ``{"weight": (O, F), "bias": (O,)}``, the new values (pruned options' rows kept).
        """
        x, t, w = self._fit_inputs(features, targets, sample_weights)
        return self.fit_checked(x.to(torch.float64), t, w, check_count("max_iter", max_iter, 1))

    def fit_checked(
        self, x: Tensor, t: Tensor, w: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """:meth:`fit_parameters` on inputs already checked: float64 features x ([S,] N, F),
        targets t ([S,] N, O) and sample weights w ([S,] N) summing to 1."""
        act = self.active
        if self.in_features == 0:
            prior = torch.where(act, (w[..., None] * t).sum(-2).clamp_min(1e-300), 0.0)
            logp = torch.log(prior / prior.sum(-1, keepdim=True))
            centred = logp - _active_mean(torch.where(act, logp, 0.0), act)
            return {"bias": torch.where(act, centred.to(self.bias.dtype), self.bias)}
        # an option without any target mass has its minimiser at logit -inf: it is left out
        # of the fit and set to DEAD_LOGIT (probability 0, pruned next)
        dead = act & ((w[..., None] * t).sum(-2) <= 0)
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
"""The bias the gating fit gives an option without any target mass (its probability is then
0 in float64, and pruning removes it)."""

NEWTON_GTOL = 1e-12
"""The gating fit takes Newton steps until the largest gradient entry of the (weight-sum
normalised) cross-entropy is below this: it is then the minimiser to round-off, whatever the
start (LBFGS, which the fit used before, stopped on its change tolerance with gradients of
~1e-7, parameters ~1e-6 from it, and took ~100 loss evaluations where Newton takes ~10)."""


def _cross_entropy(
    x: Tensor, t: Tensor, w: Tensor, W: Tensor, b: Tensor, active: Tensor, l2: float
) -> Tensor:
    """The gating fit's loss ([S]): sum_i w_i sum_o t_io (-log pi(o | x_i)) + l2/2 ||W||^2
    over the active options."""
    keep = active.unsqueeze(-2)
    logits = (x @ W.mT + b.unsqueeze(-2)).masked_fill(~keep, float("-inf"))
    logp = log_softmax(logits)
    fit = torch.where(keep, w[..., None] * t * logp, 0.0).sum((-2, -1))
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
    """Newton steps (halved until the loss does not rise) on the gating's cross-entropy from
    (W (..., O, F), b (..., O)) until the gradient is below :data:`NEWTON_GTOL` (at most
    ``max_iter``), each member of a population on its own (a converged member stops).
    Pruned options are held fixed. The loss is convex, strictly so with ``l2 > 0``; a
    damping of 1e-10 of the Hessian's mean diagonal keeps the Newton system solvable
    without it. Returns W, b and the ([S]) members whose loss, gradient or Newton system was
    not finite (features too large)."""
    X = torch.cat([x.new_ones(*x.shape[:-1], 1, dtype=torch.float64), x], -1)  # (.., N, F+1)
    theta = torch.cat([b[..., None], W], -1)  # (..., O, F+1)
    O, F1 = theta.shape[-2:]
    pen = x.new_full((F1,), l2, dtype=torch.float64)
    pen[0] = 0.0  # no penalty on the biases (the softmax's shift is fixed by the damping)
    keep = active[..., None].expand_as(theta).flatten(-2)  # (..., P)

    def loss_of(th: Tensor) -> Tensor:
        return _cross_entropy(x, t, w, th[..., 1:], th[..., 0], active, l2)

    loss = loss_of(theta)
    running = x.new_ones(theta.shape[:-2], dtype=torch.bool)
    failed = ~torch.isfinite(loss)
    for _ in range(max_iter):
        logits = (X @ theta.mT).masked_fill(~active.unsqueeze(-2), float("-inf"))
        p = softmax(logits)  # (..., N, O)
        g = (w[..., None] * (p - t)).mT @ X + pen * theta  # (..., O, F+1)
        g = torch.where(active[..., None], g, 0.0).flatten(-2)
        running &= g.abs().amax(-1) > NEWTON_GTOL
        if not bool(running.any()):
            break
        # H = sum_i w_i (diag(p_i) - p_i p_i^T) (x) x_i x_i^T + l2 I, as products over samples
        A = ((w[..., None] * p)[..., None] * X[..., None, :]).flatten(-2)  # (..., N, O F1)
        B = (p[..., None] * X[..., None, :]).flatten(-2)
        blocks = (A.mT @ X).view(*A.shape[:-2], O, F1, F1)  # sum_i w_i p_io x_i x_i^T
        H = -(A.mT @ B).view(*A.shape[:-2], O, F1, O, F1)
        eye = torch.eye(O, dtype=torch.bool, device=x.device)
        H = H + torch.where(eye[:, None, :, None], blocks[..., :, :, None, :], 0.0)
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
        """features: ([S,] N, F) -> ([S,] N, O) with 0 at the nearest centroid and -inf
        elsewhere."""
        x = self._features(features)
        nearest = torch.cdist(x, self.centroids.to(x.dtype)).argmin(dim=-1)
        out = x.new_full((*x.shape[:-1], self.n_options), float("-inf"))
        return out.scatter_(-1, nearest[..., None], 0.0)

    def fit_parameters(
        self, features: Tensor, targets: Tensor, sample_weights: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """Constant gating: nothing to fit (the inputs are checked all the same)."""
        self._fit_inputs(features, targets, sample_weights)
        return {}

    def fit_checked(
        self, x: Tensor, t: Tensor, w: Tensor, max_iter: int = 100
    ) -> dict[str, Tensor]:
        """Constant gating: nothing to fit."""
        return {}


def _active_mean(values: Tensor, active: Tensor) -> Tensor:
    """Mean of ``values`` (S, O) over each member's active options (zeros elsewhere): (S, 1)."""
    return values.sum(-1, keepdim=True) / active.sum(-1, keepdim=True)


def _replace(module: nn.Module, name: str, value: Tensor) -> None:
    """Replace the parameter or buffer ``name`` of ``module`` by ``value`` (another shape)."""
    if name in module._parameters:
        setattr(module, name, nn.Parameter(value, requires_grad=False))
    else:
        module.register_buffer(name, value)
