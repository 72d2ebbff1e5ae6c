"""Population runs: the seeds of one experiment as one population in one process (issue 14).

``python train.py pendulum --seeds 0-19 --run-dir D`` builds the 20 seeds' policies as one
population (:meth:`~hireps_torch.policies.HierarchicalPolicy.stack`), steps all their systems
in one batched environment, solves their 20 duals in one call and refits them in one batched
call per option. Each seed writes an ordinary run directory ``D/seed<S>`` (``config.json``
with its own seed, ``metrics.csv``, ``learning_curve.png``, ``summary.json``); ``D`` gets
``population.md`` (the per-seed table), ``population.json`` (the summaries) and
``population.png`` (mean +- std band over the seeds), as a sweep would.

A population of one seed is the ordinary run (written to ``D/seed<S>``): its ``metrics.csv``
is that of ``--seed S`` byte for byte. Members draw from their own generators, so a member's
samples do not depend on its companions; in the episodic task (bimodal) a member reproduces
its ordinary run to round-off, while the batched environments of pendulum and ball-on-beam
draw their restarts from per-seed generators in another order than the TorchRL collector of
the ordinary runs (the same distribution, other draws).

Population runs do not checkpoint: an interrupted one keeps the rows written so far in each
member's ``metrics.csv`` and is run again from the start.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from experiments.checkpoint import stop_on_signals
from experiments.options import RunOptions, config_dict, parse_seeds
from experiments.rundir import RunWriter, default_run_dir

__all__ = ["Members", "TaskPopulation", "member_row", "population_loop", "run_population"]

PopulationRun = Callable[[Any, "Members"], list[dict[str, Any]]]
"""An experiment's population run: (config, members) -> one summary per member."""


def member_row(diagnostics: Mapping[str, Sequence[Any]], s: int) -> dict[str, Any]:
    """Member ``s``'s entries of a population's diagnostics (lists of S entries)."""
    return {key: value[s] for key, value in diagnostics.items()}


class Members:
    """The run directories of a population: ``root/seed<S>`` for each seed, each an
    ordinary run directory (its ``config.json`` holds its own seed and no ``seeds``)."""

    def __init__(self, experiment: str, cfg: RunOptions, seeds: Sequence[int]) -> None:
        self.experiment = experiment
        self.seeds = list(seeds)
        self.root = Path(cfg.run_dir) if cfg.run_dir is not None else default_run_dir(experiment)
        self.configs = [self.member_config(cfg, s) for s in self.seeds]
        self.writers: list[RunWriter] = []

    def open(self) -> None:
        """Create the members' run directories (each refused if it exists and is not empty)
        and write their ``config.json``; called by :func:`population_loop`, after the
        experiment has checked its options, so that a refused run writes nothing."""
        try:
            for c in self.configs:
                self.writers.append(RunWriter(c.run_dir, config_dict(self.experiment, c), c.logger))
        except BaseException:
            self.close()
            raise

    def member_config(self, cfg: RunOptions, seed: int) -> Any:
        """The config of the member with ``seed``: ``cfg`` with that seed, its own run
        directory and no ``seeds`` (what ``train.py E --seed S`` would write; a ``device``
        other than the CPU stays in it, and such a member is run again with ``--seeds S
        --device D``)."""
        return dataclasses.replace(cfg, seed=seed, seeds=None, run_dir=self.root / f"seed{seed}")

    def log(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """One row per member, in the order of the seeds."""
        for writer, row in zip(self.writers, rows, strict=True):
            writer.log(row)

    def close(self) -> None:
        for writer in self.writers:
            writer.close()

    def finish(
        self,
        summaries: Sequence[Mapping[str, Any]],
        *,
        curve: tuple[str, Sequence[str]],
        title: str,
        ylabel: str = "return",
        extra_plots: Sequence[Sequence[Callable[[Path], None]]] = (),
    ) -> list[dict[str, Any]]:
        """Each member's learning curve, extra plots and ``summary.json``; returns the
        summaries as written."""
        out = []
        plots = list(extra_plots) or [[] for _ in self.writers]
        for writer, summary, mine in zip(self.writers, summaries, plots, strict=True):
            writer.plot_learning_curve(curve[0], list(curve[1]), title=title, ylabel=ylabel)
            for plot in mine:
                plot(writer.dir)
            out.append(writer.finish(summary))
        return out


def population_loop(
    members: Members,
    step: Callable[[int], list[dict[str, Any]]],
    *,
    iterations: int,
    label: str,
    postfix: Callable[[list[dict[str, Any]]], dict[str, Any]],
    progress: bool,
) -> None:
    """Iterations 0 .. iterations - 1 of ``step(it)`` (one row per member), each row logged
    to its member's ``metrics.csv``, with a progress bar. SIGINT / SIGTERM stop the loop at
    the next iteration boundary (the rows so far stay written)."""
    members.open()
    bar = tqdm(total=iterations, desc=label, disable=not progress)
    try:
        with stop_on_signals("then stopping (population runs write no checkpoint)") as stop:
            for it in range(iterations):
                rows = step(it)
                members.log(rows)
                bar.update(1)
                bar.set_postfix(**postfix(rows))
                if stop.signame is not None and it + 1 < iterations:
                    raise KeyboardInterrupt(
                        f"{stop.signame}: population stopped after iteration {it + 1}; the "
                        f"members' metrics.csv under {members.root} hold the rows so far. "
                        "Population runs write no checkpoint and do not resume: to run it "
                        f"again, move {members.root} away or pass another --run-dir"
                    )
    finally:
        bar.close()
        members.close()


class TaskPopulation:
    """S members' batched tasks (each an :class:`~environments._common.BatchedTask` of B
    systems with its own generator, as the ordinary run's environment) stepped together: one
    transition of all S x B systems per decision; starts, restarts and truncation draw from
    each member's own task, so a member's systems do not depend on its companions.

    The systems are stepped on the tasks' device; each member's start states and restart
    draws come from its task's CPU generator (moved to the device), as in its ordinary run.

    Args:
        tasks: one task per member, all of the same kind, constants, batch size and device.
    """

    def __init__(self, tasks: Sequence[Any]) -> None:
        self.tasks = list(tasks)
        first = self.tasks[0]
        self.S, self.B, self.device = len(self.tasks), first.batch, first.device
        shape = (self.S, self.B)
        self.state = torch.zeros(*shape, first.state_dim, dtype=torch.float64, device=self.device)
        self.t = torch.zeros(shape, dtype=torch.long, device=self.device)
        self.reset()

    def reset(self, mask: Tensor | None = None) -> None:
        """Restart the masked (S, B) systems (all when None); a member whose systems are not
        masked draws nothing."""
        every = torch.ones(self.S, self.B, dtype=torch.bool)
        masks = (every if mask is None else mask).cpu()
        # a new tensor: the old one may be a collected next state (before the restart)
        self.state = self.state.clone()
        for s, task in enumerate(self.tasks):
            m = masks[s]
            if bool(m.any()):
                task.t = self.t[s]  # the task sees which systems took a decision since starting
                fresh = task.start_states(m).to(self.device, torch.float64)
                md = m.to(self.device)
                self.state[s] = torch.where(md[:, None], fresh, self.state[s])
                self.t[s] = torch.where(md, 0, self.t[s])
                task.t = self.t[s]

    def collect(self, act: Callable[[Tensor], Tensor], decisions: int) -> tuple[Tensor, ...]:
        """``decisions`` decisions of every system with ``act`` (states (S, B, dim), seen as
        float32 observations as a TorchRL environment gives them -> actions (S, B, 1)):
        states, actions (float32 values), rewards, next states (before any restart) and
        terminated, each (S, B * decisions, ...), system after system. Systems whose episode
        ends (terminated or truncated) restart at once."""
        S, B = self.S, self.B
        out: list[list[Tensor]] = [[], [], [], [], []]
        for _ in range(decisions):
            obs = self.state.to(torch.float32).to(torch.float64)
            action = act(obs).to(torch.float32).to(torch.float64)
            flat = self.state.reshape(S * B, -1)
            nxt, reward, term, _ = self.tasks[0].transition(flat, action.reshape(S * B, 1))
            nxt, reward, term = nxt.reshape(S, B, -1), reward.reshape(S, B), term.reshape(S, B)
            for buf, x in zip(out, (self.state, action, reward, nxt, term), strict=True):
                buf.append(x)
            self.state = nxt
            self.t += 1
            done = torch.zeros(S, B, dtype=torch.bool, device=self.device)
            for m, task in enumerate(self.tasks):
                task.t = self.t[m]
                done[m] = term[m] | task.truncated(term[m])
            self.reset(done)
        states, a, r, s_next, terminated = (torch.stack(buf, 2).flatten(1, 2) for buf in out)
        return states, a, r, s_next, terminated


def run_population(experiment: str, cfg: Any, populations: Mapping[str, PopulationRun]) -> Any:
    """``train.py <experiment> --seeds ...``: the seeds as one population (a single seed:
    the ordinary run in ``<run-dir>/seed<S>``), then the population summary; returns it."""
    from experiments import EXPERIMENTS
    from experiments.sweep import METRICS, SweepRun, summarize

    cfg.check_run_options()
    seeds = parse_seeds(cfg.seeds)
    if experiment not in populations:
        known = ", ".join(populations)
        raise ValueError(
            f"--seeds runs a population of {known}; {experiment} runs one seed at a time "
            f"(run its seeds with train.py sweep --experiment {experiment} --seeds {cfg.seeds})"
        )
    members = None
    if len(seeds) == 1 and torch.device(cfg.device).type == "cpu":  # the ordinary run
        root = Path(cfg.run_dir) if cfg.run_dir is not None else default_run_dir(experiment)
        one = dataclasses.replace(cfg, seed=seeds[0], seeds=None, run_dir=root / f"seed{seeds[0]}")
        summaries = [EXPERIMENTS[experiment][1](one)]
    else:
        members = Members(experiment, cfg, seeds)
        root = members.root
        summaries = populations[experiment](cfg, members)
    name = experiment
    runs = [SweepRun(experiment, name, s, {}, root / f"seed{s}") for s in seeds]
    results = {(name, s): summary for s, summary in zip(seeds, summaries, strict=True)}
    table = summarize(runs, results, root, stem="population")
    metric = METRICS[experiment][0]
    values = [float(s[metric]) for s in summaries]
    walls = [float(s.get("wall_seconds", float("nan"))) for s in summaries]
    print(table)
    return {
        "experiment": experiment,
        "seeds": seeds,
        "metric": metric,
        "mean": statistics.fmean(values),
        "std": statistics.stdev(values) if len(values) > 1 else 0.0,
        "per_seed": dict(zip(map(str, seeds), values, strict=True)),
        "wall_seconds": max(walls),
        "run_dir": str(root),
        "summary": str(root / "population.md"),
        "plot": str(root / "population.png"),
    }
