"""Input checks shared by the library and the environments: one home, one message style.

Every check raises ``ValueError`` (``TypeError`` for something that is not a number at all)
whose message names the argument, the expected and actual shape, or the first bad entry, so a
user can find the bad value without reading torch's internals.
"""

from __future__ import annotations

import math
import numbers
import operator
from collections.abc import Mapping

import torch
from torch import Tensor

__all__ = [
    "as_f64",
    "as_finite_f64",
    "as_float",
    "as_float_tensor",
    "check_count",
    "check_device",
    "check_present_device",
    "check_finite",
    "check_float_dtype",
    "check_generator",
    "check_positive",
    "check_positive_float",
    "check_seed",
    "check_nonnegative_float",
    "check_state_dict",
    "check_weights",
]


def as_f64(name: str, value: Tensor | object, device: torch.device | None = None) -> Tensor:
    """``value`` as a detached float64 tensor; a ``TypeError`` naming ``name`` if it is not
    a number, a sequence of numbers or a tensor.

    Python numbers and sequences go straight to float64 (``torch.as_tensor(0.2)`` alone would
    round through float32: 0.20000000298), on ``device`` (the CPU when None); tensors keep
    their values (a float32 tensor holds float32 values already) and their device. With
    ``device`` given, a tensor on another device is a ``ValueError`` naming both (the dual's
    data must live on one device: it is solved where its inputs are). Complex values are a
    ``TypeError`` (their imaginary part would be dropped silently); a ``meta`` tensor, which
    holds no values, is a ``ValueError``."""
    if not isinstance(value, Tensor):
        try:
            value = torch.as_tensor(value, dtype=torch.float64, device=device or "cpu")
        except Exception as exc:
            raise TypeError(
                f"{name} must be a tensor or numbers, got {type(value).__name__} {_short(value)}"
            ) from exc
    if value.is_complex():
        raise TypeError(f"{name} must be real, got a {value.dtype} tensor")
    if device is not None and value.device != torch.device(device):
        raise ValueError(
            f"{name} is on device {value.device} but the other inputs are on {device}: move "
            "them to one device first"
        )
    if value.is_meta:
        raise ValueError(f"{name} is a meta tensor (no values); pass a tensor with data")
    return value.detach().to(dtype=torch.float64)


def _short(value: object) -> str:
    """repr of ``value``, cut to 60 characters (for error messages)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def all_finite(x: Tensor) -> bool:
    """Whether every entry of ``x`` is finite, in one reduction where it is (a sum is finite
    unless an entry is not, or the sum of finite entries overflows: then the entries decide)."""
    return math.isfinite(float(x.sum())) or bool(torch.isfinite(x).all())


def check_finite(
    name: str, x: Tensor, advice: str = "remove or fix those samples before the update"
) -> None:
    """Raise naming ``name``, the number of non-finite entries and the first one's index
    (followed by ``advice``, if any)."""
    if all_finite(x):
        return
    bad = ~torch.isfinite(x)
    idx = tuple(int(i) for i in bad.nonzero()[0])
    raise ValueError(
        f"{name} contains {int(bad.sum())} non-finite value(s) (first at index {idx}: "
        f"{x[idx].item()})" + (f"; {advice}" if advice else "")
    )


def as_finite_f64(name: str, value: Tensor | float, shape: tuple[int, ...] | None = None) -> Tensor:
    """``value`` as a float64 tensor, checked for ``shape`` (if given) and finiteness; the
    errors name ``name``, the shapes, and the first non-finite entry."""
    if isinstance(value, Tensor):
        t = value.to(torch.float64)  # on its device
    else:
        t = torch.as_tensor(value, dtype=torch.float64, device="cpu")
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
    """Every entry of ``value`` finite and > 0."""
    if not all_finite(value) or bool((value <= 0).any()):
        raise ValueError(f"{name} must be finite and > 0, got {value.tolist()}")


def as_float(name: str, value: object) -> float:
    """A real scalar (a Python or numpy number, or a 0-d tensor) as a float.

    Raises a ``TypeError`` naming ``name`` for a bool, a string or anything else that is not a
    number, and a ``ValueError`` naming the shape for a tensor or array with dimensions (a
    ``(2,)`` tensor where one number is expected). NaN and inf pass (the callers check ranges).
    """
    if isinstance(value, bool) or (isinstance(value, Tensor) and value.dtype == torch.bool):
        raise TypeError(f"{name} must be a number, got the bool {value!r}")
    if isinstance(value, numbers.Real):
        return float(value)
    shape = getattr(value, "shape", None)
    if shape is not None:
        if len(shape) != 0:
            raise ValueError(
                f"{name} must be one number (a float or a 0-d tensor), got a "
                f"{type(value).__name__} of shape {tuple(shape)}"
            )
        if isinstance(value, Tensor) and (value.is_complex() or value.dtype == torch.bool):
            raise TypeError(f"{name} must be a real number, got a {value.dtype} tensor")
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
    """``value`` (a tensor, number or nested sequence of numbers) as a detached ``dtype``
    tensor. Bool (unless not ``allow_bool``: a setting such as a standard deviation) and
    integer tensors are converted; complex values, strings and other objects raise a
    ``TypeError`` naming ``name``; a tensor on another ``device`` (when given) or a ``meta``
    tensor (no values) a ``ValueError`` naming the device. Values are not checked (see
    :func:`check_finite`)."""
    if not allow_bool and (
        isinstance(value, bool) or (isinstance(value, Tensor) and value.dtype == torch.bool)
    ):
        raise TypeError(f"{name} must be a number or a tensor of numbers, got the bool {value!r}")
    if isinstance(value, Tensor):
        t = value.detach()
    else:
        try:
            where = device if device is not None else torch.device("cpu")
            t = torch.as_tensor(value, device=where)
            if t.is_floating_point():  # Python floats keep their float64 precision
                t = torch.as_tensor(value, dtype=torch.float64, device=where)
        except Exception as exc:
            raise TypeError(
                f"{name} must be a tensor of numbers, got {type(value).__name__} {_short(value)}"
            ) from exc
    if t.is_complex() or not (t.is_floating_point() or t.dtype == torch.bool or _is_int(t)):
        raise TypeError(f"{name} must hold real numbers, got dtype {t.dtype}")
    if t.is_meta and device is None:
        raise ValueError(f"{name} is a meta tensor (no values); pass a tensor with data")
    if device is not None and t.device != device:
        raise ValueError(
            f"{name} is on device {t.device} but the model is on {device}; move one of them "
            f"(e.g. {name}.to({str(device)!r}))"
        )
    return t.to(dtype)


def check_weights(name: str, w: Tensor) -> None:
    """Sample weights: finite, >= 0 and not all zero (any scale); the error names ``name``
    and the first bad entry."""
    check_finite(name, w, "")
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


def check_float_dtype(dtype: object, name: str = "dtype") -> torch.dtype:
    """``dtype`` if it is a floating ``torch.dtype``; a ``TypeError`` naming it otherwise."""
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"{name} must be a floating torch.dtype, got {_short(dtype)}")
    return dtype


def check_device(device: object) -> torch.device:
    """``device`` (a ``torch.device`` or its name) as a ``torch.device``; a ``ValueError``
    naming it otherwise."""
    try:
        dev: torch.device = torch.device(device)  # type: ignore[call-overload]
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be a torch device or its name, got {device!r}") from None
    return dev


def check_present_device(device: object) -> torch.device:
    """:func:`check_device`, and a device that holds values (not ``meta``) and is present on
    this machine (``cuda`` without a GPU is refused); a ``ValueError`` naming it."""
    dev = check_device(device)
    if dev.type == "meta":
        raise ValueError(f"device {device!r} holds no values: use cpu or cuda")
    try:
        torch.empty(0, device=dev)
    except Exception as exc:  # RuntimeError, AssertionError, a missing backend module, ...
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"device {device!r} is not available here ({first})") from None
    return dev


def check_generator(name: str, value: object) -> torch.Generator | None:
    """``value`` if it is a ``torch.Generator`` or None; a ``TypeError`` naming ``name``."""
    if value is not None and not isinstance(value, torch.Generator):
        raise TypeError(
            f"{name} must be a torch.Generator or None, got {type(value).__name__} {_short(value)}"
        )
    return value


def _is_int(t: Tensor) -> bool:
    return not t.is_floating_point() and not t.is_complex() and t.dtype != torch.bool


def check_count(name: str, value: object, minimum: int = 1) -> int:
    """An integer >= ``minimum`` (a count, a dimension, a seed) as an int.

    Accepts Python and numpy integers and 0-d integer tensors; a bool, a float (even 2.0) or
    anything else raises a ``TypeError`` naming ``name``, a smaller value a ``ValueError``."""
    if isinstance(value, bool) or (isinstance(value, Tensor) and value.dtype == torch.bool):
        raise TypeError(f"{name} must be an integer, got the bool {value!r}")
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


def check_seed(name: str, value: object, headroom: int = 0) -> int:
    """An integer seed that ``torch.Generator.manual_seed`` takes (in [-2**63, 2**64 - 1],
    less ``headroom`` at the top for seeds derived as ``seed + k``), as an int; a
    ``TypeError`` / ``ValueError`` naming ``name`` otherwise."""
    seed = check_count(name, value, SEED_RANGE[0])
    top = SEED_RANGE[1] - headroom
    if seed > top:
        raise ValueError(f"{name} must be an integer in [-2**63, {top}], got {seed}")
    return seed


def check_positive_float(name: str, value: float) -> float:
    """A finite scalar > 0 (e.g. epsilon), as a float; a 0-d tensor is accepted, a tensor
    with dimensions raises (see :func:`as_float`)."""
    v = as_float(name, value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value}")
    return v


def check_nonnegative_float(name: str, value: float | None) -> float | None:
    """A finite scalar >= 0 or None (e.g. kappa_rel), as a float."""
    if value is None:
        return None
    v = as_float(name, value)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be finite and >= 0 (or None), got {value}")
    return v


def check_state_dict(
    what: str, expected: Mapping[str, Tensor], state: object, strict: bool = True
) -> None:
    """Check that ``state`` can be loaded where ``expected`` (a ``state_dict()``) lives.

    Raises before anything is copied: a ``TypeError`` if ``state`` is not a mapping of
    tensors; a ``ValueError`` naming every entry whose saved shape differs from the expected
    one (both shapes: a checkpoint of another number of options or another dimension), then
    (with ``strict``) the missing and the unexpected keys, then a bool entry that is not bool
    and the first non-finite entry of a floating one.
    """
    if not isinstance(state, Mapping):
        raise TypeError(f"{what}: a state_dict must be a mapping, got {type(state).__name__}")
    for key, value in state.items():
        if key in expected and not isinstance(value, Tensor):
            raise TypeError(f"{what}: state entry {key!r} must be a tensor, got {type(value)}")
        if key in expected and value.is_meta:
            raise ValueError(f"{what}: state entry {key!r} is a meta tensor (no values)")
    wrong = [
        f"{key}: saved {tuple(state[key].shape)}, expected {tuple(ref.shape)}"
        for key, ref in expected.items()
        if key in state and state[key].shape != ref.shape
    ]
    if wrong:
        raise ValueError(
            f"{what}: the checkpoint was made for other shapes (another number of options or "
            f"another dimension?): {'; '.join(wrong)}"
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
            if saved.is_complex() or not (saved.is_floating_point() or _is_int(saved)):
                raise ValueError(f"{what}: state entry {key!r} must be real, got {saved.dtype}")
            if not all_finite(saved):
                raise ValueError(f"{what}: state entry {key!r} holds non-finite values")
