"""Construction checks of :class:`~hireps_torch.policies.HierarchicalPolicy`."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from hireps_torch.checks import as_float_tensor
from hireps_torch.features import FeatureMap
from hireps_torch.policies.gating import Gating
from hireps_torch.policies.linear_gaussian import LinearGaussian

__all__ = ["check_feature_maps", "check_gating", "initial_means"]


def initial_means(init_mean: Tensor | None, n_options: int, action_dim: int) -> Tensor:
    """init_mean (None, (D,) or (O, D)), its shape checked, as float64."""
    if init_mean is None:
        return torch.zeros(action_dim, dtype=torch.float64)
    mean = as_float_tensor("init_mean", init_mean)
    if mean.shape not in ((action_dim,), (n_options, action_dim)):
        raise ValueError(
            f"init_mean must have shape (D,) = ({action_dim},) or (O, D) = "
            f"({n_options}, {action_dim}), got {tuple(mean.shape)}"
        )
    return mean  # its values: checked by LinearGaussian


def check_gating(gating: object, n_options: int, in_features: int | None = None) -> None:
    """``gating`` a :class:`Gating` over ``n_options`` taking ``in_features`` (when given)."""
    if not isinstance(gating, Gating):
        raise TypeError(
            f"gating must be a Gating (e.g. SoftmaxGating), got {type(gating).__name__}"
        )
    if gating.n_options != n_options:
        raise ValueError(
            f"gating has {gating.n_options} options but {n_options} sub-policies were given"
        )
    if in_features is not None and gating.in_features != in_features:
        raise ValueError(
            f"gating_features give {in_features} features but the gating takes {gating.in_features}"
        )


def check_feature_maps(
    gating: Gating, options: Sequence[LinearGaussian], gf: FeatureMap, pf: FeatureMap
) -> None:
    """The feature maps must take the same contexts and feed the gating and the options."""
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
