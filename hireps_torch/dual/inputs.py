"""Input checks of the dual wrappers and :func:`~hireps_torch.dual.solve_reps_dual` (each input is
checked once, here; the solver trusts them)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from hireps_torch._linalg import logsumexp
from hireps_torch.checks import (
    as_f64,
    as_float_tensor,
    check_count,
    check_finite,
    check_positive,
    check_positive_float,
)
from hireps_torch.dual.block_solver import LbfgsSettings
from hireps_torch.dual.solutions import DegenerateWeightsWarning

__all__ = [
    "LOG_RESP_FLOOR",
    "Checked",
    "centred",
    "check_blocks",
    "check_bounds",
    "check_feature_vector",
    "check_log_resp",
    "check_settings",
    "common_inputs",
    "per_block",
    "warn_if_degenerate",
]

LOG_RESP_FLOOR = -1.0e4  # stands in for log(0) of pruned options; exp() of it is exactly 0


def check_log_resp(log_resp: Tensor, name: str = "log_responsibilities") -> Tensor:
    """Check log-probabilities normalised over the last dim; return them with log 0 floored (rows
    off by up to 1e-4 renormalised in float64)."""
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
    name: str,
    value: float | Tensor,
    K: int,
    device: torch.device | None = None,
    S: int | None = None,
) -> Tensor:
    """A bound (one float or (K,)) as a (K,) float64 tensor on ``device``; with ``S`` (a
    population's) also (S, K), or (S,) with K = 1, as (S, K)."""
    t = as_float_tensor(name, value, allow_bool=False).to(device)
    if t.dim() == 0:
        return t.expand(K).clone()
    if t.shape == (K,):
        return t
    if S is not None and (t.shape == (S, K) or (K == 1 and t.shape == (S,))):
        return t.reshape(S, K)
    members = "" if S is None else f", or per member ({S}, {K})"
    members += f" or ({S},)" if S is not None and K == 1 else ""
    raise ValueError(
        f"{name} must be a float or have shape ({K},) (one per block){members}, got "
        f"{tuple(t.shape)}"
    )


def _led(
    name: str, x: Tensor, lead: tuple[int, ...], last: str, population: bool, device: torch.device
) -> Tensor:
    """``x`` as float64 on ``device``, of shape (*lead, ``last``), else a ValueError naming the
    shape, e.g. '(N, K, F) = (60, 3, F)' for lead (60, 3) (S first for a population)."""
    t = as_f64(name, x, device)
    if t.dim() != len(lead) + 1 or tuple(t.shape[:-1]) != lead:
        names = (["S"] if population else []) + ["N", "K"][: len(lead) - population] + [last]
        shape = f"({', '.join(names)}) = ({', '.join([*map(str, lead), last])})"
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    return t


@dataclass(frozen=True)
class Checked:
    """A wrapper's checked inputs: R (S, K, N), eps (S, K), lr (S, K, N, O) (log 0 floored), kappa
    (S, K) or None, the solver's ``settings``, and the returns' shape ``lead`` as given (S first
    for a ``population``), against which :meth:`features` checks."""

    R: Tensor
    eps: Tensor
    lr: Tensor
    kappa: Tensor | None
    settings: LbfgsSettings
    lead: tuple[int, ...]
    population: bool

    def features(self, name: str, x: Tensor) -> Tensor:
        """Features (*lead, F) checked, on R's device, as (S, N, [K,] F)."""
        phi = _led(name, x, self.lead, "F", self.population, self.R.device)
        check_finite(name, phi)
        return phi.reshape(self.R.shape[0], *self.lead[self.population :], -1)

    def feature_vector(self, name: str, x: Tensor, F: int) -> Tensor:
        """A mean feature vector (F,) checked (for a population also (S, F)), as (S, F)."""
        S = self.R.shape[0]
        phi = check_feature_vector(name, x, F, S if self.population else None, self.R.device)
        return phi.reshape(S, F)


def common_inputs(
    returns: Tensor,
    epsilon: float | Tensor,
    log_responsibilities: Tensor | None,
    kappa: float | Tensor | None,
    max_iter: object,
    name: str = "returns",
    *,
    per_step: bool = False,
    population: bool = False,
) -> Checked:
    """Validate the inputs every wrapper shares, S = 1 unless ``population``. Warns
    :class:`~hireps_torch.dual.DegenerateWeightsWarning` where epsilon >= log N.

    ``returns`` is (N,), or (N, K) ``per_step``, after S for a ``population``;
    ``log_responsibilities`` the same plus O (None: one option); epsilon a float or (K,); kappa
    None, a float or (K,) (inf: no bound), for a population also (S, K) or (S,) with K = 1;
    ``max_iter`` see :func:`check_settings`; ``name`` is what messages call ``returns``.
    """
    settings = check_settings(max_iter)
    if not isinstance(population, bool):
        raise TypeError(f"population must be True or False, got {population!r}")
    R = as_f64(name, returns)
    dev = R.device
    names = ["S"] * population + ["N"] + ["K"] * per_step
    dims = ", ".join(names) + ("," if len(names) == 1 else "")
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
    eps, kap = check_bounds(epsilon, kappa, K, N, dev, S if population else 0)
    lr = _log_responsibilities(log_responsibilities, lead, S, K, population, dev)
    kap = None if kap is None else kap.expand(S, K)
    return Checked(R, eps.expand(S, K), lr, kap, settings, lead, population)


def check_bounds(
    epsilon: float | Tensor,
    kappa: float | Tensor | None,
    K: int,
    N: int,
    device: torch.device,
    S: int = 0,
) -> tuple[Tensor, Tensor | None]:
    """epsilon (K,), > 0, and kappa (K,), >= 0 (inf: no bound) or None, on ``device``; warns (at
    the solver's caller, 4 frames up) where epsilon >= log N. ``S`` > 0: a population's kappa may
    also be (S, K) or, with K = 1, (S,) (returned as (S, K))."""
    eps = per_block("epsilon", epsilon, K, device)
    check_positive("epsilon", eps)
    warn_if_degenerate(eps.tolist(), N, 4)
    kap = None
    if kappa is not None:
        kap = per_block("kappa", kappa, K, device, S or None)
        if bool(torch.isnan(kap).any()) or bool((kap < 0).any()):
            raise ValueError(f"kappa must be >= 0 (inf: no bound), got {kap.tolist()}")
    return eps, kap


def warn_if_degenerate(epsilon: list[float], N: int, stacklevel: int) -> None:
    """:class:`~hireps_torch.dual.DegenerateWeightsWarning` where a block's epsilon >= log N,
    ``stacklevel`` frames up (1: this function's caller)."""
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
    """Checked (*lead, O) log-responsibilities on ``device`` as (S, K, N, O); zeros (S, K, N, 1) for
    None."""
    N = lead[int(population)]
    if x is None:
        return torch.zeros(S, K, N, 1, dtype=torch.float64, device=device)
    lr = _led("log_responsibilities", x, lead, "O", population, device)
    return check_log_resp(lr).reshape(S, N, K, -1).transpose(1, 2).contiguous()


def check_feature_vector(
    name: str, x: Tensor, F: int, S: int | None = None, device: torch.device | None = None
) -> Tensor:
    """Check a mean feature vector (F,), or (S, F) for a population (S given; an (F,) one is shared
    and returned as (S, F)); on ``device`` if given."""
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
) -> LbfgsSettings:
    """The solver options checked: ``max_iter`` an integer >= 1, the tolerances finite and > 0."""
    try:
        n = check_count("max_iter", max_iter, 1)
    except (TypeError, ValueError) as exc:
        raise type(exc)(f"max_iter must be an integer >= 1, got {max_iter!r}") from None
    tols = []
    for name, value in (("tolerance_grad", tolerance_grad), ("converged_grad", converged_grad)):
        try:
            tols.append(check_positive_float(name, value))
        except (TypeError, ValueError) as exc:
            raise type(exc)(f"{name} must be a finite number > 0, got {value!r:.60}") from None
    return LbfgsSettings(n, tols[0], tols[1])


def check_blocks(
    R: Tensor,
    log_resp: Tensor,
    epsilon: float | Tensor,
    D: Tensor | None,
    c: Tensor | None,
    kappa: float | Tensor | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None, Tensor | None]:
    """The inputs of :func:`~hireps_torch.dual.solve_reps_dual` checked, in float64, as a
    population of one (the leading 1 of :func:`~hireps_torch.dual.solver.solve_blocks`): R
    (1, K, N), K >= 1, N >= 2; log_resp (1, K, N, O); epsilon, kappa (1, K); D (1, K, N, P), c
    (1, P) (only with D)."""
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
    eps, kap = check_bounds(epsilon, kappa, K, N, dev)
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

    def one(x: Tensor | None) -> Tensor | None:
        return None if x is None else x[None]

    return Rt[None], lr[None], eps[None], one(Dt), one(ct), one(kap)


def centred(phi: Tensor) -> Tensor:
    """phi (..., N, F) minus its mean over samples; columns constant to round-off (spread below
    1e-14 of their magnitude) exactly 0."""
    out = phi - phi.mean(dim=-2, keepdim=True)
    spread = phi.amax(dim=-2, keepdim=True) - phi.amin(dim=-2, keepdim=True)
    constant = spread <= 1e-14 * phi.abs().amax(dim=-2, keepdim=True)
    return torch.where(constant, torch.zeros_like(out), out)
