"""The training loops every experiment shares, and the one ending of every run."""

from __future__ import annotations

import ctypes
import ctypes.util
import dataclasses
import os
import statistics
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from hireps_torch.checks import NO_MEMBER_DIMENSION
from hireps_torch.experiments.checkpoint import (
    EARLIER_POPULATION,
    EARLIER_RUN,
    FORMAT,
    CheckpointState,
    RunFinished,
    RunInterrupted,
    RunState,
    changed_options,
    check_same_run,
    checkpoint_dir,
    load_checkpoint,
    no_config_note,
    read_config,
    stop_on_signals,
)
from hireps_torch.experiments.options import RunOptions, config_dict, member_seeds, parse_seeds
from hireps_torch.experiments.rundir import (
    DirectoryLock,
    RunWriter,
    default_run_dir,
    plot_learning_curves,
)

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
    "logged_rows",
    "resume_point",
]

Postfix = Callable[[dict[str, Any]], dict[str, Any]]
"""Maps a logged row to the progress bar's postfix fields."""


@dataclass(frozen=True)
class Resume:
    """A run to continue: its directory and checkpoint (None: it starts over there)."""

    run_dir: Path
    checkpoint: CheckpointState | None


def resume_point(experiment: str, cfg: RunOptions) -> Resume | None:
    """Check the run options and, for ``cfg.resume``, that the run exists, has not finished
    (:class:`RunFinished`) and has the same options; call it at the start of a run, before
    building anything. Warns (at the run's caller) where the episodes leave part of an
    iteration over."""
    cfg.check_run_options()
    per_name = "samples_per_iteration" if experiment == "bimodal" else "episodes_per_iteration"
    episodes, per = getattr(cfg, "episodes", 0), getattr(cfg, per_name, 1)
    if episodes % per:
        warnings.warn(
            f"episodes ({episodes}) is not a multiple of {per_name} ({per}): the run plays "
            f"{episodes // per} iteration(s), {episodes // per * per} episodes",
            UserWarning,
            stacklevel=3,
        )
    if cfg.resume is None:
        return None
    run_dir = Path(cfg.resume)
    if not (run_dir / "config.json").is_file():
        raise ValueError(
            f"cannot resume {run_dir}: it holds no config.json (not a run directory)."
            + no_config_note(run_dir)
            + " (nothing was changed)"
        )
    # a run still writing the directory is refused before its files are read (they may be
    # between two writes); the run's own writer takes the lock again for the whole run
    lock = DirectoryLock(run_dir)
    try:
        saved = read_config(run_dir)
        if saved.get("experiment", experiment) != experiment:
            raise ValueError(
                f"cannot resume {run_dir}: it is a {saved.get('experiment')!r} run, not "
                f"{experiment!r}"
            )
        if diff := changed_options(saved, config_dict(experiment, cfg)):
            raise ValueError(
                f"cannot resume {run_dir} with other options than it was started with: "
                + "; ".join(diff)
                + " (pass no options, or the same ones, with --resume)"
            )
        if (run_dir / "summary.json").is_file():
            raise RunFinished(
                f"{run_dir} already finished (summary.json is there); nothing to resume"
            )
        seeds = saved.get("seeds")
        dirs = [run_dir] if seeds is None else [run_dir / f"seed{s}" for s in parse_seeds(seeds)]
        if seeds is not None:
            _check_members(experiment, cfg, run_dir)
        logged = {d: logged_rows(d / "metrics.csv") for d in dirs}
        ckpt = load_checkpoint(run_dir)
        if ckpt is None and seeds is None:
            try:
                parent, member = checkpoint_dir(run_dir, saved.get("seed", 0))
            except ValueError as exc:
                raise ValueError(f"cannot resume {run_dir}: {exc} (nothing was changed)") from None
            if member is not None:
                raise ValueError(
                    f"cannot resume {run_dir}: it is a member of the population in {parent}; "
                    f"resume that directory (--resume {parent}) (nothing was changed)"
                )
        if ckpt is not None:
            try:
                check_same_run(run_dir, ckpt, saved)
            except ValueError as exc:
                raise ValueError(f"cannot resume {run_dir}: {exc}; nothing was changed") from None
        # rows without a checkpoint: its first was not due yet, or its write failed (the run
        # starts over); more rows than that: a checkpoint was there and is gone
        every = saved.get("checkpoint_every", 1)
        for d, n in logged.items():
            if ckpt is None and n > (every if isinstance(every, int) else 0):
                earlier = seeds is None and run_dir.resolve().name == f"seed{saved.get('seed')}"
                raise ValueError(
                    f"cannot resume {run_dir}: {d / 'metrics.csv'} holds {n} row(s) but there "
                    f"is no {run_dir / 'checkpoint.pt'} to continue them from; restore the "
                    "checkpoint, or move the directory away and start a new run (nothing was "
                    "changed)" + (f". If it is a member of {EARLIER_POPULATION}" if earlier else "")
                )
        if ckpt is None and any(logged.values()):
            warnings.warn(
                f"{run_dir} holds no checkpoint.pt (the run stopped before its first one was "
                f"written): the run starts over, playing the {max(logged.values())} "
                "iteration(s) in its metrics.csv again",
                UserWarning,
                stacklevel=3,
            )
        return Resume(run_dir, ckpt)
    finally:
        lock.release()


def member_configs(cfg: RunOptions, root: Path) -> list[Any]:
    """The config of each member of a population: its seed, its directory ``root/seed<s>``."""
    return [
        dataclasses.replace(cfg, seed=s, seeds=None, resume=None, run_dir=root / f"seed{s}")
        for s in member_seeds(cfg)
    ]


def _check_members(experiment: str, cfg: RunOptions, run_dir: Path) -> None:
    """The member directories of a population to resume are its own directories, and their
    ``config.json`` (where present; a missing one is written again) are the population's
    with their seeds: a ``ValueError`` naming the first that is not."""
    for member in member_configs(cfg, run_dir):
        d = Path(member.run_dir)
        if d.is_symlink() or (d.exists() and not d.is_dir()):
            what = f"a link to {os.readlink(d)}" if d.is_symlink() else "not a directory"
            raise ValueError(
                f"cannot resume {run_dir}: its member directory {d} is {what}; a member's files "
                "are written there, so move it away (it is rebuilt from the checkpoint); "
                "nothing was changed"
            )
        config = d / "config.json"
        if not config.exists():
            continue
        try:
            if not config.is_file():
                raise ValueError(f"{config} is not a file")
            diff = changed_options(
                read_config(d), config_dict(experiment, member), ("config.json", "population")
            )
            if diff:
                raise ValueError(f"{config} is not its member's config: " + "; ".join(diff))
        except ValueError as exc:
            raise ValueError(
                f"cannot resume {run_dir}: {exc} (restore it, or delete it to have it written "
                "again); nothing was changed"
            ) from None


def logged_rows(path: Path) -> int:
    """The data rows of a ``metrics.csv`` (0 if absent; a ``ValueError`` if not a text file)."""
    if path.exists() and not path.is_file():
        raise ValueError(f"{path} is not a file; move it away (nothing was changed)")
    if not path.is_file():
        return 0
    try:
        text = path.read_bytes().decode()
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{path} is not text ({exc}); move it away (nothing was changed)"
        ) from None
    return max(sum(1 for line in text.splitlines() if line.strip()) - 1, 0)


class Run:
    """An open run (new, or reopened from a checkpoint): its members' writers and its state.
    Every run is a population of S >= 1 seeds (``seeds``; ``population``: ``--seeds`` was
    given, even of one seed); ``configs`` holds each member's config (its seed and run
    directory, member s of a population in ``seed<s>``, no ``seeds``).

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
        root = Path(
            resume.run_dir
            if resume is not None
            else cfg.run_dir
            if cfg.run_dir is not None
            else default_run_dir(experiment)
        )
        self.seeds, self.population = member_seeds(cfg), cfg.seeds is not None
        self.progress = cfg.progress
        self.configs: list[Any] = [dataclasses.replace(cfg, run_dir=root)]
        if self.population:
            self.configs = member_configs(cfg, root)
        self.state = state
        self.every = cfg.checkpoint_every
        ckpt = None if resume is None else resume.checkpoint
        self.threads = torch.get_num_threads()  # as the run computes (after collector workers)
        self.start_iteration = 0
        if ckpt is not None:  # first: a checkpoint that does not fit changes no file
            if len(ckpt["rows"]) != len(self.seeds):
                raise ValueError(
                    f"{root / 'checkpoint.pt'} holds {len(ckpt['rows'])} member(s), "
                    f"this run {len(self.seeds)}; nothing was changed"
                )
            try:
                state.load_state_dict(ckpt)
            except ValueError as exc:
                earlier = NO_MEMBER_DIMENSION in str(exc)  # an ordinary hockey run's, before
                raise ValueError(
                    f"cannot resume {root}: {exc}"
                    + (
                        f"; an earlier version of this code wrote it: {EARLIER_RUN}"
                        if earlier
                        else ""
                    )
                    + "; nothing was changed"
                ) from None
            self.start_iteration = int(ckpt["iteration"])
            threads = ckpt.get("threads", self.threads)  # format 2: not recorded
            if threads != self.threads:
                warnings.warn(
                    f"{root / 'checkpoint.pt'} was written while torch computed with {threads} "
                    f"thread(s), this run computes with {self.threads}: it goes on as a run of "
                    "its seed, but not bit for bit as it would have (round-off moves with the "
                    "threads); resume it with the thread count it was started with "
                    "(OMP_NUM_THREADS) to continue it exactly",
                    UserWarning,
                    stacklevel=2,
                )
        rows: list[Any] = [None] * len(self.seeds)  # None: a new run
        if resume is not None:
            rows = [[] for _ in self.seeds] if ckpt is None else ckpt["rows"]
        elapsed = 0.0 if ckpt is None else float(ckpt["elapsed"])
        pop = self.population
        first = rows[0] if not pop else None if resume is None else []
        self.root = RunWriter(
            root, self.config, "csv" if pop else cfg.logger, rows=first, elapsed=elapsed
        )
        self.writers = [self.root]
        if pop:
            try:
                self.writers = [
                    RunWriter(
                        c.run_dir, config_dict(experiment, c), c.logger, rows=r, elapsed=elapsed
                    )
                    for c, r in zip(self.configs, rows, strict=True)
                ]
            except BaseException:
                self.release()
                raise
        self._unsaved: CheckpointState | None = None

    @property
    def rows(self) -> list[list[dict[str, Any]]]:
        """Each member's rows so far."""
        return [w.rows for w in self.writers]

    def log(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """One row per member, in the order of the seeds."""
        for writer, row in zip(self.writers, rows, strict=True):
            writer.log(row)

    def release(self) -> None:
        """Every writer of the run writes no more (their locks dropped)."""
        for writer in {id(w): w for w in [*getattr(self, "writers", []), self.root]}.values():
            writer.release()

    def snapshot(self, iteration: int, finished: bool = False) -> CheckpointState:
        """The checkpoint of this iteration boundary."""
        return {
            "format": FORMAT,
            "experiment": self.experiment,
            "config": self.config,
            "iteration": iteration,
            "finished": finished,
            **self.state.state_dict(),
            "rows": [w.csv_text() for w in self.writers],  # a str pickles at copy speed
            "elapsed": self.root.elapsed(),
            "threads": self.threads,  # round-off moves with them
        }

    def end_iteration(self, iteration: int, force: bool = False) -> None:
        """Checkpoint now if due (or ``force``), else keep the snapshot for :meth:`save_unsaved`."""
        snap = self.snapshot(iteration)
        if force or iteration % self.every == 0:
            self.root.checkpoint(snap)
            self._unsaved = None
        else:
            self._unsaved = snap

    def save_unsaved(self) -> None:
        if self._unsaved is not None:
            self.root.checkpoint(self._unsaved)
            self._unsaved = None


def keep_freed_memory(pad: int = 1 << 30) -> bool:
    """Have glibc's ``malloc`` keep up to ``pad`` bytes of freed heap (``mallopt(M_TOP_PAD)``,
    process-wide; glibc's default is 128 KiB); returns whether it was set (why:
    benchmarks/README.md, "population.py"). With ``pad`` 0 or less: the default again, and the
    kept heap handed back (``malloc_trim``)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        done = bool(libc.mallopt(-2, pad if pad > 0 else 128 * 1024))  # M_TOP_PAD
        if done and pad <= 0:
            libc.malloc_trim(0)
        return done
    except (OSError, AttributeError, TypeError):
        return False


def _mean_row(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The members' rows as one: the mean of each number (the row itself for one member)."""
    if len(rows) == 1:
        return dict(rows[0])
    out = dict(rows[0])
    for key, value in rows[0].items():
        if isinstance(value, int | float) and not isinstance(value, bool):
            out[key] = statistics.fmean(float(r[key]) for r in rows)
    return out


def collector_loop(
    collector: Any,
    open_run: Callable[[], Run],
    update: Callable[[Any], list[dict[str, Any]]],
    *,
    iterations: int,
    episodes_per_iteration: int,
    label: str,
    postfix: Postfix,
    sync_weights: bool = False,
    progress: bool = True,
) -> Run:
    """The loop of every experiment that collects with TorchRL: ``open_run()``, then per batch
    ``update(batch)`` (the policy update; one dict of logged fields per member), a weight sync
    when ``sync_weights``, one row per member (``iteration``, ``episodes``, the fields) and a
    checkpoint when due. The collector is shut down however the loop ends. Returns the run
    for :func:`finish_run`."""
    from hireps_torch.rollout import shutdown_collector

    try:
        run = open_run()
        batches = iter(collector)

        def step(it: int) -> list[dict[str, Any]]:
            members = update(next(batches))
            if sync_weights:
                collector.update_policy_weights_()
            count = {"iteration": it + 1, "episodes": (it + 1) * episodes_per_iteration}
            return [count | fields for fields in members]

        ask_tell_loop(
            run, step, iterations=iterations, label=label, postfix=postfix, progress=progress
        )
    finally:
        shutdown_collector(collector)
    return run


def ask_tell_loop(
    run: Run,
    step: Callable[[int], list[dict[str, Any]]],
    *,
    iterations: int,
    label: str,
    postfix: Postfix,
    progress: bool = True,
) -> Run:
    """Rounds of ``step(it)`` (ask, evaluate, tell: one row per member) from the run's start
    iteration: log, checkpoint, stop on signals; returns the run."""
    S = len(run.writers)
    if S > 1:
        label = f"{label}/{S} seeds"
    keep_freed_memory()
    bar = tqdm(total=iterations, initial=run.start_iteration, desc=label, disable=not progress)
    try:
        with stop_on_signals() as stop:
            for it in range(run.start_iteration, iterations):
                rows = step(it)
                run.log(rows)
                bar.update(1)
                bar.set_postfix(**postfix(_mean_row(rows)))
                run.end_iteration(it + 1, force=stop.signame is not None)
                if stop.signame is not None and it + 1 < iterations:
                    raise RunInterrupted(run.root.dir, it + 1, stop.signame)
    except BaseException:
        try:
            run.save_unsaved()
        finally:
            run.release()
        raise
    finally:
        bar.close()
        keep_freed_memory(0)  # the process goes on (a notebook, a sweep): its heap back
    return run


def infinite_horizon_update(
    algo: Any,
    row: Callable[[torch.Tensor, torch.Tensor], list[dict[str, Any]]],
    augment: Callable[..., tuple[torch.Tensor, ...]] | None = None,
) -> Callable[[Any], list[dict[str, Any]]]:
    """The per-batch step of the pendulum and the beam: one ``algo.update`` of all members on
    the batch's decisions (through ``augment(s, a, r, s', terminated)`` when given), then each
    member's ``row(rewards, terminated)`` fields (both (S, B T)) and update diagnostics."""
    from hireps_torch.rollout import transitions

    def update(batch: Any) -> list[dict[str, Any]]:
        S = algo.population
        s, a, r, s_next, _ = transitions(batch, "state")
        terminated = batch["next", "terminated"].reshape(-1)
        data = tuple(x.reshape(S, -1, *x.shape[1:]) for x in (s, a, r, s_next, terminated))
        diag = algo.update(*(augment(*data) if augment is not None else data))
        return [
            fields | {key: value[m] for key, value in diag.items()}
            for m, fields in enumerate(row(data[2], data[4]))
        ]

    return update


def finish_run(
    run: Run,
    *,
    curve: tuple[str, Sequence[str]],
    title: str,
    summaries: Sequence[Mapping[str, Any]],
    ylabel: str = "return",
) -> dict[str, Any]:
    """The ending of every run: the final checkpoint; per member ``learning_curve.png``
    (``curve[1]`` against ``curve[0]``) and ``summary.json`` (plus ``wall_seconds``); for a
    population also the members' table, band plot and summary. Returns the summary (of the
    member, or of the population)."""
    run.root.checkpoint(run.snapshot(len(run.writers[0].rows), finished=True))
    plot_learning_curves(run.writers, curve[0], list(curve[1]), title=title, ylabel=ylabel)
    written = [writer.finish(s) for writer, s in zip(run.writers, summaries, strict=True)]
    return _population_summary(run, written) if run.population else written[0]


def _population_summary(run: Run, summaries: list[dict[str, Any]]) -> dict[str, Any]:
    """The members' ``population.*`` files (as a sweep writes them), then its summary."""
    from hireps_torch.experiments.sweep import METRICS, SweepRun, summarize

    experiment, seeds, root = run.experiment.replace("_", "-"), run.seeds, run.root.dir
    runs = [SweepRun(experiment, experiment, s, {}, root / f"seed{s}") for s in seeds]
    results = {(experiment, s): summary for s, summary in zip(seeds, summaries, strict=True)}
    table = summarize(runs, results, root, stem="population", seconds="s (population)")
    if run.progress:  # the members' table, where a bar showed the run
        print(table)
    metric = METRICS[experiment][0]
    values = [float(s[metric]) for s in summaries]
    return run.root.finish(
        {
            "experiment": experiment,
            "seeds": seeds,
            "metric": metric,
            "mean": statistics.fmean(values),
            "std": statistics.stdev(values) if len(values) > 1 else 0.0,
            "per_seed": dict(zip(map(str, seeds), values, strict=True)),
            "run_dir": str(root),
            "summary": str(root / "population.md"),
            "plot": str(root / "population.png"),
        }
    )


MAX_COUNT = 10**9
"""The largest count an experiment takes (options, episodes per iteration, ...)."""
MAX_WORKERS = 1024
"""The most worker processes a run starts."""


def check_budget(
    episodes: int,
    per_iteration: int,
    per_name: str = "episodes_per_iteration",
    least: int = 1,
    **positive: int,
) -> int:
    """Every count in 1..its top (``per_iteration``, named ``per_name``, from ``least``) and at
    least one iteration's episodes; returns the iterations (episodes // per_iteration)."""
    counts = {**positive, per_name: per_iteration, "episodes": episodes}
    for name, value in counts.items():
        low, top = least if name == per_name else 1, MAX_WORKERS if name == "workers" else MAX_COUNT
        if not low <= value <= top:
            raise ValueError(f"{name} must be in {low}..{top}, got {value}")
    if episodes < per_iteration:
        raise ValueError(f"episodes ({episodes}) must be at least {per_name} ({per_iteration})")
    return episodes // per_iteration


def infinite_horizon_postfix(row: dict[str, Any]) -> dict[str, Any]:
    """Progress-bar fields of the infinite-horizon tasks: return, KL and active options."""
    return {
        "ret": f"{row['average_return']:.1f}",
        "kl": f"{row['kl']:.2f}",
        "opts": row["n_active_options"],
    }
