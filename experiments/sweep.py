"""Sweeps: a grid of configurations x seeds, each run an ordinary run directory::

    hireps-train sweep --experiment pendulum --seeds 0-4 \\
        --grid n_options=1,2,5 --grid steps_per_decision=1,5 --set episodes=200 \\
        --out runs/sweep --backend ray --workers 2

Each (configuration, seed) runs in ``OUT/<experiment>/<configuration>/seed<S>``, or, with
``--members M``, each configuration's seeds run as populations of at most M members
(``train.py --seeds``), each in ``OUT/<experiment>/<configuration>/seeds0-9`` (its seeds);
finished runs are reused and interrupted ones resumed. Each local worker process starts once,
keeps to cores of its own and takes runs one after the other. At the end: ``sweep.md`` (table),
``sweep.json`` (summaries) and ``sweep.png`` (mean +- std curves) of this command's runs, per
seed (a later sweep into the same ``OUT`` rewrites them and keeps every run directory).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import itertools
import json
import signal
import typing
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import torch
import tyro
from tqdm.auto import tqdm

from hireps_torch.experiments import EXPERIMENTS
from hireps_torch.experiments.checkpoint import (
    changed_options,
    read_config,
    saved_config,
)
from hireps_torch.experiments.options import config_dict, parse_seeds
from hireps_torch.experiments.pool import LocalPool
from hireps_torch.experiments.report import summarize
from hireps_torch.experiments.rundir import DirectoryLock
from hireps_torch.experiments.workers import MAX_RETRIES, RAY_ENV, Backend, check_pool, start_ray
from hireps_torch.rollout import signal_handled

__all__ = [
    "SweepConfig",
    "SweepFailed",
    "SweepRun",
    "check_configurations",
    "check_same_options",
    "main",
    "parse_grid",
    "parse_seeds",
    "plan",
    "run_one",
    "run_sweep",
]

RUN_OPTIONS = {"seed", "seeds", "run_dir", "resume", "progress"}
"""Options a sweep sets itself (not allowed in --grid or --set)."""


@dataclass(frozen=True)
class SweepConfig:
    """A grid of configurations x seeds of one experiment, on local processes or Ray."""

    experiment: str = "bimodal"
    """The experiment (a train.py subcommand such as pendulum or hockey-sequential)."""
    seeds: str = "0-4"
    """Seeds: a range 0-4, a list 0,3,7, or both 0-2,9."""
    grid: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """OPTION=V1,V2,... (repeat --grid for more options): every combination is a configuration."""
    set: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """OPTION=VALUE (repeat --set for more options): fixed for every configuration."""
    out: Path = Path("runs/sweep")
    """Where the runs and the summary go (runs already there are reused or resumed)."""
    backend: Backend = "local"
    """local: this process (--workers 1) or spawned processes; ray: one Ray task per run."""
    workers: int = 1
    """Runs at the same time (CPUs of the local Ray instance with --backend ray)."""
    members: int = 1
    """Seeds per run: above 1, each configuration's seeds as populations of at most this many."""
    ray_address: str | None = None
    """An existing Ray cluster (HOST:PORT, ray://HOST:PORT or auto) for --backend ray."""
    progress: bool = True
    """Show a progress bar over the runs."""


@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: configuration ``name`` of ``experiment`` with ``options``; with
    ``seeds``, a population of those seeds (``seed`` the first) whose members write
    ``run_dir/seed<s>``."""

    experiment: str
    name: str
    seed: int
    options: dict[str, Any] = field(default_factory=dict)
    run_dir: Path = Path()
    seeds: tuple[int, ...] = ()

    def members(self) -> list[SweepRun]:
        """A population's members as ordinary runs in their own directories; else ``[self]``."""
        if not self.seeds:
            return [self]
        return [
            dataclasses.replace(self, seed=s, run_dir=Path(self.run_dir) / f"seed{s}", seeds=())
            for s in self.seeds
        ]

    def config(self, config_cls: type, **run_options: Any) -> Any:
        """The run's config: its options, seed(s) and ``run_options``."""
        seeds = {"seeds": seeds_text(self.seeds)} if self.seeds else {"seed": self.seed}
        return config_cls(**self.options, **seeds, **run_options)


def seeds_text(seeds: Sequence[int]) -> str:
    """Seeds sorted, as ``--seeds`` ranges: (9, 0, 1, 2, 5) -> ``"0-2,5,9"``."""
    ordered = sorted(seeds)
    spans = [
        [s for _, s in g] for _, g in itertools.groupby(enumerate(ordered), lambda p: p[1] - p[0])
    ]
    return ",".join(str(a[0]) if len(a) == 1 else f"{a[0]}-{a[-1]}" for a in spans)


def _population_dir(seeds: Sequence[int]) -> str:
    """``seeds<text>`` (:func:`seeds_text`), or for a long text its first and last seed and a
    hash of it: one name per set of seeds."""
    text = seeds_text(seeds)
    if len(text) <= 64:
        return f"seeds{text}"
    return f"seeds{min(seeds)}-{max(seeds)}_{hashlib.sha1(text.encode()).hexdigest()[:12]}"


def _config_class(experiment: str) -> type:
    if experiment not in EXPERIMENTS:
        raise ValueError(
            f"unknown experiment {experiment!r}; choose one of {', '.join(EXPERIMENTS)}"
        )
    return EXPERIMENTS[experiment].config


def _split(entry: str, what: str) -> tuple[str, str]:
    key, sep, value = entry.partition("=")
    key = key.strip().replace("-", "_")
    if not sep or not key or not value:
        raise ValueError(f"--{what} entries must look like OPTION=VALUE, got {entry!r}")
    return key, value


def _typed(config_cls: type, assignments: Mapping[str, str]) -> dict[str, Any]:
    """Option strings -> typed values, parsed by tyro as ``train.py <experiment>`` does."""

    fields = {f.name for f in dataclasses.fields(config_cls)}
    for key in assignments:
        if key in RUN_OPTIONS:
            raise ValueError(f"a sweep sets {key!r} itself; it cannot be in --grid or --set")
        if key not in fields:
            raise ValueError(
                f"{config_cls.__name__} has no option {key!r}; options: "
                + ", ".join(sorted(fields - RUN_OPTIONS))
            )
    hints = typing.get_type_hints(config_cls)
    args = []
    for key, value in assignments.items():
        flag = key.replace("_", "-")
        if hints.get(key) is bool:  # tyro takes booleans as --flag / --no-flag
            truth = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}
            if value.strip().lower() not in truth:
                raise ValueError(f"option {key!r} is true or false, got {value!r}")
            args.append(f"--{flag}" if truth[value.strip().lower()] else f"--no-{flag}")
        else:
            args.append(f"--{flag}={value}")
    said = io.StringIO()  # tyro prints its error box even without console outputs
    try:
        with contextlib.redirect_stderr(said), contextlib.redirect_stdout(said):
            cfg: Any = tyro.cli(config_cls, args=args, console_outputs=False)
    except SystemExit:
        raise ValueError(
            f"bad option value for {config_cls.__name__}: {_why(said.getvalue(), hints, args)}"
        ) from None
    return {key: getattr(cfg, key) for key in assignments}


def _why(said: str, hints: Mapping[str, Any], args: Sequence[str]) -> str:
    """What tyro's error text ``said`` (one paragraph after "Error parsing ") says, or the
    choices of a Literal option, or the arguments."""
    lines = [line.strip(" │") for line in said.splitlines()]
    start = next((i for i, line in enumerate(lines) if line.startswith("Error parsing ")), None)
    if start is not None:
        para = itertools.takewhile(lambda line: line and set(line) - set("─-"), lines[start:])
        return " ".join(para).removeprefix("Error parsing ")
    for arg in args:
        flag, _, value = arg.partition("=")
        hint = hints.get(flag.removeprefix("--").replace("-", "_"))
        choices = [str(c) for c in typing.get_args(hint)]
        if typing.get_origin(hint) is typing.Literal and value not in choices:
            return f"{flag} is one of {', '.join(choices)}, got {value!r}"
    return " ".join(args)


def _value_text(value: Any) -> str:
    """An option's parsed value as a configuration's name shows it."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def parse_grid(
    experiment: str, grid: Sequence[str] = (), fixed: Sequence[str] = ()
) -> dict[str, dict[str, Any]]:
    """Configurations of a grid: name -> typed options. ``grid`` entries ``OPTION=V1,V2``,
    ``fixed`` entries ``OPTION=VALUE``; bad options and values are a ValueError naming them."""
    config_cls = _config_class(experiment)
    fixed_list = [_split(e, "set") for e in fixed]
    fixed_pairs = dict(fixed_list)
    if len(fixed_pairs) != len(fixed_list):
        raise ValueError(f"an option appears twice in --set: {list(fixed)}")
    axes: dict[str, list[str]] = {}
    for entry in grid:
        key, values = _split(entry, "grid")
        if key in axes or key in fixed_pairs:
            raise ValueError(f"option {key!r} appears twice in --grid / --set")
        axes[key] = [v.strip() for v in values.split(",")]
        if len(set(axes[key])) != len(axes[key]) or "" in axes[key]:
            raise ValueError(f"--grid {entry!r}: values must be distinct and non-empty")
    for key, strings in axes.items():  # equal after parsing (0.1 and 1e-1): one configuration
        typed = [repr(_typed(config_cls, {key: v})[key]) for v in strings]
        if len(set(typed)) != len(typed):
            raise ValueError(f"--grid {key}: values {strings} name the same value twice")
    configs: dict[str, dict[str, Any]] = {}
    for combo in itertools.product(*axes.values()):
        chosen = dict(zip(axes, combo, strict=True))
        # the name: sorted keys, so that the order of --grid options does not rename runs
        options = _typed(config_cls, {**fixed_pairs, **chosen})
        # named by the parsed values (1e-1 and 0.1, ١ and 1: one name), sorted keys, so that
        # neither the spelling nor the order of --grid options renames runs
        name = ",".join(f"{k}={_value_text(options[k])}" for k in sorted(chosen)) or "default"
        configs[name] = options
    return configs


def plan(
    experiment: str,
    configurations: Mapping[str, Mapping[str, Any]],
    seeds: Sequence[int],
    out: Path,
    members: int = 1,
) -> list[SweepRun]:
    """Every (configuration, seed) as a :class:`SweepRun` in ``out/<experiment>/<name>/seed<S>``;
    for ``members`` > 1 each configuration's seeds, in the order given, as populations of at
    most ``members`` (sizes as equal as can be), each in ``out/<experiment>/<name>/seeds<...>``
    named by its seeds (:func:`seeds_text`: ``seeds0-4``, ``seeds3,5-6``)."""
    _config_class(experiment)
    if not seeds:
        raise ValueError("a sweep needs at least one seed")
    if isinstance(members, bool) or not isinstance(members, int) or members < 1:
        raise ValueError(f"members must be an integer >= 1, got {members!r}")
    n = -(-len(seeds) // members)  # runs per configuration
    cuts = [round(i * len(seeds) / n) for i in range(n + 1)]
    groups = [sorted(int(s) for s in seeds[a:b]) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    one = members == 1
    return [
        SweepRun(
            experiment,
            name,
            g[0],
            dict(opts),
            Path(out) / experiment / name / (f"seed{g[0]}" if one else _population_dir(g)),
            () if one else tuple(g),
        )
        for name, opts in configurations.items()
        for g in groups
    ]


def run_one(run: SweepRun) -> dict[str, Any]:
    """Run, resume or reuse one run of a sweep; returns its ``summary.json`` (plus
    ``"reused": True`` when it had finished before)."""
    entry = EXPERIMENTS[run.experiment]
    config_cls = entry.config
    d = Path(run.run_dir)
    cfg = run.config(config_cls, run_dir=d, progress=False)
    if (d / "config.json").is_file():
        check_same_options(run, cfg)
        if (d / "summary.json").is_file():
            for m in run.members() if run.seeds else []:  # each member's own config too
                check_same_options(m, m.config(config_cls, run_dir=m.run_dir, progress=False))
            return {**_finished_summary(run), "reused": True}
        # interrupted: continue from its checkpoint
        cfg = dataclasses.replace(
            saved_config(config_cls, run.experiment, d), progress=False, run_dir=d, resume=d
        )
    elif d.exists() and any(d.iterdir()):
        raise FileExistsError(
            f"sweep run directory {d} holds files but no config.json (a run stopped before it "
            "started, or something else was written there); delete it and run the sweep again"
        )
    return entry.run(cfg)


class DamagedSummary(ValueError):
    """A finished run's ``summary.json`` that cannot be read back, or its missing
    ``metrics.csv``."""


def _finished_summary(run: SweepRun, population: Path | None = None) -> dict[str, Any]:
    """A finished run's ``summary.json`` holding its metric (a population's: its members' do),
    else a :class:`DamagedSummary` (for a member of the ``population`` in that directory)."""
    for member in run.members() if run.seeds else []:
        _finished_summary(member, Path(run.run_dir))
    path = Path(run.run_dir) / "summary.json"
    metric = EXPERIMENTS[run.experiment].metric
    redo = (
        None
        if population is None
        else f"move {population / 'summary.json'} away: the population then writes it again"
    )
    try:
        summary = json.loads(path.read_text())
        if not isinstance(summary, dict):
            raise ValueError(f"it holds a JSON {type(summary).__name__}")
        if not run.seeds and metric not in summary:  # a population's members hold it
            raise ValueError(f"it has no {metric!r}")
        if not run.seeds and summary[metric] is not None:  # None: NaN in summary.json
            float(summary[metric])
    except (OSError, UnicodeDecodeError, ValueError, TypeError) as exc:
        again = redo or "move it away to run it again"
        raise DamagedSummary(f"{path} is damaged ({exc}); {again}") from None
    if not run.seeds and not (path.parent / "metrics.csv").is_file():  # the curves read it
        again = redo or "restore it, or move the run directory away to run it again"
        raise DamagedSummary(f"{path.parent} finished but its metrics.csv is missing; {again}")
    return summary


def check_same_options(run: SweepRun, cfg: Any) -> None:
    """A ValueError naming every option in which the run already in ``run.run_dir`` differs
    from the one the sweep asks for (e.g. another ``--set``): nothing is reused or mixed."""
    saved = read_config(Path(run.run_dir))
    now = config_dict(str(saved.get("experiment", run.experiment)), cfg)
    if diff := changed_options(saved, now, run_only=EXPERIMENTS[run.experiment].run_only):
        raise ValueError(
            f"{run.run_dir} holds a run with other options than this sweep asks for: "
            + "; ".join(diff)
            + " (use another --out, or the same options)"
        )


def check_configurations(runs: Sequence[SweepRun]) -> None:
    """Every configuration of ``runs`` checked as its run would check it (with its first
    seed), before any run starts: a ``ValueError`` naming each bad configuration and why."""
    errors, seen = [], set()
    for run in runs:
        if run.name in seen:
            continue
        seen.add(run.name)
        config_cls = _config_class(run.experiment)
        try:
            with torch.random.fork_rng(devices=[]):  # a check draws nothing a run would see
                cfg = run.config(config_cls, progress=False)
                cfg.check_run_options()
                EXPERIMENTS[run.experiment].algorithm(cfg)
        except (ValueError, TypeError, ImportError) as exc:
            errors.append(f"configuration {run.name} (seed {run.seed}): {exc}")
    if errors:
        raise ValueError(
            "the sweep was not started, " + "; ".join(errors) + " (nothing was run or written)"
        )


class SweepFailed(Exception):
    """Runs of a sweep that failed (the others ran): ``failures`` maps (configuration, the
    run's folder: ``seed<S>`` or a population's ``seeds0-9``) to the error, ``results``
    holds the summaries of the (configuration, seed) runs that ended."""

    def __init__(
        self, failures: Mapping[tuple[str, str], str], results: Mapping[tuple[str, int], Any]
    ) -> None:
        self.failures, self.results = dict(failures), dict(results)
        super().__init__(
            f"{len(self.failures)} run(s) of the sweep failed, the others ran: "
            + "; ".join(f"{n}/{d}: {why}" for (n, d), why in self.failures.items())
        )


Done = Callable[[SweepRun, dict[str, Any]], None]
Failed = Callable[[SweepRun, BaseException], None]


def _one_thread(run: SweepRun) -> dict[str, Any]:
    torch.set_num_threads(1)
    return run_one(run)


class SweepTerminated(KeyboardInterrupt):
    """A sweep stopped by SIGTERM (as Ctrl-C stops it; ``signame`` gives the exit code 143)."""

    signame = "SIGTERM"


def _terminate(signum: int, frame: Any) -> None:
    raise SweepTerminated("SIGTERM")


def _local(runs: Sequence[SweepRun], workers: int, done: Done, failed: Failed) -> None:
    """The runs in this process (one worker) or in a :class:`~.pool.LocalPool` of ``workers``
    processes held to cores of their own; a run whose worker died is resumed by another, up to
    :data:`MAX_RETRIES` times. SIGTERM stops a sweep as Ctrl-C does: the runs going stop at
    their next iteration boundary, with a checkpoint."""
    with signal_handled(signal.SIGTERM, _terminate):
        if workers == 1:  # one thread as in the worker processes: the same sums, the same results
            for run in runs:
                try:
                    summary = _one_thread(run)
                except Exception as exc:
                    failed(run, exc)
                    continue
                done(run, summary)
            return
        pool = LocalPool(workers, pin=True, runs=True)
        deaths = dict.fromkeys(range(len(runs)), 0)
        todo = dict(enumerate(runs))
        try:
            while todo:
                futures = {pool.submit(_one_thread, run): k for k, run in todo.items()}
                todo = {}
                for future in as_completed(futures):
                    k = futures[future]
                    try:
                        summary = future.result()
                    except BrokenProcessPool:  # its worker, or another's, died: resume it
                        deaths[k] += 1
                        if deaths[k] <= MAX_RETRIES:
                            todo[k] = runs[k]
                        else:
                            failed(
                                runs[k], RuntimeError(f"its worker process died {deaths[k]} times")
                            )
                        continue
                    except Exception as exc:
                        failed(runs[k], exc)
                        continue
                    done(runs[k], summary)
                if todo:
                    pool.restart()
        finally:  # the end, an error or Ctrl-C: the runs going stop at their next boundary
            pool.stop()
            pool.close()


def _ray(
    runs: Sequence[SweepRun], workers: int, address: str | None, done: Done, failed: Failed
) -> None:
    ray, owns = start_ray(workers, address, RAY_ENV)  # one thread and MKL as local workers
    task = ray.remote(num_cpus=1, max_retries=2)(_one_thread)
    try:
        pending = {task.remote(r): r for r in runs}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                run = pending.pop(ref)
                try:
                    summary = ray.get(ref)
                except Exception as exc:  # a RayTaskError: the run's own error is its cause
                    failed(run, getattr(exc, "cause", None) or exc)
                    continue
                done(run, summary)
    except BaseException:
        for ref in list(locals().get("pending", {})):
            ray.cancel(ref, force=True)
        raise
    finally:
        if owns:
            ray.shutdown()


def run_sweep(
    runs: Sequence[SweepRun],
    *,
    backend: Backend = "local",
    workers: int = 1,
    ray_address: str | None = None,
    progress: bool = True,
    on_result: Callable[[SweepRun, dict[str, Any]], None] | None = None,
    checked: bool = False,
) -> dict[tuple[str, int], dict[str, Any]]:
    """Run every run of ``runs`` (finished ones reused, interrupted ones resumed), calling
    ``on_result(run, summary)`` as each ends; returns ``{(name, seed): summary}``. The
    backend and the configurations are checked first unless ``checked``; failed runs do not
    stop the others and raise :class:`SweepFailed` once all have ended."""
    keys = [(m.name, m.seed) for r in runs for m in r.members()]
    if len(set(keys)) != len(keys):
        raise ValueError("a sweep holds the same (configuration, seed) twice")
    if not checked:
        check_pool(workers, backend, ray_address, reach=True)
        check_configurations(runs)
    results: dict[tuple[str, int], dict[str, Any]] = {}
    failures: dict[tuple[str, str], str] = {}
    bar = tqdm(total=len(runs), desc="sweep", disable=not progress)

    def failed(run: SweepRun, exc: BaseException) -> None:
        failures[(run.name, Path(run.run_dir).name)] = f"{type(exc).__name__}: {exc}"
        bar.update(1)

    def done(run: SweepRun, summary: dict[str, Any]) -> None:
        if run.seeds:  # a population: its members' own summaries
            reused = {"reused": True} if summary.get("reused") else {}
            try:
                ends = [(m, {**_finished_summary(m, run.run_dir), **reused}) for m in run.members()]
            except DamagedSummary as exc:
                failed(run, exc)
                return
        else:
            ends = [(run, summary)]
        bar.update(1)
        for member, end in ends:
            results[(member.name, member.seed)] = end
            if on_result is not None:
                on_result(member, end)

    todo = []
    for run in runs:  # finished runs are read here: no worker (and no Ray) for them
        if (Path(run.run_dir) / "summary.json").is_file():
            try:
                summary = run_one(run)
            except DamagedSummary as exc:  # that run fails; other options stop the sweep
                failed(run, exc)
                continue
            done(run, summary)
        else:
            todo.append(run)
    try:
        if todo and backend == "ray":
            _ray(todo, workers, ray_address, done, failed)
        elif todo:
            _local(todo, workers, done, failed)
    finally:
        bar.close()
    if failures:
        raise SweepFailed(failures, results)
    return results


def main(cfg: SweepConfig) -> dict[str, Any]:
    """``hireps-train sweep``: plan, run (reusing, resuming), summarize; returns what it wrote."""
    configurations = parse_grid(cfg.experiment, cfg.grid, cfg.set)
    runs = plan(cfg.experiment, configurations, parse_seeds(cfg.seeds), cfg.out, cfg.members)
    check_pool(cfg.workers, cfg.backend, cfg.ray_address, reach=True)  # before anything is written
    check_configurations(runs)
    out = Path(cfg.out) / cfg.experiment
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"--out {cfg.out}: cannot create {out} ({exc.strerror})") from None
    lock = DirectoryLock(out)  # one sweep per directory (each run also locks its own)
    try:
        reused = sum((r.run_dir / "summary.json").is_file() for r in runs)
        if cfg.progress and reused:
            print(f"{reused} of {len(runs)} runs already finished; running the rest", flush=True)
        failure: SweepFailed | None = None
        try:
            results = run_sweep(
                runs,
                backend=cfg.backend,
                workers=cfg.workers,
                ray_address=cfg.ray_address,
                progress=cfg.progress,
                checked=True,
            )
        except SweepFailed as exc:
            failure, results = exc, exc.results
        except KeyboardInterrupt as stop:
            why = f" ({stop})" if str(stop) else ""
            term = getattr(stop, "signame", None) == "SIGTERM"
            raise (SweepTerminated if term else KeyboardInterrupt)(
                f"the sweep stopped{why}; every run keeps its last checkpoint (the runs that "
                "were going wrote one as they stopped). Run the same command again: finished "
                "runs are reused and the others resume from their checkpoints"
            ) from None
        ended = [m for r in runs for m in r.members() if (m.name, m.seed) in results]
        seconds = "s (population)" if cfg.members > 1 else "s/run"
        entry = EXPERIMENTS[cfg.experiment]
        table = (
            summarize(ended, results, out, entry.metric, entry.curve, seconds=seconds)
            if ended
            else ""
        )
    finally:
        lock.release()
    print(table)
    if failure is not None:
        table_note = f"The table in {out / 'sweep.md'} holds the runs that ended. " if ended else ""
        raise ValueError(
            f"{failure}. {table_note}Run the sweep again once the failed runs are fixed (the "
            "others are reused)"
        )
    return {
        "experiment": cfg.experiment,
        "runs": len(runs),
        "reused": reused,
        "summary": str(out / "sweep.md"),
        "plot": str(out / "sweep.png"),
    }
