"""The training loops every experiment shares, and the one ending of every run.

- :func:`collector_loop`: a TorchRL collector hands over one batch per iteration; ``update``
  turns it into the iteration's logged fields (the policy update happens there).
- :func:`ask_tell_loop`: no environment process at all; ``step`` asks the algorithm, scores
  the samples and tells it back (the toy objectives, a real robot driven from Python).
- :func:`finish_run`: checkpoint, learning-curve plot and ``summary.json``, in that order, so a
  directory holding ``summary.json`` is a finished run.

Every loop writes one row per iteration to the run directory (:class:`RunWriter`) and shows a
tqdm progress bar. Nothing here reads a config object: the arguments are explicit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from experiments.rundir import LoggerName, RunWriter, default_run_dir

__all__ = [
    "Postfix",
    "ask_tell_loop",
    "check_budget",
    "collector_loop",
    "finish_run",
    "infinite_horizon_postfix",
    "infinite_horizon_update",
    "open_run",
]

Postfix = Callable[[dict[str, Any]], dict[str, Any]]
"""Maps a logged row to the progress bar's postfix fields."""


def open_run(
    experiment: str,
    run_dir: Path | None,
    config: Mapping[str, Any],
    logger: LoggerName = "csv",
) -> RunWriter:
    """The run directory (``runs/<experiment>/<timestamp>`` unless ``run_dir`` is given) with
    ``config.json`` written; refuses a directory that exists and is not empty."""
    return RunWriter(run_dir or default_run_dir(experiment), config, logger)


def _log(writer: RunWriter, bar: Any, row: dict[str, Any], postfix: Postfix) -> None:
    writer.log(row)
    bar.update(1)
    bar.set_postfix(**postfix(row))


def collector_loop(
    collector: Any,
    open_writer: Callable[[], RunWriter],
    update: Callable[[Any], dict[str, Any]],
    *,
    iterations: int,
    episodes_per_iteration: int,
    label: str,
    postfix: Postfix,
    sync_weights: bool = False,
    progress: bool = True,
) -> RunWriter:
    """The training loop of every experiment that collects with TorchRL.

    Opens the run directory (``open_writer()``), then for every collected batch:
    ``update(batch)`` (the policy update; returns the iteration's logged fields), a weight
    sync to the worker processes when ``sync_weights``, one logged row (``iteration``,
    ``episodes`` and the fields) and a progress-bar step showing ``postfix(row)``. The
    collector is shut down however the loop ends (also when the run directory cannot be
    opened). Returns the writer for :func:`finish_run`.
    """
    from hireps_torch.rollout import shutdown_collector

    try:
        writer = open_writer()
    except BaseException:
        shutdown_collector(collector)
        raise
    bar = tqdm(total=iterations, desc=label, disable=not progress)
    try:
        for it, batch in enumerate(collector):
            fields = update(batch)
            if sync_weights:
                collector.update_policy_weights_()
            row = {"iteration": it + 1, "episodes": (it + 1) * episodes_per_iteration, **fields}
            _log(writer, bar, row, postfix)
    finally:
        bar.close()
        shutdown_collector(collector)
    return writer


def ask_tell_loop(
    writer: RunWriter,
    step: Callable[[int], dict[str, Any]],
    *,
    iterations: int,
    label: str,
    postfix: Postfix,
    progress: bool = True,
) -> RunWriter:
    """``iterations`` rounds of ``step(it)`` (ask, evaluate, tell; returns the logged row),
    one row and one progress-bar step each. Returns the writer for :func:`finish_run`."""
    bar = tqdm(range(iterations), desc=label, disable=not progress)
    try:
        for it in bar:
            row = step(it)
            writer.log(row)
            bar.set_postfix(**postfix(row))
    finally:
        bar.close()
    return writer


def infinite_horizon_update(
    algo: Any,
    row: Callable[[torch.Tensor, torch.Tensor], dict[str, Any]],
    augment: Callable[..., tuple[torch.Tensor, ...]] | None = None,
) -> Callable[[Any], dict[str, Any]]:
    """The per-batch step of the pendulum and the beam: one ``algo.update`` on the batch's
    decisions (terminal ones flagged; passed through ``augment(s, a, r, s', terminated)``
    first when given), then ``row(rewards, terminated)`` on the collected decisions for the
    task's own columns (after the update) followed by the update's diagnostics."""
    from hireps_torch.rollout import transitions

    def update(batch: Any) -> dict[str, Any]:
        s, a, r, s_next, _ = transitions(batch, "state")
        terminated = batch["next", "terminated"].reshape(-1)
        data = (s, a, r, s_next, terminated)
        diag = algo.update(*(augment(*data) if augment is not None else data))
        return {**row(r, terminated), **diag}

    return update


def finish_run(
    writer: RunWriter,
    *,
    checkpoint: Mapping[str, Any],
    curve: tuple[str, Sequence[str]],
    title: str,
    summary: Mapping[str, Any],
    ylabel: str = "return",
    extra_plots: Iterable[Callable[[Path], None]] = (),
) -> dict[str, Any]:
    """The ending of every run: ``checkpoint.pt``, ``learning_curve.png`` (columns
    ``curve[1]`` of ``metrics.csv`` against ``curve[0]``), any ``extra_plots`` (each called
    with the run directory), then ``summary.json`` (plus ``wall_seconds``), which marks the
    run finished. Returns the summary."""
    writer.checkpoint(checkpoint)
    writer.plot_learning_curve(curve[0], list(curve[1]), title=title, ylabel=ylabel)
    for plot in extra_plots:
        plot(writer.dir)
    return writer.finish(summary)


def check_budget(episodes: int, episodes_per_iteration: int, **positive: int) -> int:
    """Every count in ``positive`` >= 1 (the error names it) and at least one iteration's
    episodes; returns the number of iterations."""
    for name, value in {**positive, "episodes_per_iteration": episodes_per_iteration}.items():
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    if episodes < episodes_per_iteration:
        raise ValueError(
            f"episodes ({episodes}) must be at least episodes_per_iteration "
            f"({episodes_per_iteration})"
        )
    return episodes // episodes_per_iteration


def infinite_horizon_postfix(row: dict[str, Any]) -> dict[str, Any]:
    """Progress-bar fields of the infinite-horizon tasks: return, KL and active options."""
    return {
        "ret": f"{row['average_return']:.1f}",
        "kl": f"{row['kl']:.2f}",
        "opts": row["n_active_options"],
    }
