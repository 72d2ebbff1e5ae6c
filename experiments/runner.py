"""The run library every experiment's loop uses: its registry entry (:class:`Experiment`),
:func:`resume_point` (the run options and a resume checked before anything is built) and
:class:`Run` (the run directories, iterations with checkpoints and signals, rows, the end)."""

from __future__ import annotations

import ctypes
import ctypes.util
import dataclasses
import os
import statistics
import warnings
from collections.abc import Callable, Generator, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from hireps_torch.experiments.checkpoint import (
    FORMAT,
    CheckpointState,
    RunFinished,
    RunInterrupted,
    RunState,
    changed_options,
    check_same_run,
    checkpoint_dir,
    load_checkpoint,
    read_config,
    stop_on_signals,
)
from hireps_torch.experiments.migrations import (
    EARLIER_POPULATION,
    earlier_version_note,
    no_config_note,
)
from hireps_torch.experiments.options import RunOptions, config_dict, member_seeds, parse_seeds
from hireps_torch.experiments.report import Member, summarize
from hireps_torch.experiments.rundir import (
    DirectoryLock,
    RunWriter,
    default_run_dir,
    plot_learning_curves,
)

__all__ = [
    "Experiment",
    "Postfix",
    "Resume",
    "Run",
    "check_budget",
    "infinite_horizon_postfix",
    "keep_freed_memory",
    "logged_rows",
    "resume_point",
]

Postfix = Callable[[dict[str, Any]], dict[str, Any]]
"""Maps a logged row (the members' mean) to the progress bar's postfix fields."""


@dataclass(frozen=True)
class Experiment:
    """One registry entry: an experiment's command-line name (also ``config.json``'s
    ``experiment``), its config class, ``run(cfg) -> summary``, ``algorithm(cfg)`` (the config
    checked and the untrained algorithm, writing nothing), the summary's final ``metric``, the
    ``metrics.csv`` column its population and sweep bands show (``curve``; ``curves``: those of
    each run's learning curve, default ``(curve,)``), the option that counts episodes per
    iteration, the options that may change between a run and its resumption besides
    :data:`~hireps_torch.experiments.checkpoint.RUN_ONLY_OPTIONS`."""

    name: str
    config: type
    run: Callable[[Any], dict[str, Any]]
    algorithm: Callable[[Any], Any]
    metric: str
    curve: str
    curves: tuple[str, ...] = ()
    per_iteration: str = "episodes_per_iteration"
    run_only: tuple[str, ...] = ()

    @property
    def plotted(self) -> tuple[str, ...]:
        return self.curves or (self.curve,)


@dataclass(frozen=True)
class Resume:
    """A run to continue: its directory and checkpoint (None: it starts over there)."""

    run_dir: Path
    checkpoint: CheckpointState | None


def resume_point(entry: Experiment, cfg: RunOptions) -> Resume | None:
    """Check the run options and, for ``cfg.resume``, that the run exists, has not finished
    (:class:`RunFinished`) and has the same options; call it at the start of a run, before
    building anything. Warns (at the run's caller) where the episodes leave part of an
    iteration over."""
    cfg.check_run_options()
    per_name, run_only, experiment = entry.per_iteration, entry.run_only, entry.name
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
        if diff := changed_options(saved, config_dict(experiment, cfg), run_only=run_only):
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
            _check_members(experiment, cfg, run_dir, run_only)
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
                check_same_run(run_dir, ckpt, saved, run_only)
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


def _check_members(
    experiment: str, cfg: RunOptions, run_dir: Path, run_only: tuple[str, ...]
) -> None:
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
                read_config(d),
                config_dict(experiment, member),
                ("config.json", "population"),
                run_only,
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
    """An open run (new, or reopened from a checkpoint) that an experiment's loop drives::

        resume = resume_point(EXPERIMENT, cfg)  # first: refuses before anything is built
        ...  # build the task, the algorithm, the collector
        with Run(EXPERIMENT, cfg, RunState(algo), resume) as run:
            for it in run.iterations(n, label):  # from the checkpoint's iteration on
                ...  # collect, update, evaluate
                run.log(rows)  # one row per member
            return run.finish(summaries, title=label)

    :meth:`iterations` writes the checkpoint when due and, after a SIGINT/SIGTERM, at the next
    iteration boundary, then raises :class:`RunInterrupted`; leaving the ``with`` block by an
    error writes the last iteration's checkpoint if it was not due yet, and releases the run
    directories. Every run is a population of S >= 1 seeds (``seeds``; ``population``:
    ``--seeds`` was given, even of one seed); ``configs`` holds each member's config (its seed
    and run directory, member s of a population in ``seed<s>``, no ``seeds``).

    Args:
        experiment: the experiment's registry entry.
        cfg: the experiment's config (its :class:`RunOptions` part places the run).
        state: what the checkpoints hold; restored here from the checkpoint when resuming.
        resume: from :func:`resume_point`.
    """

    def __init__(
        self, entry: Experiment, cfg: RunOptions, state: RunState, resume: Resume | None
    ) -> None:
        self.entry = entry
        self.experiment = experiment = entry.name
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
                raise ValueError(
                    f"cannot resume {root}: {exc}{earlier_version_note(exc)}; nothing was changed"
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
        self._loop: Generator[int, None, None] | None = None

    def __enter__(self) -> Run:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: Any) -> None:
        if self._loop is not None:
            self._loop.close()  # its progress bar and signal handlers
        try:
            if kind is not None:
                self.save_unsaved()
        finally:
            self.release()

    def iterations(self, total: int, label: str, postfix: Postfix | None = None) -> Iterator[int]:
        """The iterations left, ``start_iteration`` .. ``total - 1``, with a progress bar
        (``postfix`` of the members' mean row); after each, the checkpoint when due; a first
        SIGINT/SIGTERM stops the loop at the next boundary with :class:`RunInterrupted`."""
        self._loop = self._iterations(total, label, postfix)
        return self._loop

    def _iterations(
        self, total: int, label: str, postfix: Postfix | None
    ) -> Generator[int, None, None]:
        S = len(self.writers)
        label = f"{label}/{S} seeds" if S > 1 else label
        keep_freed_memory()
        bar = tqdm(total=total, initial=self.start_iteration, desc=label, disable=not self.progress)
        try:
            with stop_on_signals() as stop:
                for it in range(self.start_iteration, total):
                    yield it
                    if len(self.writers[0].rows) != it + 1:
                        raise RuntimeError(f"iteration {it + 1} logged no rows (call run.log)")
                    bar.update(1)
                    if postfix is not None:
                        bar.set_postfix(**postfix(_mean_row([w.rows[-1] for w in self.writers])))
                    self.end_iteration(it + 1, force=stop.signame is not None)
                    if stop.signame is not None and it + 1 < total:
                        raise RunInterrupted(self.root.dir, it + 1, stop.signame)
        finally:
            bar.close()
            keep_freed_memory(0)  # the process goes on (a notebook, a sweep): its heap back

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

    def finish(
        self, summaries: Sequence[Mapping[str, Any]], *, title: str, ylabel: str = "return"
    ) -> dict[str, Any]:
        """The ending of every run: the final checkpoint; per member ``learning_curve.png``
        (the entry's ``curves`` against episodes) and ``summary.json`` (plus
        ``wall_seconds``); for a population also the members' table, band plot and summary.
        Returns the summary (of the member, or of the population)."""
        self.root.checkpoint(self.snapshot(len(self.writers[0].rows), finished=True))
        self._unsaved = None
        curves = list(self.entry.plotted)
        plot_learning_curves(self.writers, "episodes", curves, title=title, ylabel=ylabel)
        written = [w.finish(s) for w, s in zip(self.writers, summaries, strict=True)]
        if not self.population:
            return written[0]
        root, metric = self.root.dir, self.entry.metric
        name = self.experiment
        members = [Member(name, name, s, root / f"seed{s}") for s in self.seeds]
        results = {(self.experiment, s): w for s, w in zip(self.seeds, written, strict=True)}
        table = summarize(
            members, results, root, metric, self.entry.curve, "population", "s (population)"
        )
        if self.progress:  # the members' table, where a bar showed the run
            print(table)
        values = [float(w[metric]) for w in written]
        return self.root.finish(
            {
                "experiment": self.experiment,
                "seeds": self.seeds,
                "metric": metric,
                "mean": statistics.fmean(values),
                "std": statistics.stdev(values) if len(values) > 1 else 0.0,
                "per_seed": dict(zip(map(str, self.seeds), values, strict=True)),
                "run_dir": str(root),
                "summary": str(root / "population.md"),
                "plot": str(root / "population.png"),
            }
        )


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
