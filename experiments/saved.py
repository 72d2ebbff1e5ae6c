"""A trained run loaded back: its config, its algorithm as saved, and a policy to act with.

:func:`load_run` (also ``hireps_torch.load_run``) reads a run directory that ``hireps-train``
wrote (finished or interrupted, of any experiment), or a member ``<dir>/seed<s>`` of a
population, and rebuilds what the run held at its last checkpoint::

    run = hireps_torch.load_run("runs/pendulum/2026-12-02_10-00-00")
    actions = run.mean_action(states)          # (N, C) -> (N, D), the final policy's mean
    run.algorithm.state_dict()                 # the run's algorithm, as saved

The algorithm is the one the run learned with, its ``state_dict()`` the checkpoint's: for the
batched experiments a population of S = 1 members (its inputs and outputs have a leading 1),
for hockey an ordinary algorithm. :meth:`LoadedRun.mean_action` and :meth:`LoadedRun.sample`
take and return the ordinary shapes for both.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from hireps_torch.algorithms import Algorithm
from hireps_torch.experiments.checkpoint import load_checkpoint, read_config, run_config

__all__ = ["LoadedRun", "load_run"]


@dataclass(frozen=True)
class LoadedRun:
    """A run as its last checkpoint left it.

    Attributes:
        run_dir: the directory loaded.
        experiment: its experiment's command-line name (``pendulum``, ``hockey-sequential``, ...).
        config: the experiment's config as the run used it (``run_dir`` where it is now).
        algorithm: the run's algorithm with the checkpoint's state, on the CPU (a population
            of one for the batched experiments, see the module docstring).
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

    def mean_action(self, states: Tensor, step: int = 0) -> Tensor:
        """The learned policy's mean action: states (N, C) -> (N, D) (at decision ``step`` of
        a time-indexed policy). No exploration: the action the run evaluates."""
        return self._one(self.algorithm.mean_action, states, step)

    def sample(self, states: Tensor, step: int = 0) -> Tensor:
        """Exploratory actions (N, C) -> (N, D) from the learned policy, drawn with the
        algorithm's generator (its state the run's, so samples continue the run's stream)."""
        return self._one(self.algorithm.sample, states, step)

    def _one(self, act: Callable[[Tensor, int], Tensor], states: Tensor, step: int) -> Tensor:
        if self.algorithm.population is None:  # hockey: one ordinary algorithm
            return act(states, step)
        return act(torch.as_tensor(states)[None], step)[0]


def load_run(run_dir: str | Path) -> LoadedRun:
    """Load a run directory (or a population member ``<dir>/seed<s>``) written by
    ``hireps-train``; a ``ValueError`` names what is wrong with a directory that is not one,
    that holds no checkpoint yet, or whose checkpoint does not fit its config. Loading
    changes nothing on disk."""
    from hireps_torch.experiments import ALGORITHMS, EXPERIMENTS

    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file():
        raise ValueError(f"{run_dir} holds no config.json: it is not a run directory")
    saved = read_config(run_dir)
    name = str(saved.get("experiment", "")).replace("_", "-")
    if name not in EXPERIMENTS:
        raise ValueError(
            f"{run_dir / 'config.json'} names the experiment {saved.get('experiment')!r}; "
            f"this code knows {sorted(EXPERIMENTS)}"
        )
    config = run_config(EXPERIMENTS[name][0], name, run_dir)
    if saved.get("seeds") is not None:
        raise ValueError(
            f"{run_dir} is a population (seeds {saved['seeds']}); load one member, e.g. "
            f"load_run({str(run_dir / 'seed<s>')!r})"
        )
    root, member = _checkpoint_dir(run_dir, config.seed)
    ckpt = load_checkpoint(root, map_location="cpu")
    if ckpt is None:
        raise ValueError(
            f"{root} holds no checkpoint.pt: the run stopped before its first iteration "
            "ended, so nothing was learned"
        )
    _check_same_run(run_dir, root, ckpt, saved)
    population = ALGORITHMS[name](run_config(EXPERIMENTS[name][0], name, root)) if member else None
    algorithm = ALGORITHMS[name](config)
    state = ckpt["algorithm"]
    if population is not None and member is not None:
        population.load_state_dict(state)
        state = _member_state(population.state_dict(), algorithm.state_dict(), *member)
    algorithm.load_state_dict(state)
    return LoadedRun(
        run_dir=run_dir,
        experiment=name,
        config=config,
        algorithm=algorithm,
        iteration=int(ckpt["iteration"]),
        finished=(run_dir / "summary.json").is_file(),
        metrics=[dict(r) for r in ckpt["rows"][member[0] if member else 0]],
    )


def _checkpoint_dir(run_dir: Path, seed: int) -> tuple[Path, tuple[int, int] | None]:
    """Where the run's checkpoint is, and for a population member (index, S)."""
    parent = run_dir.resolve().parent
    if (run_dir / "checkpoint.pt").exists() or not (parent / "config.json").is_file():
        return run_dir, None
    from hireps_torch.experiments.options import parse_seeds

    seeds = read_config(parent).get("seeds")
    if seeds is None or seed not in parse_seeds(seeds) or run_dir.name != f"seed{seed}":
        return run_dir, None
    members = parse_seeds(seeds)
    return parent, (members.index(seed), len(members))


def _check_same_run(
    run_dir: Path, root: Path, ckpt: Mapping[str, Any], saved: Mapping[str, Any]
) -> None:
    if ckpt.get("experiment") != saved.get("experiment"):
        raise ValueError(
            f"{root / 'checkpoint.pt'} is of a {ckpt.get('experiment')!r} run, but "
            f"{run_dir / 'config.json'} of a {saved.get('experiment')!r} run"
        )


def _member_state(population: Any, member: Any, s: int, S: int) -> Any:
    """Member s's part of a population's state, in the shape of ``member`` (a population of
    one's state): tensors with a leading S and lists of S entries give their s-th, what the
    members share is kept."""
    if isinstance(population, Mapping):
        return {k: _member_state(v, member[k], s, S) for k, v in population.items()}
    if isinstance(population, Tensor) and population.shape != member.shape:
        return population[s : s + 1].clone()
    if isinstance(population, list) and len(population) == S and len(member) == 1:
        return [population[s]]
    return population
