"""A trained run loaded back at its last checkpoint: config, algorithm and policy::

run = hireps_torch.load_run("runs/pendulum/20261202-100000")
actions = run.mean_action(states)          # (N, C) -> (N, D), the final policy's mean
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from hireps_torch.algorithms import Algorithm
from hireps_torch.checks import as_finite_f64, as_float_tensor, check_count
from hireps_torch.experiments import EXPERIMENTS
from hireps_torch.experiments.checkpoint import (
    changed_options,
    check_same_run,
    checkpoint_dir,
    load_checkpoint,
    read_config,
    run_config,
)
from hireps_torch.experiments.migrations import earlier_version_note, no_config_note
from hireps_torch.experiments.runner import logged_rows

__all__ = ["LoadedRun", "load_run"]


@dataclass(frozen=True)
class LoadedRun:
    """A run as its last checkpoint left it.

    Attributes:
        run_dir: the directory loaded.
        experiment: its experiment's command-line name (``pendulum``, ``hockey-sequential``, ...).
        config: the experiment's config as the run used it (``run_dir`` where it is now).
        algorithm: the run's algorithm with the checkpoint's state, on the CPU (batched
            experiments: a population of S = 1, its inputs and outputs with a leading 1).
        iteration: iterations done.
        finished: whether the run finished (``summary.json`` written).
        metrics: the rows of its ``metrics.csv`` (one dict per iteration), from the checkpoint.
    """

    run_dir: Path
    experiment: str
    config: Any
    algorithm: Algorithm
    iteration: int
    finished: bool
    metrics: list[dict[str, Any]]

    def mean_action(self, states: Tensor | int, step: int = 0) -> Tensor:
        """The policy's mean action (no exploration): states (N, C) -> (N, D) at decision
        ``step``; N itself for a task without states (C = 0)."""
        return self._one(self.algorithm.mean_action, states, step)

    def sample(self, states: Tensor | int, step: int = 0) -> Tensor:
        """Exploratory actions (N, C) -> (N, D), continuing the run's generator stream."""
        return self._one(self.algorithm.sample, states, step)

    def _one(self, act: Callable[[Tensor, int], Tensor], states: Tensor | int, step: int) -> Tensor:
        C = self.algorithm.policies[0].context_dim
        if C == 0 and getattr(states, "ndim", 0) == 0 and not isinstance(states, list | tuple):
            x = torch.zeros(check_count("N", states, 1), 0, dtype=torch.float64)  # a count
        else:
            x = as_float_tensor("states", states)
            if x.dim() != 2 or x.shape[-1] != C or x.shape[0] == 0:
                raise ValueError(
                    f"states must have shape (N, {C}) with N >= 1, got {tuple(x.shape)}"
                )
            as_finite_f64("states", x)  # named at the user's (N, C), before a leading 1
        return act(x[None], step)[0]


def load_run(run_dir: str | Path) -> LoadedRun:
    """Load a run directory (or a population member ``<dir>/seed<s>``) written by
    ``hireps-train``, changing nothing on disk; a ``ValueError`` says what is wrong."""
    if not isinstance(run_dir, str | os.PathLike):
        raise TypeError(f"run_dir must be a path (str or Path), got {type(run_dir).__name__}")
    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file():
        note = no_config_note(run_dir)
        raise ValueError(f"{run_dir} holds no config.json: it is not a run directory.{note}")
    saved = read_config(run_dir)
    name = str(saved.get("experiment", ""))
    if name not in EXPERIMENTS:
        raise ValueError(
            f"{run_dir / 'config.json'} names the experiment {saved.get('experiment')!r}; "
            f"this code knows {sorted(EXPERIMENTS)}"
        )
    if saved.get("seeds") is not None:
        raise ValueError(
            f"{run_dir} is a population (seeds {saved['seeds']}); load one member, e.g. "
            f"load_run({str(run_dir / 'seed<s>')!r})"
        )
    config, algorithm = _build(name, run_dir)
    root, member = checkpoint_dir(run_dir, config.seed)
    ckpt = load_checkpoint(root, map_location="cpu")
    if ckpt is None:
        rows = logged_rows(run_dir / "metrics.csv")
        raise ValueError(
            f"{root} holds no checkpoint.pt: the run had not finished its first iteration, "
            "so nothing was learned yet"
            if not rows
            else f"{root} holds no checkpoint.pt but {rows} metrics row(s) and a summary.json: a "
            "population member's policy is in its population's checkpoint (load it inside the "
            "population's directory), the checkpoint was moved away, or it is a member of a "
            "population that an earlier version of this code ran, which wrote no checkpoint"
            if (run_dir / "summary.json").is_file()
            else f"{root} holds no checkpoint.pt but {rows} metrics row(s): the run is writing "
            "its first checkpoint (load it again in a moment), a population member's policy is "
            "in its population's checkpoint (load it inside the population's directory), or the "
            "checkpoint was moved away"
        )
    run_only = EXPERIMENTS[name].run_only
    check_same_run(root, ckpt, saved if member is None else read_config(root), run_only)
    state = ckpt["algorithm"]
    if member is not None:
        _check_member(run_dir, root, saved, run_only)
        population = _build(name, root)[1]
        population.load_state_dict(state)
        state = _member_state(population.state_dict(), algorithm.state_dict(), *member)
    try:
        algorithm.load_state_dict(state)
    except ValueError as exc:
        raise ValueError(
            f"{root / 'checkpoint.pt'} does not fit its run: {exc}{earlier_version_note(exc)}"
        ) from None
    return LoadedRun(
        run_dir=run_dir,
        experiment=name,
        config=config,
        algorithm=algorithm,
        iteration=int(ckpt["iteration"]),
        finished=(run_dir / "summary.json").is_file(),
        metrics=[dict(r) for r in ckpt["rows"][member[0] if member else 0]],
    )


def _build(name: str, run_dir: Path) -> tuple[Any, Algorithm]:
    """The config in ``run_dir/config.json`` and its untrained algorithm."""
    entry = EXPERIMENTS[name]
    config = run_config(entry.config, name, run_dir)
    try:
        return config, entry.algorithm(config)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"{run_dir / 'config.json'} does not hold the options of a {name} run: {exc}"
        ) from None


def _check_member(
    run_dir: Path, root: Path, saved: Mapping[str, Any], run_only: tuple[str, ...]
) -> None:
    """A member's config.json is its population's with its own seed."""
    population = {k: v for k, v in read_config(root).items() if k not in ("seed", "seeds")}
    member = {k: v for k, v in saved.items() if k != "seed"}
    if diff := changed_options(population, member, ("population", "member"), run_only):
        raise ValueError(
            f"{run_dir / 'config.json'} does not match its population's {root / 'config.json'}: "
            + "; ".join(diff)
        )


def _member_state(population: Any, member: Any, s: int, S: int) -> Any:
    """Member s's part of a population's state, shaped like ``member`` (a population of one's,
    or an ordinary algorithm's for hockey)."""
    if isinstance(population, Mapping):
        return {k: _member_state(v, member[k], s, S) for k, v in population.items()}
    if isinstance(population, Tensor) and population.shape != member.shape:
        return population[s : s + 1].clone() if population.dim() == member.dim() else population[s]
    if isinstance(population, list) and isinstance(member, Tensor):  # S generators, one
        return population[s]
    if isinstance(population, list) and len(population) == len(member) and member:
        if isinstance(member[0], Mapping):  # hockey's policies, one per shot
            return [_member_state(p, m, s, S) for p, m in zip(population, member, strict=True)]
    if isinstance(population, list) and len(population) == S and len(member) == 1:
        return [population[s]]
    return population
