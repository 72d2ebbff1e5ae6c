"""Input checks of the dual wrappers (episodic, infinite-horizon, time-indexed).

The generic checks (float64 conversion, finiteness, positivity) come from
:mod:`hireps_torch.checks`; the dual-specific ones (normalised log-responsibilities, per-block
bounds, feature shapes, solver settings) live here. Each input is checked once, here; the
solver trusts them.
"""

from __future__ import annotations

import math
import numbers
import operator
import warnings

import torch
from torch import Tensor

from hireps_torch._linalg import logsumexp
from hireps_torch.checks import as_f64, as_float, check_finite, check_positive
from hireps_torch.dual.solutions import DegenerateWeightsWarning

__all__ = [
    "LOG_RESP_FLOOR",
    "centred",
    "check_blocks",
    "check_bounds",
    "check_feature_vector",
    "check_features",
    "check_log_resp",
    "check_settings",
    "common_inputs",
    "per_block",
    "warn_if_degenerate",
]

LOG_RESP_FLOOR = -1.0e4  # stands in for log(0) of pruned options; exp() of it is exactly 0


def check_log_resp(log_resp: Tensor, name: str = "log_responsibilities") -> Tensor:
    """Check log-probabilities normalised over the last dim; return them with log 0 floored.

    Rows normalised only to float32 precision (off by up to 1e-4) are renormalised in float64,
    so that the old distribution q p~ sums to 1 and its KL to itself is 0."""
    if log_resp.shape[-1] == 0:
        raise ValueError(
            f"{name} must have at least one option column, got {tuple(log_resp.shape)}"
        )
    bad = torch.isnan(log_resp) | torch.isposinf(log_resp)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{name} contains NaN or +inf (first at index {idx}: {log_resp[idx].item()})"
        )
    if bool((log_resp > 1e-6).any()):
        raise ValueError(f"{name} must be log-probabilities (<= 0), max is {log_resp.max().item()}")
    norm = logsumexp(log_resp)
    off = norm.abs()
    worst = off.max().item()
    if worst > 1e-4:
        row = ", ".join(str(int(i)) for i in (off == worst).nonzero()[0])
        raise ValueError(
            f"{name} must be normalised over options (logsumexp over the last dim = 0); "
            f"row [{row}] is off by {worst:.3g}"
            + (" (every option has probability 0)" if math.isinf(worst) else "")
        )
    if worst > 1e-13:
        log_resp = log_resp - norm.unsqueeze(-1)
    return log_resp.clamp_min(LOG_RESP_FLOOR)


def per_block(
    name: str, value: float | Tensor, K: int, device: torch.device | None = None
) -> Tensor:
    """A bound given as one float or one value per block (K,), as a (K,) float64 tensor on
    ``device`` (a setting, so a tensor on another device is moved); a bool is a ``TypeError``
    (``epsilon=True`` is no bound)."""
    if isinstance(value, bool) or (isinstance(value, Tensor) and value.dtype == torch.bool):
        raise TypeError(f"{name} must be a number or a tensor of numbers, got {value!r}")
    t = as_f64(name, value).to(device)
    if t.dim() == 0:
        return t.expand(K).clone()
    if t.shape != (K,):
        raise ValueError(
            f"{name} must be a float or have shape ({K},) (one per decision step), got "
            f"{tuple(t.shape)}"
        )
    return t


def _shape_text(lead: tuple[int, ...], last: str, population: bool = False) -> str:
    """'(N, K, F) = (60, 3, F)' for lead (60, 3) and last 'F' ('(S, N, F) = ...' with a
    population dimension first)."""
    names = (["S"] if population else []) + ["N", "K"][: len(lead) - population] + [last]
    return f"({', '.join(names)}) = ({', '.join([*map(str, lead), last])})"


def common_inputs(
    returns: Tensor,
    epsilon: float | Tensor,
    log_responsibilities: Tensor | None,
    kappa: float | Tensor | None,
    name: str = "returns",
    *,
    per_step: bool = False,
    population: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Validate the inputs every wrapper shares and return them block-major for the solver,
    with a leading population dimension S (1 for one problem).

    Warns (at the wrapper's caller) with a
    :class:`~hireps_torch.dual.DegenerateWeightsWarning` where epsilon >= log N.

    Args:
        returns: (N,) returns, or (N, K) rewards of K decision steps when ``per_step``; with
            ``population``, one more leading dimension S (S independent problems).
        epsilon: KL bound, > 0: a float or (K,) (the same for every problem).
        log_responsibilities: (N, O), or (N, K, O) when ``per_step``, after the same leading S
            as ``returns``; None means one option.
        kappa: entropy bound, >= 0 (inf: no bound on that block): None, a float or (K,); with
            ``population`` also one per problem, (S, K) or (S,) for one block.
        name: what the error messages call ``returns``.
        per_step: whether the returns are per decision step (the time-indexed dual).
        population: whether the inputs carry a leading population dimension S.

    Returns:
        R (S, K, N), epsilon (S, K), log p~ (S, K, N, O) with log 0 floored, kappa (S, K) or
        None.
    """
    if not isinstance(population, bool):
        raise TypeError(f"population must be True or False, got {population!r}")
    R = as_f64(name, returns)
    dev = R.device
    dims = ("S, " if population else "") + ("N, K" if per_step else "N,")
    if R.dim() != (2 if per_step else 1) + int(population):
        raise ValueError(f"{name} must have shape ({dims}), got {tuple(R.shape)}")
    if population and R.shape[0] < 1:
        raise ValueError(f"{name}: a population needs S >= 1 problems, got {tuple(R.shape)}")
    N = R.shape[int(population)]
    if N < 2:
        raise ValueError(f"the dual needs at least 2 samples, got N = {N}")
    if R.numel() == 0:
        raise ValueError(
            f"{name} must hold at least one decision step (K >= 1), got shape {tuple(R.shape)}"
        )
    check_finite(name, R)
    S = R.shape[0] if population else 1
    lead = tuple(int(d) for d in R.shape)
    R = R.reshape(S, N, -1).transpose(1, 2).contiguous()
    K = R.shape[1]
    per_problem = population and isinstance(kappa, Tensor) and _per_problem(kappa, S, K)
    eps, kap = check_bounds(epsilon, None if per_problem else kappa, K, N, 4, dev)
    if per_problem:
        kap = as_f64("kappa", kappa).to(dev).reshape(S, K)
        if bool(torch.isnan(kap).any()) or bool((kap < 0).any()):
            raise ValueError(f"kappa must be >= 0 (inf: no bound), got {kap.tolist()}")
    lr = _log_responsibilities(log_responsibilities, lead, S, K, population, dev)
    return R, eps.expand(S, K), lr, None if kap is None else kap.expand(S, K)


def _per_problem(kappa: Tensor, S: int, K: int) -> bool:
    """Whether a population's ``kappa`` holds one bound per problem: (S, K), or (S,) for
    one block (K = 1)."""
    return kappa.shape == (S, K) or (K == 1 and kappa.shape == (S,))


def check_bounds(
    epsilon: float | Tensor,
    kappa: float | Tensor | None,
    K: int,
    N: int,
    stacklevel: int,
    device: torch.device | None = None,
) -> tuple[Tensor, Tensor | None]:
    """epsilon (K,), > 0, and kappa (K,), >= 0 (inf: no bound) or None, on ``device``, from
    one float or one value per block; a :class:`~hireps_torch.dual.DegenerateWeightsWarning`
    (``stacklevel`` frames up) where epsilon >= log N."""
    eps = per_block("epsilon", epsilon, K, device)
    check_positive("epsilon", eps)
    warn_if_degenerate(eps.tolist(), N, stacklevel)
    kap = None
    if kappa is not None:
        kap = per_block("kappa", kappa, K, device)
        if bool(torch.isnan(kap).any()) or bool((kap < 0).any()):
            raise ValueError(f"kappa must be >= 0 (inf: no bound), got {kap.tolist()}")
    return eps, kap


def warn_if_degenerate(epsilon: list[float], N: int, stacklevel: int) -> None:
    """A :class:`~hireps_torch.dual.DegenerateWeightsWarning` where a block's epsilon >= log N
    (the weights then collapse onto the best samples), attributed ``stacklevel`` frames up
    (1: the caller of this function)."""
    big = [(k, e) for k, e in enumerate(epsilon) if e >= math.log(N)]
    if big:
        K = len(epsilon)
        which = ", ".join(
            f"epsilon = {e:.4g}" if K == 1 else f"epsilon[{k}] = {e:.4g}" for k, e in big
        )
        warnings.warn(
            f"{which} >= log N = {math.log(N):.4g} (N = {N}): the KL bound cannot bind and the "
            "weights collapse onto the best sample(s); use a smaller epsilon or more samples",
            DegenerateWeightsWarning,
            stacklevel=stacklevel + 1,
        )


def _log_responsibilities(
    x: Tensor | None,
    lead: tuple[int, ...],
    S: int,
    K: int,
    population: bool,
    device: torch.device,
) -> Tensor:
    """Checked (*lead, O) log-responsibilities on ``device`` as (S, K, N, O); zeros
    (S, K, N, 1) for None."""
    N = lead[int(population)]
    if x is None:
        return torch.zeros(S, K, N, 1, dtype=torch.float64, device=device)
    lr = as_f64("log_responsibilities", x, device)
    if lr.dim() != len(lead) + 1 or tuple(lr.shape[:-1]) != lead:
        raise ValueError(
            f"log_responsibilities must have shape {_shape_text(lead, 'O', population)}, got "
            f"{tuple(lr.shape)}"
        )
    return check_log_resp(lr).reshape(S, N, K, -1).transpose(1, 2).contiguous()


def check_features(
    name: str,
    x: Tensor,
    *lead: int,
    population: bool = False,
    device: torch.device | None = None,
) -> Tensor:
    """Check features of shape (*lead, F): (N, F), or (N, K, F) per decision step, after a
    leading S for a population (then ``lead`` starts with S); on ``device`` if given (another
    device is a ``ValueError``)."""
    phi = as_f64(name, x, device)
    if phi.dim() != len(lead) + 1 or tuple(phi.shape[:-1]) != lead:
        raise ValueError(
            f"{name} must have shape {_shape_text(lead, 'F', population)}, got {tuple(phi.shape)}"
        )
    check_finite(name, phi)
    return phi


def check_feature_vector(
    name: str, x: Tensor, F: int, S: int | None = None, device: torch.device | None = None
) -> Tensor:
    """Check a mean feature vector (F,) such as phi_hat_0, or (S, F) for a population (S
    given; one (F,) vector is then shared by every problem and returned as (S, F)); on
    ``device`` if given (numbers go there, a tensor elsewhere is a ``ValueError``)."""
    phi = as_f64(name, x, device)
    if S is not None and phi.shape == (F,):
        phi = phi.expand(S, F)
    shape = (F,) if S is None else (S, F)
    if phi.shape != shape:
        text = f"({F},)" if S is None else f"({F},) or ({S}, {F})"
        raise ValueError(f"{name} must have shape {text}, got {tuple(phi.shape)}")
    check_finite(name, phi)
    return phi


def check_settings(
    max_iter: object, tolerance_grad: object = 1e-7, converged_grad: object = 1e-6
) -> tuple[int, float, float]:
    """The solver options: ``max_iter`` an integer >= 1 (LBFGS iterations per phase), the
    tolerances finite and > 0; a message naming the bad value otherwise."""
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral | Tensor):
        raise TypeError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    try:
        n = operator.index(max_iter)
    except TypeError as exc:
        raise TypeError(f"max_iter must be an integer >= 1, got {max_iter!r}") from exc
    if n < 1:
        raise ValueError(f"max_iter must be an integer >= 1, got {n}")
    tols = []
    for name, value in (("tolerance_grad", tolerance_grad), ("converged_grad", converged_grad)):
        try:
            t = as_float(name, value)
        except (TypeError, ValueError) as exc:
            raise type(exc)(f"{name} must be a finite number > 0, got {value!r}") from None
        if not (math.isfinite(t) and t > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        tols.append(t)
    return n, tols[0], tols[1]


def check_blocks(
    R: Tensor,
    log_resp: Tensor,
    epsilon: float | Tensor,
    D: Tensor | None,
    c: Tensor | None,
    kappa: float | Tensor | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None, Tensor | None]:
    """The inputs of :func:`~hireps_torch.dual.solve_reps_dual`, checked and in float64:
    R (K, N) finite with K >= 1 and N >= 2, log_resp (K, N, O) normalised, epsilon and kappa
    per block, D (K, N, P) and c (P,) finite (c only with D)."""
    Rt = as_f64("R", R)
    if Rt.dim() != 2 or Rt.shape[0] < 1 or Rt.shape[1] < 2:
        raise ValueError(f"R must have shape (K, N) with K >= 1, N >= 2, got {tuple(Rt.shape)}")
    check_finite("R", Rt)
    K, N = Rt.shape
    dev = Rt.device
    lr = as_f64("log_resp", log_resp, dev)
    if lr.dim() != 3 or tuple(lr.shape[:2]) != (K, N) or lr.shape[2] < 1:
        raise ValueError(
            f"log_resp must have shape (K, N, O) = ({K}, {N}, O), got {tuple(lr.shape)}"
        )
    lr = check_log_resp(lr, "log_resp")
    eps, kap = check_bounds(epsilon, kappa, K, N, 4, dev)
    Dt = ct = None
    if D is not None:
        Dt = as_f64("D", D, dev)
        if Dt.dim() != 3 or tuple(Dt.shape[:2]) != (K, N):
            raise ValueError(f"D must have shape (K, N, P) = ({K}, {N}, P), got {tuple(Dt.shape)}")
        check_finite("D", Dt)
    if c is not None:
        if Dt is None:
            raise ValueError("c (the linear term in v) needs D (the features)")
        ct = check_feature_vector("c", c, Dt.shape[-1], device=dev)
    return Rt, lr, eps, Dt, ct, kap


def centred(phi: Tensor) -> Tensor:
    """phi (..., N, F) minus its mean over samples, with the columns that are constant to
    round-off (spread below 1e-14 of their magnitude) exactly 0: centring would leave them as
    round-off noise that no longer shows the magnitude it came from, and the solver would
    take that noise for a feature."""
    out = phi - phi.mean(dim=-2, keepdim=True)
    spread = phi.amax(dim=-2, keepdim=True) - phi.amin(dim=-2, keepdim=True)
    constant = spread <= 1e-14 * phi.abs().amax(dim=-2, keepdim=True)
    return torch.where(constant, torch.zeros_like(out), out)
