"""The base of the policy modules: all-or-nothing loading and setting of parameters."""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

import torch
from torch import Tensor, nn

from hireps_torch.checks import all_finite, check_count, check_state_dict
from hireps_torch.policies._population import check_members

__all__ = ["PolicyModule"]

M = TypeVar("M", bound="PolicyModule")


class PolicyModule(nn.Module):
    """An ``nn.Module`` whose :meth:`load_state_dict` and :meth:`set_parameters` either
    complete or leave the module as it was; subclasses add rules in :meth:`check_state`."""

    OPTIONAL_STATE: tuple[str, ...] = ()
    """Entries an older checkpoint may lack; they keep their value."""

    population: int | None = None
    """S for a population of S modules stacked by :meth:`stack`; None for one module."""
    _stacked: tuple[str, ...] = ()
    """Parameters and buffers a population stacks along S (the others the members share)."""
    _shared: tuple[str, ...] = ()
    """Attributes the members of a population must share."""

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """() for one module, (S,) for a population."""
        return () if self.population is None else (self.population,)

    @classmethod
    def stack(cls: type[M], members: Sequence[M]) -> M:
        """A population of S modules of one kind (copies) stacked along a leading S of every
        input and output; the members and their submodules must pass :meth:`_check_alike`."""
        items: list[M] = check_members("members", members, cls)
        out = copy.deepcopy(items[0])
        for path, module in out.named_modules():
            if isinstance(module, PolicyModule):
                alike = [m.get_submodule(path) for m in items]
                for s, m in enumerate(alike[1:], 1):
                    module._check_alike(s, m)
                module.population = len(items)
                with torch.no_grad():
                    for name in module._stacked:
                        _replace(module, name, torch.stack([getattr(m, name) for m in alike]))
        return out

    def _check_alike(self, s: int, m: nn.Module) -> None:
        """Raise unless member ``s``'s ``m`` may be stacked with this (member 0's) module: one
        kind, the same :attr:`_shared`, dtype and unstacked buffers."""
        if type(m) is not type(self):
            raise TypeError(
                f"members[{s}] is a {type(m).__name__} but members[0] a "
                f"{type(self).__name__}: a population holds one kind"
            )
        for what in self._shared:
            if getattr(m, what) != getattr(self, what):
                raise ValueError(
                    f"members[{s}].{what} = {getattr(m, what)} but members[0].{what} = "
                    f"{getattr(self, what)}: a population shares it"
                )
        for name, value in self.named_buffers(recurse=False):
            if name not in self._stacked and not torch.equal(getattr(m, name), value):
                raise ValueError(f"members[{s}].{name} differs from members[0]'s")
        a, b = getattr(m, self._stacked[-1]), getattr(self, self._stacked[-1])
        if a.dtype != b.dtype:
            raise ValueError(f"members[{s}] is {a.dtype} but members[0] is {b.dtype}")

    def member(self: M, s: int) -> M:
        """Member ``s`` of a population as an ordinary module (a copy), submodules included."""
        if self.population is None:
            raise ValueError(
                "member() takes a member of a population; this module holds one policy"
            )
        index = check_count("s", s, 0)
        if index >= self.population:
            raise ValueError(f"member s must be in [0, {self.population}), got {index}")
        out = copy.deepcopy(self)
        with torch.no_grad():
            for module in out.modules():
                if isinstance(module, PolicyModule):
                    module.population = None
                    for name in module._stacked:
                        _replace(module, name, getattr(module, name)[index].clone())
        return out

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
        """Checks of this module's own entries (unprefixed, may be absent); a ``ValueError``."""

    def check_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True) -> None:
        """Raise, naming the entry, unless :meth:`load_state_dict` would load ``state_dict``."""
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
        """``nn.Module.load_state_dict`` after :meth:`check_state_dict`."""
        self.check_state_dict(state_dict, strict)
        return super().load_state_dict(self._completed(state_dict), strict, assign)

    @torch.no_grad()
    def set_parameters(self, values: Mapping[str, Tensor]) -> None:
        """Copy values (``state_dict`` names -> same-shape tensors), all checked first."""
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
        """:meth:`set_parameters` of values already checked (as ``fit_checked`` returns)."""
        modules: dict[str, nn.Module] = {"": self}
        for key, value in values.items():
            path, _, name = key.rpartition(".")
            module = modules.get(path)
            if module is None:
                module = modules[path] = self.get_submodule(path)
            getattr(module, name).copy_(value)


def _replace(module: nn.Module, name: str, value: Tensor) -> None:
    """Replace parameter or buffer ``name`` by ``value`` (of another shape)."""
    if name in module._parameters:
        setattr(module, name, nn.Parameter(value, requires_grad=False))
    else:
        module.register_buffer(name, value)
