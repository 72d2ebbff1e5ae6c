"""The tasks: toy multimodal objectives (and, as they land, pendulum, ball on a beam, hockey)."""

from environments.toy import ContextualTwoGaussians, TwoGaussians

__all__ = ["ContextualTwoGaussians", "TwoGaussians"]
