"""Hierarchical policy: a gating pi(o | s) over options pi(theta | s, o)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import torch
from torch import Tensor, nn

from hireps_torch._linalg import log_softmax, logsumexp, reduce_each
from hireps_torch.checks import (
    FIX_SAMPLES,
    as_checked,
    as_float_tensor,
    as_weights,
    check_count,
    check_finite,
    check_generator,
    check_nonnegative_float,
    check_prune_threshold,
)
from hireps_torch.features import FeatureMap, IdentityFeatures, check_feature_map
from hireps_torch.policies._module import PolicyModule, _replace
from hireps_torch.policies._population import (
    Generators,
    categorical,
    check_population_generators,
    normal,
)
from hireps_torch.policies.gating import Gating, SoftmaxGating
from hireps_torch.policies.linear_gaussian import LinearGaussian, power_of_two_scaled

__all__ = ["HierarchicalPolicy"]

MAX_OPTIONS = 10_000
"""The most options :meth:`HierarchicalPolicy.create` builds (each one a module of its own)."""


class HierarchicalPolicy(PolicyModule):
    """Mixture policy ``pi(theta | s) = sum_o pi(o | s) pi(theta | s, o)``.

    The gating sees ``gating_features(s)``, every option ``policy_features(s)``. Shapes:
    ``context: (N, C)`` (C may be 0), ``theta: (N, D)``, options ``(N,)`` int64. A wrong
    shape, non-finite entry or other device raises a ``ValueError`` naming it.

    Args:
        gating: a :class:`Gating` over O options (e.g. :class:`SoftmaxGating`).
        options: O :class:`LinearGaussian` sub-policies, all with the same action_dim.
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
        options = list(options)
        for o, opt in enumerate(options):
            if not isinstance(opt, LinearGaussian):
                raise TypeError(f"options[{o}] must be a LinearGaussian, got {type(opt).__name__}")
        if not isinstance(gating, Gating):
            raise TypeError(
                f"gating must be a Gating (e.g. SoftmaxGating), got {type(gating).__name__}"
            )
        if gating.n_options != len(options):
            raise ValueError(
                f"gating has {gating.n_options} options but {len(options)} sub-policies were given"
            )
        for o, opt in enumerate(options):
            if opt.population != gating.population:
                held = [
                    "one policy" if S is None else f"a population of {S}"
                    for S in (opt.population, gating.population)
                ]
                raise ValueError(
                    f"options[{o}] holds {held[0]} but the gating {held[1]}: build the "
                    "members' policies, then HierarchicalPolicy.stack them"
                )
        dims = {o.action_dim for o in options}
        if len(dims) != 1:
            raise ValueError(f"all options must share action_dim, got {sorted(dims)}")
        gf = check_feature_map("gating_features", gating_features) or IdentityFeatures(
            gating.in_features
        )
        pf = check_feature_map("policy_features", policy_features) or IdentityFeatures(
            options[0].in_features
        )
        if gf.in_features != pf.in_features:
            raise ValueError(
                f"gating_features take contexts of dimension {gf.in_features} but policy_features "
                f"of dimension {pf.in_features}"
            )
        if gf.out_features != gating.in_features:
            raise ValueError(
                f"gating_features give {gf.out_features} features but the gating takes "
                f"{gating.in_features}"
            )
        widths = sorted({o.in_features for o in options})
        if widths != [pf.out_features]:
            raise ValueError(
                f"policy_features give {pf.out_features} features but the options take {widths}"
            )
        self.gating = gating
        self.options = nn.ModuleList(options)
        self.gating_features = gf
        self.policy_features = pf
        self.action_dim = dims.pop()
        self.population = gating.population

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
        mean_prior: float = 0.0,
    ) -> HierarchicalPolicy:
        """Build a mixture of linear-Gaussian options.

        Option means: the rows of an (O, D) ``init_mean``, else ``init_mean + spread * init_std
        * randn`` (exactly ``init_mean`` for one option); covariances ``init_std^2 I``. The
        gating: ``gating``, else a uniform :class:`SoftmaxGating`. The priors go to every option.
        """
        n_options = check_count("n_options", n_options, 1)
        if n_options > MAX_OPTIONS:
            raise ValueError(
                f"n_options must be at most {MAX_OPTIONS:,} (each option is a module of its own), "
                f"got {n_options:,}"
            )
        context_dim = check_count("context_dim", context_dim, 0)
        action_dim = check_count("action_dim", action_dim, 1)
        check_generator("generator", generator)
        gf = check_feature_map("gating_features", gating_features) or IdentityFeatures(context_dim)
        pf = check_feature_map("policy_features", policy_features) or IdentityFeatures(context_dim)
        for name, fmap in (("gating_features", gf), ("policy_features", pf)):
            if fmap.in_features != context_dim:
                raise ValueError(
                    f"{name} take contexts of dimension {fmap.in_features}, not context_dim = "
                    f"{context_dim}"
                )
        mean = (
            torch.zeros(action_dim, dtype=torch.float64)
            if init_mean is None
            else as_float_tensor("init_mean", init_mean)  # its values: checked by LinearGaussian
        )
        if mean.shape not in ((action_dim,), (n_options, action_dim)):
            raise ValueError(
                f"init_mean must have shape (D,) = ({action_dim},) or (O, D) = "
                f"({n_options}, {action_dim}), got {tuple(mean.shape)}"
            )
        spread = check_nonnegative_float("spread", spread)
        rows = mean if mean.dim() == 2 else mean.expand(n_options, action_dim)
        opts = [  # every argument is checked (by LinearGaussian, then cls) before the draws
            LinearGaussian(
                pf.out_features,
                action_dim,
                m,
                init_std,
                min_variance,
                covariance_prior=covariance_prior,
                mean_prior=mean_prior,
            )
            for m in rows
        ]
        if gating is None:
            gating = SoftmaxGating(gf.out_features, n_options)
        policy = cls(gating, opts, gf, pf)
        if mean.dim() == 1 and n_options > 1:  # spread the one mean (chol's diagonal: init_std)
            for opt in opts:
                noise = torch.randn(action_dim, generator=generator, dtype=torch.float64)
                opt.bias.add_(spread * opt.chol.diagonal() * noise)
            means = torch.stack([opt.bias for opt in opts])
            check_finite("init_mean + spread * init_std * randn", means, "lower spread or init_std")
        return policy

    def _check_alike(self, s: int, m: Any) -> None:
        """:meth:`stack` needs one option count and the same feature maps in every member (the
        gatings and options are checked on their own: one kind, action_dim, ...)."""
        if m.n_options != self.n_options:
            raise ValueError(
                f"members[{s}] has {m.n_options} options but members[0] {self.n_options}"
            )
        for name in ("gating_features", "policy_features"):
            if not _same_map(getattr(m, name), getattr(self, name)):
                raise ValueError(
                    f"members[{s}].{name} differ from members[0]'s: a population shares "
                    "its feature maps"
                )

    # ---- helpers ----------------------------------------------------------------------------
    @property
    def sub_policies(self) -> list[LinearGaussian]:
        """The options as a typed list (the same modules as ``self.options``)."""
        return cast(list[LinearGaussian], list(self.options))

    @property
    def n_options(self) -> int:
        return len(self.options)

    @property
    def context_dim(self) -> int:
        """The width of the contexts."""
        return self.gating_features.in_features

    @property
    def active(self) -> Tensor:
        """([S,] O) bool mask of options that have not been pruned."""
        return self.gating.active

    def _context(self, context: Tensor) -> Tensor:
        """context checked, as float64 ([S,] N, C)."""
        lead, device = self.batch_shape, self.sub_policies[0].bias.device
        names = "(population, N, C) = " if lead else "(N, C) = "
        shape = (*lead, None, self.context_dim)
        c = as_checked("context", context, shape, device=device, names=names)
        if not bool(self.active.any(-1).all()):
            raise ValueError("every option of this policy is pruned (active is all False)")
        return c

    def _features(self, context: Tensor) -> tuple[Tensor, Tensor]:
        c = self._context(context)
        return self.gating_features(c), self.policy_features(c)

    # ---- distribution -----------------------------------------------------------------------
    def log_joint(self, context: Tensor, theta: Tensor) -> Tensor:
        """context: ([S,] N, C), theta: ([S,] N, D) -> log pi(o | s) + log pi(theta | s, o):
        ([S,] N, O)."""
        gf, pf = self._features(context)
        log_gate = self.gating.log_probs(gf)
        comps = torch.stack([opt.log_prob(pf, theta) for opt in self.sub_policies], dim=-1)
        active = self.active.unsqueeze(-2)
        return torch.where(active, log_gate + comps, torch.full_like(comps, float("-inf")))

    def log_prob(self, context: Tensor, theta: Tensor) -> Tensor:
        """Marginal log density of theta: ([S,] N)."""
        return logsumexp(self.log_joint(context, theta))

    def log_responsibilities(self, context: Tensor, theta: Tensor) -> Tensor:
        """log p(o | s, theta): ([S,] N, O); -inf for pruned options.

        Raises:
            ValueError: when a sample has zero density under every active option.
        """
        joint = self.log_joint(context, theta)
        impossible = torch.isneginf(joint).all(dim=-1)
        if bool(impossible.any()):
            at = tuple(int(j) for j in impossible.nonzero()[0])
            i = at[0] if len(at) == 1 else list(at)
            raise ValueError(
                f"theta[{i}] has zero density under every active option (|theta| up to "
                f"{float(torch.as_tensor(theta)[at].abs().max()):.3g}); its responsibilities are "
                "undefined: rescale or drop that sample"
            )
        return log_softmax(joint)

    def responsibilities(self, context: Tensor, theta: Tensor) -> Tensor:
        """p(o | s, theta): ([S,] N, O)."""
        return self.log_responsibilities(context, theta).exp()

    def sample(self, context: Tensor, generator: Generators = None) -> tuple[Tensor, Tensor]:
        """Draw an option from the gating, then theta from it (a population may take S generators).

        Returns:
            theta ([S,] N, D) and option ([S,] N) int64 (empty for N = 0).
        """
        gen = check_population_generators(self.population, generator)
        gf, pf = self._features(context)
        probs = self.gating.probs(gf)
        lead, N = pf.shape[:-2], pf.shape[-2]
        dtype = self.sub_policies[0].bias.dtype
        option = categorical(probs, gen)  # each member with its own generator, where given
        subs, D = self.sub_policies, self.action_dim
        # one standard normal per sample, whichever option is chosen (theta = mean_o + L_o noise)
        noise = normal((*lead, N, D), gen, dtype, pf.device)
        weight = torch.stack([o.weight for o in subs], -3)  # ([S,] O, D, F)
        bias = torch.stack([o.bias for o in subs], -2)  # ([S,] O, D)
        chol = torch.stack([o.chol for o in subs], -3)  # ([S,] O, D, D)
        x = pf.to(weight.dtype)
        mean = torch.einsum("...nf,...odf->...ond", x, weight) + bias[..., :, None, :]
        all_theta = mean + torch.einsum("...ode,...ne->...ond", chol, noise)
        index = option[..., None, :, None].expand(*option.shape[:-1], 1, N, D)
        theta = all_theta.gather(-3, index).squeeze(-3)
        return theta, option

    def mean_action(self, context: Tensor) -> tuple[Tensor, Tensor]:
        """Noise-free policy: the mean of the most probable option.

        Returns:
            theta ([S,] N, D) and option ([S,] N) int64.
        """
        gf, pf = self._features(context)
        option = self.gating.log_probs(gf).argmax(dim=-1)
        means = torch.stack([opt.mean(pf) for opt in self.sub_policies], dim=-2)
        index = option[..., None, None].expand(*option.shape, 1, self.action_dim)
        return means.gather(-2, index).squeeze(-2), option

    # ---- refit and pruning ------------------------------------------------------------------
    @torch.no_grad()
    def fit_parameters(self, context: Tensor, theta: Tensor, weights: Tensor) -> dict[str, Tensor]:
        """The new values (``state_dict`` names -> tensors) of :meth:`weighted_fit`, not set.

        Raises:
            ValueError: for bad inputs or a failed refit, naming the input or the option.
        """
        gf, pf = self._features(context)
        lead, members = tuple(pf.shape[:-1]), self.population is not None
        t = as_checked("theta", theta, (*lead, self.action_dim), advice=FIX_SAMPLES)
        w = as_weights("weights", weights, (*lead, self.n_options), members)
        on_pruned = ((w > 0) & ~self.active.unsqueeze(-2)).any(-2)
        if bool(on_pruned.any()):
            pruned = [list(map(int, j)) for j in on_pruned.nonzero()]
            where = [j[-1] for j in pruned] if self.population is None else pruned
            raise ValueError(
                f"weights put mass on pruned option(s) {where}; give them weight 0 (their "
                "column of the weights must be zero)"
            )
        return self.fit_checked(gf, pf, t, power_of_two_scaled(w, members))

    def fit_checked(self, gf: Tensor | None, pf: Tensor, t: Tensor, w: Tensor) -> dict[str, Tensor]:
        """:meth:`fit_parameters` on checked features gf, pf ([S,] N, .) (gf None: one option),
        float64 t ([S,] N, D) and w ([S,] N, O) (0 on pruned options, at most 2^200)."""
        new: dict[str, Tensor] = {}
        O = self.n_options
        if O > 1:  # one option: pi(o | s) = 1 whatever the gating holds
            assert gf is not None
            ws = w.sum(-1)
            targets = w / torch.where(ws > 0, ws, 1.0)[..., None]  # rows without weight stay 0
            norm = ws / reduce_each(ws, "sum", -1, True)
            x = gf.to(torch.float64)
            new = {f"gating.{k}": v for k, v in self.gating.fit_checked(x, targets, norm).items()}
            total = reduce_each(w, "sum", (-2, -1))
            fitted = self.active & (
                reduce_each(w, "sum", -2) > 1e-12 * total[..., None]
            )  # ([S,] O)
            flags = fitted.reshape(-1, O).T.tolist()  # per option, per member
        else:  # the one option is active (the most probable is never pruned) and has it all
            fitted, flags = self.active, [[True]]
        x = pf.to(torch.float64)
        # columns of one layout either way (a member's sums round as in its own run)
        filled = torch.where(fitted[..., None, :], w, 1.0)
        for o, opt in enumerate(self.sub_policies):
            if not any(flags[o]):  # no weight (or pruned) in every member: left to pruning
                continue
            every = all(flags[o])
            col = w[..., o] if every else filled[..., o]
            try:
                fit = opt.fit_checked(x, t, col)
            except ValueError as exc:
                raise ValueError(f"option {o}: {exc}") from None
            for k, v in fit.items():
                if not every:  # the members without weight on it keep their values
                    v = torch.where(fitted[:, o].view(-1, *[1] * (v.dim() - 1)), v, getattr(opt, k))
                new[f"options.{o}.{k}"] = v
        return new

    @torch.no_grad()
    def weighted_fit(self, context: Tensor, theta: Tensor, weights: Tensor) -> None:
        """Refit gating and options to the weighted samples; a failure changes nothing.

        Args:
            context: ([S,] N, C).
            theta: ([S,] N, D).
            weights: ([S,] N, O) joint weights P_io >= 0 (0 on pruned options): option o is
                fitted to P[..., o], the gating to targets P_io / sum_o P_io with sample
                weights sum_o P_io; options without weight are kept.
        """
        self.set_parameters(self.fit_parameters(context, theta, weights))

    @torch.no_grad()
    def prune(
        self, context: Tensor, threshold: float = 1e-4, members: Tensor | None = None
    ) -> list[int] | list[list[int]]:
        """Deactivate options whose mass ``mean_i pi(o | s_i)`` is below ``threshold`` (never the
        most probable; only where ``members`` ([S], bool) is True). Returns the pruned indices (per
        member for a population)."""
        limit = check_prune_threshold(threshold, "threshold")
        c = self._context(context)
        if members is not None and (
            not isinstance(members, Tensor)
            or members.dtype != torch.bool
            or members.shape != self.batch_shape
            or members.device != self.active.device
        ):
            got = (
                f"a {members.dtype} tensor of shape {tuple(members.shape)} on {members.device}"
                if isinstance(members, Tensor)
                else repr(members)
            )
            raise ValueError(
                f"members must be None or a bool tensor of shape {tuple(self.batch_shape)} "
                f"([S] for a population of S) on {self.active.device}; got {got}"
            )
        if c.shape[-2] == 0:
            raise ValueError("prune needs at least one context, got an empty (0, C) batch")
        prior = reduce_each(self.gating.probs(self.gating_features(c)), "mean", -2)
        drop = self.active & (prior < limit)
        drop.scatter_(-1, prior.argmax(-1, keepdim=True), False)
        if members is not None:
            drop &= members[..., None]
        if bool(drop.any()):
            if self.gating.active.is_inference():  # made under torch.inference_mode: no writes
                _replace(self.gating, "active", self.gating.active & ~drop)
            else:
                self.gating.active &= ~drop
        if self.population is None:
            return [int(i) for i in drop.nonzero().flatten()]
        return [[int(i) for i in row.nonzero().flatten()] for row in drop]

    def option_entropy(self, context: Tensor, theta: Tensor) -> Tensor:
        """Mean entropy of p(o | s, theta) over the samples: a scalar or (S,)."""
        lr = self.log_responsibilities(context, theta)
        p = lr.exp()
        return -reduce_each(torch.where(p > 0, p * lr, torch.zeros_like(p)).sum(-1), "mean", -1)


def _same_map(a: FeatureMap, b: FeatureMap) -> bool:
    """Whether two feature maps have one kind, widths and state."""
    if type(a) is not type(b) or (a.in_features, a.out_features) != (b.in_features, b.out_features):
        return False
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
