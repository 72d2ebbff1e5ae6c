"""Hierarchical policy: a gating pi(o | s) over options pi(theta | s, o)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import torch
from torch import Tensor, nn

from hireps_torch.checks import as_finite_f64
from hireps_torch.features import FeatureMap, IdentityFeatures
from hireps_torch.policies.gating import Gating, SoftmaxGating
from hireps_torch.policies.linear_gaussian import LinearGaussian

__all__ = ["HierarchicalPolicy"]


class HierarchicalPolicy(nn.Module):
    """Mixture policy ``pi(theta | s) = sum_o pi(o | s) pi(theta | s, o)``.

    The gating sees ``gating_features(s)``, every option sees ``policy_features(s)``.
    Shapes: ``context: (N, S)`` (S may be 0), ``theta: (N, D)``, options ``(N,)`` int64.

    Args:
        gating: a gating module with ``log_probs(features) -> (N, O)``, ``weighted_fit`` and an
            ``active`` mask (e.g. :class:`SoftmaxGating`).
        options: O sub-policies (e.g. :class:`LinearGaussian`), all with the same action_dim.
        gating_features: feature map for the gating (identity by default).
        policy_features: feature map for the sub-policies (identity by default).
    """

    gating: Gating
    gating_features: FeatureMap
    policy_features: FeatureMap

    def __init__(
        self,
        gating: Gating,
        options: Sequence[LinearGaussian],
        gating_features: FeatureMap | None = None,
        policy_features: FeatureMap | None = None,
    ) -> None:
        super().__init__()
        if len(options) != gating.n_options:
            raise ValueError(
                f"gating has {gating.n_options} options but {len(options)} sub-policies were given"
            )
        dims = {o.action_dim for o in options}
        if len(dims) != 1:
            raise ValueError(f"all options must share action_dim, got {sorted(dims)}")
        self.gating = gating
        self.options = nn.ModuleList(options)
        self.gating_features = gating_features or IdentityFeatures(gating.in_features)
        self.policy_features = policy_features or IdentityFeatures(options[0].in_features)
        self.action_dim = dims.pop()

    @classmethod
    def create(
        cls,
        n_options: int,
        context_dim: int,
        action_dim: int,
        init_mean: Tensor | None = None,
        init_std: float | Tensor = 1.0,
        spread: float = 1.0,
        gating_features: FeatureMap | None = None,
        policy_features: FeatureMap | None = None,
        min_variance: float | Tensor = 1e-8,
        generator: torch.Generator | None = None,
        gating: Gating | None = None,
        covariance_prior: float = 0.0,
    ) -> HierarchicalPolicy:
        """Build a mixture of linear-Gaussian options.

        Option means start at ``init_mean + spread * init_std * randn`` (exactly ``init_mean``
        for one option) when ``init_mean`` is (D,) or None (zeros), and exactly at the rows of
        ``init_mean`` when it is (O, D), one mean per option (no random spread); covariances
        at ``init_std^2 I``. The gating is ``gating`` when given (e.g. a
        :class:`ConstantGating` on ``gating_features``), else a uniform
        :class:`SoftmaxGating`. ``covariance_prior`` goes to every option (see
        :class:`LinearGaussian`).
        """
        gf = gating_features or IdentityFeatures(context_dim)
        pf = policy_features or IdentityFeatures(context_dim)
        mean = (
            torch.zeros(action_dim, dtype=torch.float64)
            if init_mean is None
            else (torch.as_tensor(init_mean, dtype=torch.float64))
        )
        if mean.shape not in ((action_dim,), (n_options, action_dim)):
            raise ValueError(
                f"init_mean must have shape (D,) = ({action_dim},) or (O, D) = "
                f"({n_options}, {action_dim}), got {tuple(mean.shape)}"
            )
        std = torch.as_tensor(init_std, dtype=torch.float64).expand(action_dim)
        opts = []
        for o in range(n_options):
            m = (
                mean[o]
                if mean.dim() == 2
                else mean
                if n_options == 1
                else mean
                + spread * std * torch.randn(action_dim, generator=generator, dtype=torch.float64)
            )
            opts.append(
                LinearGaussian(
                    pf.out_features,
                    action_dim,
                    m,
                    std,
                    min_variance,
                    covariance_prior=covariance_prior,
                )
            )
        if gating is None:
            gating = SoftmaxGating(gf.out_features, n_options)
        return cls(gating, opts, gf, pf)

    # ---- helpers ----------------------------------------------------------------------------
    @property
    def sub_policies(self) -> list[LinearGaussian]:
        """The options as a typed list (the same modules as ``self.options``)."""
        return cast(list[LinearGaussian], list(self.options))

    @property
    def n_options(self) -> int:
        return len(self.options)

    @property
    def active(self) -> Tensor:
        """(O,) bool mask of options that have not been pruned."""
        return self.gating.active

    def _features(self, context: Tensor) -> tuple[Tensor, Tensor]:
        if context.dim() != 2:
            raise ValueError(f"context must have shape (N, S), got {tuple(context.shape)}")
        as_finite_f64("context", context)
        return self.gating_features(context), self.policy_features(context)

    # ---- distribution -----------------------------------------------------------------------
    def gating_log_probs(self, context: Tensor) -> Tensor:
        """context: (N, S) -> log pi(o | s): (N, O)."""
        return self.gating.log_probs(self.gating_features(context))

    def log_joint(self, context: Tensor, theta: Tensor) -> Tensor:
        """context: (N, S), theta: (N, D) -> log pi(o | s) + log pi(theta | s, o): (N, O)."""
        gf, pf = self._features(context)
        log_gate = self.gating.log_probs(gf)
        comps = torch.stack([opt.log_prob(pf, theta) for opt in self.sub_policies], dim=-1)
        return torch.where(self.active, log_gate + comps, torch.full_like(comps, float("-inf")))

    def log_prob(self, context: Tensor, theta: Tensor) -> Tensor:
        """Marginal log density of theta: (N,)."""
        return torch.logsumexp(self.log_joint(context, theta), dim=-1)

    def log_responsibilities(self, context: Tensor, theta: Tensor) -> Tensor:
        """log p(o | s, theta): (N, O); -inf for pruned options."""
        return torch.log_softmax(self.log_joint(context, theta), dim=-1)

    def responsibilities(self, context: Tensor, theta: Tensor) -> Tensor:
        """p(o | s, theta): (N, O)."""
        return self.log_responsibilities(context, theta).exp()

    def sample(
        self, context: Tensor, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """Draw an option from the gating, then theta from that option.

        Returns:
            theta (N, D) and option (N,) int64.
        """
        gf, pf = self._features(context)
        probs = self.gating.probs(gf)
        option = torch.multinomial(probs, 1, generator=generator).squeeze(-1)
        N = context.shape[0]
        used = torch.bincount(option, minlength=self.n_options).tolist()
        theta = pf.new_empty((N, self.action_dim), dtype=self.sub_policies[0].bias.dtype)
        for o, opt in enumerate(self.sub_policies):
            if used[o]:
                rows = option == o
                theta[rows] = opt.sample(pf, generator)[rows]
            else:  # unchosen option: only advance the generator as its sample would have
                b = opt.bias
                torch.randn(
                    (N, self.action_dim), generator=generator, dtype=b.dtype, device=b.device
                )
        return theta, option

    def mean_action(self, context: Tensor) -> tuple[Tensor, Tensor]:
        """Noise-free policy: the mean of the most probable option.

        Returns:
            theta (N, D) and option (N,) int64.
        """
        gf, pf = self._features(context)
        option = self.gating.log_probs(gf).argmax(dim=-1)
        means = torch.stack([opt.mean(pf) for opt in self.sub_policies], dim=1)
        return means[torch.arange(context.shape[0]), option], option

    # ---- refit and pruning ------------------------------------------------------------------
    @torch.no_grad()
    def weighted_fit(self, context: Tensor, theta: Tensor, weights: Tensor) -> None:
        """Refit gating and options to the weighted samples.

        Args:
            context: (N, S).
            theta: (N, D).
            weights: (N, O) non-negative joint sample-option weights P_io (any scale).
                Option o is refitted with weights P[:, o]; the gating with targets
                P_io / sum_o P_io and sample weights sum_o P_io. Options without weight keep
                their parameters (they are left to pruning).
        """
        gf, pf = self._features(context)
        if weights.shape != (context.shape[0], self.n_options):
            raise ValueError(
                f"weights must have shape ({context.shape[0]}, {self.n_options}), got "
                f"{tuple(weights.shape)}"
            )
        w = weights.to(torch.float64)
        ws = w.sum(-1)
        targets = w / ws.clamp_min(1e-300)[:, None]
        self.gating.weighted_fit(gf, targets, ws)
        total = float(w.sum())
        for o, opt in enumerate(self.sub_policies):
            if bool(self.active[o]) and float(w[:, o].sum()) > 1e-12 * total:
                opt.weighted_fit(pf, theta, w[:, o])

    @torch.no_grad()
    def prune(self, context: Tensor, threshold: float = 1e-4) -> list[int]:
        """Deactivate options whose prior mass ``mean_i pi(o | s_i)`` is below ``threshold``.

        The most probable option is never pruned. Returns the indices pruned by this call.
        """
        prior = self.gating.probs(self.gating_features(context)).mean(0)
        drop = self.active & (prior < threshold)
        drop[int(prior.argmax())] = False
        if bool(drop.any()):
            self.gating.active &= ~drop
        return [int(i) for i in drop.nonzero().flatten()]

    def option_entropy(self, context: Tensor, theta: Tensor) -> Tensor:
        """Mean entropy of the responsibilities p(o | s, theta) over the samples (scalar)."""
        lr = self.log_responsibilities(context, theta)
        p = lr.exp()
        return -(torch.where(p > 0, p * lr, torch.zeros_like(p))).sum(-1).mean()
