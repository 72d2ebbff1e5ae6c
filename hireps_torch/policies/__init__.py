"""Policies: linear-Gaussian options, gating networks and the hierarchical mixture."""

from hireps_torch.policies.gating import ConstantGating, SoftmaxGating
from hireps_torch.policies.hierarchical import HierarchicalPolicy
from hireps_torch.policies.linear_gaussian import LinearGaussian, weighted_least_squares

__all__ = [
    "ConstantGating",
    "HierarchicalPolicy",
    "LinearGaussian",
    "SoftmaxGating",
    "weighted_least_squares",
]
