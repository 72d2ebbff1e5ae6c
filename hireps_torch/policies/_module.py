"""The base of the policy modules: checkpoints that do not fit are refused before anything is
copied, and a refit's new values are set all at once (or not at all)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn

from hireps_torch.checks import all_finite, check_state_dict

__all__ = ["PolicyModule"]


class PolicyModule(nn.Module):
    """An ``nn.Module`` whose :meth:`load_state_dict` and :meth:`set_parameters` either
    complete or leave the module exactly as it was.

    Subclasses add their own rules for a loaded state in :meth:`check_state` (e.g. a Cholesky
    factor must be lower triangular with a positive diagonal).
    """

    OPTIONAL_STATE: tuple[str, ...] = ()
    """This module's entries that an older checkpoint may lack; they keep their value."""

    def _completed(self, state_dict: Mapping[str, Any]) -> Mapping[str, Any]:
        """``state_dict`` with the optional entries it lacks taken from this module."""
        mine = self.state_dict()
        missing = {
            f"{name}.{key}" if name else key
            for name, module in self.named_modules()
            if isinstance(module, PolicyModule)
            for key in module.OPTIONAL_STATE
        } - set(state_dict)
        missing &= set(mine)
        return state_dict if not missing else {**state_dict, **{k: mine[k] for k in missing}}

    def check_state(self, state: Mapping[str, Tensor]) -> None:
        """Module-specific checks of this module's own entries of a state (names without the
        module's prefix; keys and shapes are already checked, entries may be absent when not
        strict). Raises a ``ValueError`` naming the entry."""

    def check_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True) -> None:
        """Raise (``ValueError`` / ``TypeError``, naming the entry and, for a shape, both the
        saved and the expected shape) unless :meth:`load_state_dict` would load
        ``state_dict`` completely. Changes nothing."""
        what = type(self).__name__
        state_dict = self._completed(state_dict)
        check_state_dict(what, self.state_dict(), state_dict, strict)
        for name, module in self.named_modules():
            if isinstance(module, PolicyModule):
                prefix = f"{name}." if name else ""
                own = {
                    key[len(prefix) :]: value
                    for key, value in state_dict.items()
                    if key.startswith(prefix) and "." not in key[len(prefix) :]
                }
                try:
                    module.check_state(own)
                except ValueError as exc:
                    raise ValueError(f"{what}: {prefix}{exc}") from None

    def load_state_dict(
        self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False
    ) -> Any:
        """``nn.Module.load_state_dict`` after :meth:`check_state_dict`: a checkpoint of
        another number of options or dimension, with a missing key or a non-finite value is
        refused with a message naming it, before anything is copied."""
        self.check_state_dict(state_dict, strict)
        return super().load_state_dict(self._completed(state_dict), strict, assign)

    @torch.no_grad()
    def set_parameters(self, values: Mapping[str, Tensor]) -> None:
        """Copy new values into parameters and buffers (``state_dict`` names -> tensors of
        the same shapes), all checked (names, shapes, finiteness) before the first copy."""
        current = {**dict(self.named_parameters()), **dict(self.named_buffers())}
        for key, value in values.items():
            if key not in current:
                raise ValueError(f"{type(self).__name__} has no parameter or buffer {key!r}")
            if value.shape != current[key].shape:
                raise ValueError(
                    f"{key} must have shape {tuple(current[key].shape)}, got {tuple(value.shape)}"
                )
            if value.is_floating_point() and not all_finite(value):
                raise ValueError(f"the new value of {key} is not finite")
        self.set_checked(values)

    @torch.no_grad()
    def set_checked(self, values: Mapping[str, Tensor]) -> None:
        """:meth:`set_parameters` of values already checked (names, shapes, finiteness), as
        the refits' ``fit_checked`` return them."""
        modules: dict[str, nn.Module] = {"": self}
        for key, value in values.items():
            path, _, name = key.rpartition(".")
            module = modules.get(path)
            if module is None:
                module = modules[path] = self.get_submodule(path)
            getattr(module, name).copy_(value)
