"""Input checks shared by the library and the environments: a ``ValueError`` (``TypeError``
for a non-number) naming the argument, the shapes or the first bad entry."""

from __future__ import annotations

import math
import numbers
import operator
from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "FIX_SAMPLES",
    "NO_MEMBER_DIMENSION",
    "as_checked",
    "as_f64",
    "as_finite_f64",
    "as_float",
    "as_float_tensor",
    "as_weights",
    "check_count",
    "check_device",
    "check_present_device",
    "check_finite",
    "check_float_dtype",
    "check_generator",
    "check_positive",
    "check_positive_float",
    "check_prune_threshold",
    "check_seed",
    "check_nonnegative_float",
    "check_state_dict",
]


def as_f64(name: str, value: Tensor | object, device: torch.device | None = None) -> Tensor:
    """:func:`as_float_tensor` in float64 (bools as 0 / 1)."""
    return as_float_tensor(name, value, torch.float64, device)


def _short(value: object) -> str:
    """repr of ``value``, cut to 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def all_finite(x: Tensor) -> bool:
    """Whether every entry of ``x`` is finite (one sum when it is)."""
    return math.isfinite(float(x.sum())) or bool(torch.isfinite(x).all())


FIX_SAMPLES = "remove or fix those samples before the update"
"""The advice of :func:`check_finite` for samples."""


def check_finite(name: str, x: Tensor, advice: str = FIX_SAMPLES) -> None:
    """Raise naming ``name`` and the first non-finite entry (then ``advice``) unless all finite."""
    if all_finite(x):
        return
    bad = ~torch.isfinite(x)
    idx = tuple(int(i) for i in bad.nonzero()[0])
    raise ValueError(
        f"{name} contains {int(bad.sum())} non-finite value(s) (first at index {idx}: "
        f"{x[idx].item()})" + (f"; {advice}" if advice else "")
    )


def as_finite_f64(name: str, value: Tensor | float, shape: tuple[int, ...] | None = None) -> Tensor:
    """``value`` as a float64 tensor, checked for ``shape`` (if given) and finiteness."""
    if isinstance(value, Tensor):
        if value.is_complex():  # .to would drop the imaginary part
            raise TypeError(f"{name} must hold real numbers, got dtype {value.dtype}")
        t = value.to(torch.float64)  # on its device (gradients flow through)
    else:
        t = as_float_tensor(name, value)  # on the CPU
    if shape is not None and tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    if not all_finite(t):
        bad = (~torch.isfinite(t)).nonzero()[0].tolist()
        where = bad[0] if len(bad) == 1 else bad
        raise ValueError(
            f"{name} contains non-finite values (first at index {where}: {t[tuple(bad)].item()})"
        )
    return t


def check_positive(name: str, value: Tensor) -> None:
    """Every entry of ``value`` finite and > 0 (a ValueError shows one number for a value
    broadcast from one)."""
    if not all_finite(value) or bool((value <= 0).any()):
        flat = value.reshape(-1)
        one = bool((flat == flat[0]).all())  # non-empty: an empty value passes
        raise ValueError(
            f"{name} must be finite and > 0, got {flat[0].item() if one else value.tolist()}"
        )


def as_float(name: str, value: object) -> float:
    """A real scalar (number or 0-d tensor) as a float; NaN and inf pass. A ``TypeError`` for a
    bool, a complex or non-number, a ``ValueError`` for a tensor or array with dimensions, a
    meta tensor or an integer past float64's range."""
    if isinstance(value, bool | np.bool_) or (
        isinstance(value, Tensor) and value.dtype == torch.bool
    ):
        raise TypeError(f"{name} must be a number, got the bool {value!r}")
    if isinstance(value, numbers.Real):
        try:
            return float(value)
        except OverflowError:  # an integer past float64's range
            raise ValueError(f"{name} is beyond float64's range, got {value!r:.60}") from None
    shape = getattr(value, "shape", None)
    if shape is not None:
        if len(shape) != 0:
            raise ValueError(
                f"{name} must be one number (a float or a 0-d tensor), got a "
                f"{type(value).__name__} of shape {tuple(shape)}"
            )
        if isinstance(value, Tensor):
            if value.is_complex():
                raise TypeError(f"{name} must be a real number, got a {value.dtype} tensor")
            if value.is_meta:
                raise ValueError(f"{name} is a meta tensor (no values); pass a number")
        elif isinstance(value, np.ndarray | np.generic) and np.iscomplexobj(value):
            raise TypeError(f"{name} must be a real number, got a complex {type(value).__name__}")
        try:
            return float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            pass
    raise TypeError(f"{name} must be a number, got {type(value).__name__} {value!r}")


def as_float_tensor(
    name: str,
    value: object,
    dtype: torch.dtype = torch.float64,
    device: torch.device | None = None,
    *,
    allow_bool: bool = True,
) -> Tensor:
    """``value`` (a tensor or numbers; bools as 0 / 1 only with ``allow_bool``) as a detached
    ``dtype`` tensor, values unchecked; numbers go on ``device`` (CPU when None), tensors keep
    theirs. A ``TypeError`` for bools, complex values, non-numbers or sparse and nested
    tensors, a ``ValueError`` for a meta tensor or one on another ``device`` (when given)."""
    if isinstance(value, Tensor):
        if value.layout != torch.strided or value.is_nested:
            what = "nested" if value.is_nested else str(value.layout).removeprefix("torch.")
            raise TypeError(f"{name} must be a dense tensor, got a {what} one: pass .to_dense()")
        t = value.detach()
    else:
        try:
            where = device if device is not None else torch.device("cpu")
            try:
                t = torch.as_tensor(value, device=where)
            except (TypeError, ValueError, OverflowError):  # integers past int64: as float64
                t = torch.as_tensor(value, dtype=torch.float64, device=where)
            if t.is_floating_point():  # Python floats keep their float64 precision
                t = torch.as_tensor(value, dtype=torch.float64, device=where)
        except Exception as exc:
            raise TypeError(
                f"{name} must be a tensor of numbers, got {type(value).__name__} {_short(value)}"
            ) from exc
    if t.dtype == torch.bool and not allow_bool:
        raise TypeError(
            f"{name} must be a number or a tensor of numbers, got bools: {_short(value)}"
        )
    if t.is_complex():
        raise TypeError(f"{name} must hold real numbers, got dtype {t.dtype}")
    if device is not None and t.device != torch.device(device):
        raise ValueError(
            f"{name} is on device {t.device} but the other inputs are on {device}: move them "
            f"to one device (e.g. {name}.to({str(device)!r}))"
        )
    if t.is_meta:
        raise ValueError(f"{name} is a meta tensor (no values); pass a tensor with data")
    return t.to(dtype)


def as_checked(
    name: str,
    value: object,
    shape: tuple[int | None, ...],
    dtype: torch.dtype = torch.float64,
    device: torch.device | None = None,
    advice: str = "",
    names: str = "",
) -> Tensor:
    """:func:`as_float_tensor` of ``value`` checked for ``shape`` (None: any size; the message
    shows it as N, after ``names``) and finiteness (:func:`check_finite` with ``advice``)."""
    t = as_float_tensor(name, value, dtype, device)
    sizes = zip(shape, t.shape, strict=False)
    if t.dim() != len(shape) or any(n not in (None, m) for n, m in sizes):
        want = str(shape).replace("None", "N")
        raise ValueError(f"{name} must have shape {names}{want}, got {tuple(t.shape)}")
    check_finite(name, t, advice)
    return t


def as_weights(name: str, value: object, shape: tuple[int, ...], members: bool = False) -> Tensor:
    """Sample weights of ``shape`` (:func:`as_checked`): >= 0 and not all zero (with
    ``members``: for no member along the first dimension)."""
    w = as_checked(name, value, shape)
    negative = w < 0
    if bool(negative.any()):
        idx = tuple(int(i) for i in negative.nonzero()[0])
        raise ValueError(
            f"{name} must be non-negative, got {int(negative.sum())} negative value(s) (first "
            f"at index {idx}: {w[idx].item()})"
        )
    if not bool((w > 0).any()):
        raise ValueError(
            f"{name} are all zero (shape {tuple(w.shape)}); they must be non-negative and not "
            "all zero"
        )
    if members:
        empty = ~(w > 0).flatten(1).any(1)
        if bool(empty.any()):
            s = int(empty.nonzero()[0, 0])
            raise ValueError(f"{name}[{s}] are all zero (member {s} of the population)")
    return w


def check_float_dtype(dtype: object, name: str = "dtype") -> torch.dtype:
    """``dtype`` if a floating ``torch.dtype``; a ``TypeError`` otherwise."""
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"{name} must be a floating torch.dtype, got {_short(dtype)}")
    return dtype


def check_device(device: object) -> torch.device:
    """``device`` (a ``torch.device`` or its name) as a ``torch.device``."""
    try:
        dev: torch.device = torch.device(device)  # type: ignore[call-overload]
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be a torch device or its name, got {device!r}") from None
    return dev


def check_present_device(device: object) -> torch.device:
    """:func:`check_device` of a device present on this machine (not ``meta``)."""
    dev = check_device(device)
    if dev.type == "meta":
        raise ValueError(f"device {device!r} holds no values: use cpu or cuda")
    try:
        torch.empty(0, device=dev)
    except Exception as exc:  # RuntimeError, AssertionError, a missing backend module, ...
        said = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        first = said.split(". ")[0].rstrip(".")[:160]  # torch's text runs on for lines
        raise ValueError(f"device {str(dev)!r} is not available here ({first})") from None
    return dev


def check_generator(name: str, value: object) -> torch.Generator | None:
    """``value`` if a ``torch.Generator`` or None; a ``TypeError`` otherwise."""
    if value is not None and not isinstance(value, torch.Generator):
        raise TypeError(
            f"{name} must be a torch.Generator or None, got {type(value).__name__} {_short(value)}"
        )
    return value


def check_count(name: str, value: object, minimum: int = 1) -> int:
    """An integer (Python, numpy or 0-d tensor; not bool or float) >= ``minimum`` as an int."""
    if isinstance(value, bool) or (isinstance(value, Tensor) and value.dtype == torch.bool):
        raise TypeError(f"{name} must be an integer, got the bool {value!r}")
    if isinstance(value, Tensor) and (value.dim() or value.is_meta):
        what = "a meta tensor" if value.is_meta else f"a tensor of shape {tuple(value.shape)}"
        raise TypeError(f"{name} must be an integer (a 0-d tensor at most), got {what}")
    try:
        n = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(
            f"{name} must be an integer, got {type(value).__name__} {value!r}"
        ) from None
    if n < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {n}")
    return int(n)


SEED_RANGE = (-(2**63), 2**64 - 1)
"""The seeds ``torch.Generator.manual_seed`` takes."""


def check_seed(name: str, value: object) -> int:
    """An integer seed in :data:`SEED_RANGE`, as an int."""
    seed = check_count(name, value, SEED_RANGE[0])
    if seed > SEED_RANGE[1]:
        raise ValueError(f"{name} must be an integer in [-2**63, {SEED_RANGE[1]}], got {seed}")
    return seed


def check_positive_float(name: str, value: object) -> float:
    """A finite scalar > 0 (:func:`as_float`), as a float."""
    v = as_float(name, value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value}")
    return v


def check_nonnegative_float(name: str, value: object) -> float:
    """A finite scalar >= 0 (:func:`as_float`), as a float."""
    v = as_float(name, value)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return v


def check_prune_threshold(value: float, name: str = "prune_threshold") -> float:
    """A prior mass in [0, 1) below which options are pruned (0: never), as a float."""
    threshold = as_float(name, value)
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"{name} must be in [0, 1) (0: never prune), got {value}")
    return threshold


NO_MEMBER_DIMENSION = "it holds one run without a member dimension"


def check_state_dict(
    what: str, expected: Mapping[str, Tensor], state: object, strict: bool = True
) -> None:
    """Raise unless ``state`` can be loaded where ``expected`` (a ``state_dict()``) lives:
    a mapping of tensors with the expected shapes, keys (``strict``), dtypes, finite values."""
    if not isinstance(state, Mapping):
        raise TypeError(f"{what}: a state_dict must be a mapping, got {type(state).__name__}")
    for key, value in state.items():
        if key in expected and not isinstance(value, Tensor):
            raise TypeError(f"{what}: state entry {key!r} must be a tensor, got {type(value)}")
        if key in expected and value.is_meta:
            raise ValueError(f"{what}: state entry {key!r} is a meta tensor (no values)")
    wrong = [key for key, ref in expected.items() if key in state and state[key].shape != ref.shape]
    if wrong:
        if all(expected[k].shape == (1, *state[k].shape) for k in wrong):
            why = f"{NO_MEMBER_DIMENSION}, where this is a population of one"
        else:
            why = "another population size, number of options or dimension?"
        shapes = [
            f"{k}: saved {tuple(state[k].shape)}, expected {tuple(expected[k].shape)}"
            for k in wrong
        ]
        if len(shapes) > 3:
            shapes = [*shapes[:2], f"and {len(shapes) - 2} more"]
        raise ValueError(
            f"{what}: the checkpoint was made for other shapes ({why}): {'; '.join(shapes)}"
        )
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    if strict and (missing or unexpected):
        raise ValueError(
            f"{what}: the checkpoint does not match: missing keys {missing}, unexpected keys "
            f"{unexpected}"
        )
    for key, ref in expected.items():
        if key not in state:
            continue
        saved: Tensor = state[key]
        if ref.dtype == torch.bool and saved.dtype != torch.bool:
            raise ValueError(f"{what}: state entry {key!r} must be bool, got {saved.dtype}")
        if ref.is_floating_point():
            if saved.is_complex() or saved.dtype == torch.bool:
                raise ValueError(f"{what}: state entry {key!r} must be real, got {saved.dtype}")
            if not all_finite(saved):
                raise ValueError(f"{what}: state entry {key!r} holds non-finite values")
