"""The training loops every experiment shares, and the one ending of every run.

- :class:`Run`: the run directory of a new or resumed run, with what it must checkpoint.
- :func:`collector_loop`: a TorchRL collector hands over one batch per iteration; ``update``
  turns it into the iteration's logged fields (the policy update happens there).
- :func:`ask_tell_loop`: no environment process at all; ``step`` asks the algorithm, scores
  the samples and tells it back (the toy objectives, a real robot driven from Python).
- :func:`finish_run`: final checkpoint, learning-curve plot and ``summary.json``, in that
  order, so a directory holding ``summary.json`` is a finished run.

Every loop writes one row per iteration to the run directory, a checkpoint after every
``checkpoint_every`` iterations, and shows a tqdm progress bar. SIGINT/SIGTERM stop the loop
at the next iteration boundary with a checkpoint written (:func:`stop_on_signals`); ``--resume``
continues from it and ends exactly as the uninterrupted run would. Nothing here reads a config
object beyond the shared :class:`RunOptions`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import repeat
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from experiments.checkpoint import (
    FORMAT,
    CheckpointState,
    RunFinished,
    RunInterrupted,
    RunState,
    changed_options,
    load_checkpoint,
    read_config,
    stop_on_signals,
)
from experiments.options import RunOptions, config_dict
from experiments.rundir import RunWriter, default_run_dir

__all__ = [
    "Postfix",
    "Resume",
    "Run",
    "ask_tell_loop",
    "check_budget",
    "collector_loop",
    "finish_run",
    "infinite_horizon_postfix",
    "infinite_horizon_update",
    "resume_point",
]

Postfix = Callable[[dict[str, Any]], dict[str, Any]]
"""Maps a logged row to the progress bar's postfix fields."""


@dataclass(frozen=True)
class Resume:
    """A run to continue: its directory and its checkpoint (None: it stopped before its
    first iteration ended, so it starts over in the same directory)."""

    run_dir: Path
    checkpoint: CheckpointState | None


def resume_point(experiment: str, cfg: RunOptions) -> Resume | None:
    """Check the run options and, for ``cfg.resume``, that the run can be continued: it
    exists, has not finished (:class:`RunFinished`), and was started with the same options
    (a ``ValueError`` naming every option that differs). Call it before building anything."""
    cfg.check_run_options()
    if cfg.resume is None:
        return None
    run_dir = Path(cfg.resume)
    if not (run_dir / "config.json").is_file():
        raise ValueError(f"cannot resume {run_dir}: it holds no config.json (not a run directory)")
    if (run_dir / "summary.json").is_file():
        raise RunFinished(f"{run_dir} already finished (summary.json is there); nothing to resume")
    saved = read_config(run_dir)
    if saved.get("experiment", experiment) != experiment:
        raise ValueError(
            f"cannot resume {run_dir}: it is a {saved.get('experiment')!r} run, not {experiment!r}"
        )
    diff = changed_options(saved, config_dict(experiment, cfg))
    if diff:
        raise ValueError(
            f"cannot resume {run_dir} with other options than it was started with: "
            + "; ".join(diff)
            + " (pass no options, or the same ones, with --resume)"
        )
    logged = _logged_rows(run_dir / "metrics.csv")
    ckpt = load_checkpoint(run_dir)
    if ckpt is None:
        if logged:
            raise ValueError(
                f"cannot resume {run_dir}: its metrics.csv holds {logged} row(s) but there is "
                f"no {run_dir / 'checkpoint.pt'} to continue them from; restore the checkpoint, "
                "or move the directory away and start a new run (nothing was changed)"
            )
    else:
        theirs = ckpt.get("config")
        if not isinstance(theirs, dict) or ckpt.get("experiment") != experiment:
            raise ValueError(
                f"cannot resume {run_dir}: its checkpoint.pt is of a "
                f"{ckpt.get('experiment')!r} run, not of this {experiment!r} run (nothing was "
                "changed)"
            )
        mismatch = changed_options(theirs, saved, ("checkpoint.pt", "config.json"))
        if mismatch:
            raise ValueError(
                f"cannot resume {run_dir}: its checkpoint.pt was written by a run with other "
                "options than its config.json holds: "
                + "; ".join(mismatch)
                + " (was one of them copied or edited?); nothing was changed"
            )
    return Resume(run_dir, ckpt)


def _logged_rows(path: Path) -> int:
    """The data rows of a ``metrics.csv`` (0 if there is none); a ``ValueError`` naming it
    when it is there but not a file."""
    if path.exists() and not path.is_file():
        raise ValueError(f"{path} is not a file; move it away (nothing was changed)")
    if not path.is_file():
        return 0
    return max(sum(1 for line in path.read_bytes().splitlines() if line.strip()) - 1, 0)


class Run:
    """An open run directory (new, or reopened from a checkpoint) and the state it saves.

    Args:
        experiment: the experiment's name (``config.json``'s ``experiment``).
        cfg: the experiment's config (its :class:`RunOptions` part places the run).
        state: what the checkpoints hold; restored here from the checkpoint when resuming.
        resume: from :func:`resume_point`.
    """

    def __init__(
        self, experiment: str, cfg: RunOptions, state: RunState, resume: Resume | None
    ) -> None:
        self.experiment = experiment
        self.config = config_dict(experiment, cfg)
        self.state = state
        self.every = cfg.checkpoint_every
        ckpt = None if resume is None else resume.checkpoint
        self.start_iteration = 0
        if ckpt is not None:  # first: a checkpoint that does not fit changes no file
            state.load_state_dict(ckpt)
            self.start_iteration = int(ckpt["iteration"])
        if resume is None:
            run_dir = cfg.run_dir or default_run_dir(experiment)
            self.writer = RunWriter(run_dir, self.config, cfg.logger)
        else:
            rows = [] if ckpt is None else ckpt["rows"]
            elapsed = 0.0 if ckpt is None else float(ckpt["elapsed"])
            self.writer = RunWriter(
                resume.run_dir, self.config, cfg.logger, rows=rows, elapsed=elapsed
            )
        self._unsaved: CheckpointState | None = None

    @property
    def rows(self) -> list[dict[str, Any]]:
        return self.writer.rows

    def snapshot(self, iteration: int, finished: bool = False) -> CheckpointState:
        """The checkpoint of this iteration boundary."""
        return {
            "format": FORMAT,
            "experiment": self.experiment,
            "config": self.config,
            "iteration": iteration,
            "finished": finished,
            **self.state.state_dict(),
            "rows": [dict(r) for r in self.writer.rows],
            "elapsed": self.writer.elapsed(),
        }

    def end_iteration(self, iteration: int, force: bool = False) -> None:
        """Checkpoint now if due (or ``force``); otherwise keep the snapshot in memory so an
        error or a second interrupt before the next checkpoint can still write it."""
        snap = self.snapshot(iteration)
        if force or iteration % self.every == 0:
            self.writer.checkpoint(snap)
            self._unsaved = None
        else:
            self._unsaved = snap

    def save_unsaved(self) -> None:
        if self._unsaved is not None:
            self.writer.checkpoint(self._unsaved)
            self._unsaved = None


def _iterate(
    run: Run,
    items: Iterable[Any],
    step: Callable[[int, Any], dict[str, Any]],
    *,
    iterations: int,
    label: str,
    postfix: Postfix,
    progress: bool,
) -> None:
    """Iterations ``run.start_iteration .. iterations - 1``: ``step(it, item)`` gives the
    row; log it, checkpoint, and stop cleanly at a boundary after SIGINT/SIGTERM."""
    bar = tqdm(total=iterations, initial=run.start_iteration, desc=label, disable=not progress)
    try:
        with stop_on_signals() as stop:
            for it, item in zip(range(run.start_iteration, iterations), items, strict=False):
                row = step(it, item)
                run.writer.log(row)
                bar.update(1)
                bar.set_postfix(**postfix(row))
                run.end_iteration(it + 1, force=stop.signame is not None)
                if stop.signame is not None and it + 1 < iterations:
                    raise RunInterrupted(run.writer.dir, it + 1, stop.signame)
    except BaseException:
        try:
            run.save_unsaved()
        finally:
            run.writer.release()
        raise
    finally:
        bar.close()


def collector_loop(
    collector: Any,
    open_run: Callable[[], Run],
    update: Callable[[Any], dict[str, Any]],
    *,
    iterations: int,
    episodes_per_iteration: int,
    label: str,
    postfix: Postfix,
    sync_weights: bool = False,
    progress: bool = True,
) -> Run:
    """The training loop of every experiment that collects with TorchRL.

    Opens the run (``open_run()``; a resumed run restores its state there), then for every
    collected batch: ``update(batch)`` (the policy update; returns the iteration's logged
    fields), a weight sync to the worker processes when ``sync_weights``, one logged row
    (``iteration``, ``episodes`` and the fields), a checkpoint when due and a progress-bar
    step showing ``postfix(row)``. The collector is shut down however the loop ends (also
    when the run cannot be opened). Returns the run for :func:`finish_run`.
    """
    from hireps_torch.rollout import shutdown_collector

    try:
        run = open_run()

        def step(it: int, batch: Any) -> dict[str, Any]:
            fields = update(batch)
            if sync_weights:
                collector.update_policy_weights_()
            return {"iteration": it + 1, "episodes": (it + 1) * episodes_per_iteration, **fields}

        _iterate(
            run,
            collector,
            step,
            iterations=iterations,
            label=label,
            postfix=postfix,
            progress=progress,
        )
    finally:
        shutdown_collector(collector)
    return run


def ask_tell_loop(
    run: Run,
    step: Callable[[int], dict[str, Any]],
    *,
    iterations: int,
    label: str,
    postfix: Postfix,
    progress: bool = True,
) -> Run:
    """Rounds ``run.start_iteration .. iterations - 1`` of ``step(it)`` (ask, evaluate, tell;
    returns the logged row), one row, a checkpoint when due and one progress-bar step each.
    Returns the run for :func:`finish_run`."""
    _iterate(
        run,
        repeat(None),
        lambda it, _: step(it),
        iterations=iterations,
        label=label,
        postfix=postfix,
        progress=progress,
    )
    return run


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
    run: Run,
    *,
    curve: tuple[str, Sequence[str]],
    title: str,
    summary: Mapping[str, Any],
    ylabel: str = "return",
    extra_plots: Iterable[Callable[[Path], None]] = (),
) -> dict[str, Any]:
    """The ending of every run: the final ``checkpoint.pt`` (``finished``), the learning
    curve ``learning_curve.png`` (columns ``curve[1]`` of ``metrics.csv`` against
    ``curve[0]``), any ``extra_plots`` (each called with the run directory), then
    ``summary.json`` (plus ``wall_seconds``), which marks the run finished. Returns the
    summary."""
    writer = run.writer
    writer.checkpoint(run.snapshot(len(writer.rows), finished=True))
    writer.plot_learning_curve(curve[0], list(curve[1]), title=title, ylabel=ylabel)
    for plot in extra_plots:
        plot(writer.dir)
    return writer.finish(summary)


MAX_COUNT = 10**9
"""The largest count an experiment takes (options, episodes per iteration, ...)."""
MAX_WORKERS = 1024
"""The most worker processes a run starts."""


def check_budget(episodes: int, episodes_per_iteration: int, **positive: int) -> int:
    """Every count in ``positive`` >= 1 (the error names it) and at least one iteration's
    episodes; returns the number of iterations."""
    for name, value in {**positive, "episodes_per_iteration": episodes_per_iteration}.items():
        top = MAX_WORKERS if name == "workers" else MAX_COUNT
        if not 1 <= value <= top:
            raise ValueError(f"{name} must be in 1..{top}, got {value}")
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
