"""train.py sweep (experiments/sweep.py): grids, seeds, resumable sweeps on local processes
and Ray."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hireps_torch.experiments.report import summarize  # noqa: E402
from hireps_torch.experiments.sweep import (
    SweepFailed,
    parse_grid,
    parse_seeds,
    plan,
    run_sweep,
    seeds_text,
)

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}


def _sweep(args: list[str], timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "train.py", "sweep", "--no-progress", *args],
        cwd=ROOT,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def test_parse_seeds_ranges_lists_and_errors():
    assert parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert parse_seeds("0,3,7") == [0, 3, 7]
    assert parse_seeds("0-2,9") == [0, 1, 2, 9]
    assert parse_seeds("-2--1") == [-2, -1]
    with pytest.raises(ValueError, match=r"seed\(s\) \[1\] more than once"):
        parse_seeds("0-2,1")
    for bad in ("", "a", "3-1", "1-", "0,,1", "\u0663"):
        with pytest.raises(ValueError, match="--seeds must look like"):
            parse_seeds(bad)
    for bad in ("0-999999", str(2**70)):
        with pytest.raises(ValueError, match=r"must lie in \[-2\*\*62, 2\*\*62\]"):
            parse_seeds(bad)


def test_parse_grid_gives_every_combination_with_typed_values():
    configs = parse_grid("pendulum", ["n_options=1,5", "gating=learned,flat"], ["episodes=40"])
    assert list(configs) == [  # keys sorted in the names: --grid order does not rename runs
        "gating=learned,n_options=1",
        "gating=flat,n_options=1",
        "gating=learned,n_options=5",
        "gating=flat,n_options=5",
    ]
    assert configs["gating=flat,n_options=5"] == {"episodes": 40, "n_options": 5, "gating": "flat"}
    assert set(parse_grid("pendulum", ["gating=learned,flat", "n_options=1,5"])) == set(configs)
    assert parse_grid("bimodal", ["contextual=true,false"]) == {
        "contextual=true": {"contextual": True},
        "contextual=false": {"contextual": False},
    }
    assert parse_grid("bimodal") == {"default": {}}
    assert parse_grid("pendulum", ["steps-per-decision=2"]) == {
        "steps_per_decision=2": {"steps_per_decision": 2}
    }


def test_a_configuration_is_named_by_its_parsed_values():
    """Other spellings of the same values name the same runs (before: the raw text, so that
    ``n_options=\u0661,\u0663`` ran n_options 1 and 3 under other names than ``1,3``)."""
    arabic = parse_grid("pendulum", ["n_options=\u0661,\u0663", "epsilon=1e-1"])
    plain = parse_grid("pendulum", ["n_options=1,3", "epsilon=0.1"])
    assert arabic == plain
    assert list(plain) == ["epsilon=0.1,n_options=1", "epsilon=0.1,n_options=3"]


@pytest.mark.parametrize(
    ("grid", "fixed", "message"),
    [
        (["n_options"], [], "must look like OPTION=VALUE"),
        (["no_such=1,2"], [], "has no option 'no_such'"),
        (["seed=1,2"], [], "sets 'seed' itself"),
        (["n_options=1,x"], [], "bad option value"),
        (["n_options=1,1"], [], "distinct"),
        (["n_options=1,2"], ["n_options=3"], "appears twice"),
        ([], ["episodes=10", "episodes=20"], "appears twice in --set"),
        (["epsilon=0.1,1e-1"], [], "same value twice"),
        (["mirror_samples=maybe"], [], "true or false"),
    ],
)
def test_parse_grid_names_bad_entries(grid, fixed, message):
    with pytest.raises(ValueError, match=message):
        parse_grid("pendulum", grid, fixed)


def test_an_unknown_option_lists_only_the_options_a_sweep_may_set():
    with pytest.raises(ValueError, match="has no option 'no_such'; options: ") as info:
        parse_grid("pendulum", ["no_such=1,2"])
    listed = str(info.value).split("options: ")[1].split(", ")
    assert "n_options" in listed and "episodes" in listed
    assert not {"seed", "seeds", "run_dir", "resume", "progress"} & set(listed)


@pytest.mark.parametrize(
    ("grid", "why"),
    [
        ("epsilon=abc,0.1", "--epsilon: could not convert string to float: 'abc'"),
        ("gating=learned,foo", "--gating is one of learned, constant, flat, got 'foo'"),
        (
            "epsilon_end=None,abc",
            "--epsilon-end: no type matching {None}|FLOAT could be instantiated from ['abc'].",
        ),
    ],
)
def test_a_bad_grid_value_is_one_line_naming_the_option_and_value(capsys, grid, why):
    """A value the option's type refuses: one ValueError naming --option, the value and why,
    and nothing printed (no help box)."""
    with pytest.raises(ValueError) as err:
        parse_grid("pendulum", [grid])
    assert str(err.value) == f"bad option value for PendulumConfig: {why}"
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""


def test_unknown_experiment_and_bad_sweep_options(tmp_path):
    with pytest.raises(ValueError, match="unknown experiment 'tennis'"):
        parse_grid("tennis")
    runs = plan("bimodal", {"default": {}}, [0], tmp_path)
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        run_sweep(runs, workers=0)
    with pytest.raises(ValueError, match="needs --backend ray"):
        run_sweep(runs, ray_address="127.0.0.1:1")
    with pytest.raises(ValueError, match="cannot reach the Ray cluster at --ray-address '127.0"):
        run_sweep(runs, backend="ray", ray_address="127.0.0.1:1")
    with pytest.raises(ValueError, match="same \\(configuration, seed\\) twice"):
        run_sweep(runs + runs)
    assert not any(tmp_path.iterdir())


def test_an_in_process_sweep_writes_runs_table_and_plot_and_reuses_them(tmp_path):
    configs = parse_grid("bimodal", ["n_options=1,3"], ["episodes=400"])
    runs = plan("bimodal", configs, [0, 1], tmp_path)
    results = run_sweep(runs, progress=False)
    assert set(results) == {(n, s) for n in configs for s in (0, 1)}
    for r in runs:
        assert (r.run_dir / "summary.json").is_file() and (r.run_dir / "metrics.csv").is_file()
        cfg = json.loads((r.run_dir / "config.json").read_text())
        assert cfg["seed"] == r.seed and cfg["n_options"] == r.options["n_options"]
    table = summarize(runs, results, tmp_path / "bimodal", "final_return", "eval_return")
    assert table.count("\n") == 3 and "| n_options=3 | 2 |" in table
    assert (tmp_path / "bimodal" / "sweep.png").stat().st_size > 0
    stamps = [(r.run_dir / "summary.json").stat().st_mtime_ns for r in runs]
    again = run_sweep(runs, progress=False)
    assert all(v.get("reused") for v in again.values())
    assert stamps == [(r.run_dir / "summary.json").stat().st_mtime_ns for r in runs]


def test_the_plots_band_is_the_tables_sample_std(tmp_path, monkeypatch):
    """The band around each curve is the sample std (n - 1), as in the table beside it
    (before: the population std, narrower by sqrt((n - 1) / n))."""
    import matplotlib.axes
    import numpy as np

    from hireps_torch.experiments.sweep import SweepRun

    runs, results = [], {}
    for seed, value in ((0, 0.0), (1, 3.0), (2, 6.0)):
        d = tmp_path / f"seed{seed}"
        d.mkdir()
        (d / "metrics.csv").write_text(f"episodes,eval_return\n10,{value}\n20,{2 * value}\n")
        runs.append(SweepRun("bimodal", "c", seed, {}, d))
        results[("c", seed)] = {"final_return": value, "wall_seconds": 1.0}
    bands = []
    fill = matplotlib.axes.Axes.fill_between
    monkeypatch.setattr(
        matplotlib.axes.Axes,
        "fill_between",
        lambda self, x, lo, hi, **kw: bands.append((lo, hi)) or fill(self, x, lo, hi, **kw),
    )
    table = summarize(
        runs, results, tmp_path, "final_return", "eval_return", "population", "s (population)"
    )
    assert "3 ± 3 |" in table and "| s (population) |" in table
    ((lo, hi),) = bands
    np.testing.assert_allclose(hi, [6.0, 12.0])  # mean 3, 6 + sample std 3, 6
    np.testing.assert_allclose(lo, [0.0, 0.0])


def _ray_processes() -> list[str]:
    found = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            args = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if "/ray/core/src/ray/" in args or args.startswith("ray::"):
            found.append(args[:120])
    return found


BEAM = [
    "--experiment",
    "ball-on-beam",
    "--seeds",
    "0-1",
    "--grid",
    "n_options=1,2",
    "--set",
    "episodes=12",
]


@pytest.mark.slow
def test_an_interrupted_sweep_finishes_on_ray_and_ends_as_an_uninterrupted_one(tmp_path):
    """A local sweep stopped by SIGINT inside its first run, then the same sweep on a local
    Ray instance with 2 CPUs: every run finishes, the interrupted one resumed from its
    checkpoint ends exactly as a run that was never stopped, a third call reuses all four,
    and no process is left behind."""
    pytest.importorskip("ray")
    out = tmp_path / "sweep"
    first = out / "ball-on-beam" / "n_options=1" / "seed0"
    proc = subprocess.Popen(
        [sys.executable, "train.py", "sweep", "--no-progress", *BEAM, "--out", str(out)],
        cwd=ROOT,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        metrics = first / "metrics.csv"
        if metrics.is_file() and len(metrics.read_text().splitlines()) >= 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert not (first / "summary.json").exists() and (first / "checkpoint.pt").is_file()

    done = _sweep([*BEAM, "--out", str(out), "--backend", "ray", "--workers", "2"])
    assert done.returncode == 0, done.stderr[-3000:]
    assert '"reused": 0' in done.stdout
    for cfg in ("n_options=1", "n_options=2"):
        for seed in (0, 1):
            assert (out / "ball-on-beam" / cfg / f"seed{seed}" / "summary.json").is_file()
    table = (out / "ball-on-beam" / "sweep.md").read_text()
    assert "| n_options=1 | 2 |" in table and "| n_options=2 | 2 |" in table

    ref = subprocess.run(
        [
            sys.executable,
            "train.py",
            "ball-on-beam",
            "--episodes",
            "12",
            "--n-options",
            "1",
            "--no-progress",
            "--run-dir",
            str(tmp_path / "ref"),
        ],
        cwd=ROOT,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert ref.returncode == 0, ref.stderr[-2000:]
    drop = ("wall_seconds", "seconds")

    def rows(path: Path) -> list[dict[str, str]]:
        import csv

        with path.open() as f:
            return [
                {k: v for k, v in r.items() if not any(d in k for d in drop)}
                for r in csv.DictReader(f)
            ]

    assert rows(first / "metrics.csv") == rows(tmp_path / "ref" / "metrics.csv")

    again = _sweep([*BEAM, "--out", str(out)])  # local backend: reuse needs no Ray
    assert again.returncode == 0 and '"reused": 4' in again.stdout
    deadline = time.monotonic() + 20
    while _ray_processes() and time.monotonic() < deadline:
        time.sleep(0.5)
    assert _ray_processes() == []


def test_a_ray_sweep_without_ray_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    runs = plan("bimodal", {"default": {}}, [0], tmp_path)
    with pytest.raises(ImportError, match="distributed"):
        run_sweep(runs, backend="ray", workers=2)
    assert not any(tmp_path.iterdir())


def test_a_sweep_refuses_runs_with_other_options_and_unknown_leftovers(tmp_path):
    """A finished run is reused only with the options it was made with; a directory with
    files but no config.json is named, not overwritten."""
    first = plan("bimodal", parse_grid("bimodal", [], ["episodes=400"]), [0], tmp_path)
    run_sweep(first, progress=False)
    summary = (first[0].run_dir / "summary.json").read_bytes()
    other = plan("bimodal", parse_grid("bimodal", [], ["episodes=800"]), [0], tmp_path)
    with pytest.raises(ValueError, match=r"other options than this sweep asks for: episodes"):
        run_sweep(other, progress=False)
    assert (first[0].run_dir / "summary.json").read_bytes() == summary
    leftover = plan("bimodal", {"default": {}}, [1], tmp_path)
    leftover[0].run_dir.mkdir(parents=True)
    (leftover[0].run_dir / ".config.json.x.tmp").write_text("{")
    with pytest.raises(SweepFailed, match="default/seed1: FileExistsError: .* holds files but no"):
        run_sweep(leftover, progress=False)
    assert (leftover[0].run_dir / ".config.json.x.tmp").read_text() == "{"


def test_repeated_set_and_grid_flags_all_count():
    """``--set A --set B`` keeps both (a plain tuple option kept only the last one, which
    silently dropped options from a sweep)."""
    import train

    cfg = train.parse(
        [
            "sweep",
            "--experiment",
            "hockey-sequential",
            "--set",
            "flat_pucks=false",
            "--set",
            "floor_friction=0.05",
            "--grid",
            "n_options=1,2",
            "--grid",
            "mean_prior=0,4",
        ]
    )
    assert cfg.set == ("flat_pucks=false", "floor_friction=0.05")
    assert cfg.grid == ("n_options=1,2", "mean_prior=0,4")
    configs = parse_grid(cfg.experiment, cfg.grid, cfg.set)
    assert len(configs) == 4
    assert all(c["flat_pucks"] is False and c["floor_friction"] == 0.05 for c in configs.values())


def test_every_configuration_is_checked_before_the_first_run(tmp_path):
    out = tmp_path / "sw"
    p = _sweep(
        [
            "--experiment",
            "bimodal",
            "--seeds",
            "0-1",
            "--grid",
            "epsilon=0.5,-1",
            "--set",
            "episodes=400",
            "--out",
            str(out),
        ]
    )
    assert p.returncode == 2
    assert "configuration epsilon=-1.0 (seed 0): epsilon must be finite and > 0" in p.stderr
    assert not out.exists()  # nothing ran, nothing was written


@pytest.mark.slow
def test_a_failing_run_is_named_and_the_others_still_run(tmp_path):
    """Seed 1's run directory holds a damaged checkpoint: seeds 0 and 2 run, the sweep names
    seed 1 and writes the table of the others; once it is fixed, a rerun finishes."""
    out = tmp_path / "sw"
    args = ["--experiment", "bimodal", "--seeds", "0-2", "--set", "episodes=400", "--out", str(out)]
    bad = out / "bimodal" / "default" / "seed1"
    from hireps_torch.experiments import EXPERIMENTS

    config_cls, run = EXPERIMENTS["bimodal"].config, EXPERIMENTS["bimodal"].run
    run(config_cls(episodes=400, seed=1, run_dir=bad, progress=False))
    (bad / "summary.json").unlink()
    (bad / "checkpoint.pt").write_bytes(b"")
    p = _sweep(args)
    assert p.returncode == 2, p.stderr
    assert "1 run(s) of the sweep failed" in p.stderr and "default/seed1" in p.stderr
    assert "cannot be read" in p.stderr
    for seed in (0, 2):
        assert (out / "bimodal" / "default" / f"seed{seed}" / "summary.json").is_file()
    table = (out / "bimodal" / "sweep.md").read_text()
    assert "0: " in table and "2: " in table and "1: " not in table
    (bad / "checkpoint.pt").unlink()
    (bad / "metrics.csv").unlink()
    again = _sweep(args)
    assert again.returncode == 0, again.stderr
    assert "1: " in (out / "bimodal" / "sweep.md").read_text()


def test_a_sweep_directory_has_one_sweep_at_a_time(tmp_path):
    from hireps_torch.experiments.rundir import DirectoryLock

    out = tmp_path / "sw"
    (out / "bimodal").mkdir(parents=True)
    held = DirectoryLock(out / "bimodal")
    p = _sweep(
        ["--experiment", "bimodal", "--seeds", "0", "--set", "episodes=400", "--out", str(out)]
    )
    assert p.returncode == 2 and "being written by another process" in p.stderr
    assert list((out / "bimodal").iterdir()) == []
    held.release()


@pytest.mark.slow
@pytest.mark.parametrize("stop", ["ctrl-c", "sigterm", "kill -9"])
def test_a_stopped_sweep_with_workers_leaves_no_process_and_says_how_to_finish_it(tmp_path, stop):
    """Ctrl-C (SIGINT to the group), SIGTERM to the sweep alone (a cluster's requeue; before:
    the sweep died at once and its workers ran on), kill -9 of the sweep (before: its workers
    ran their runs to the end): every worker stops at an iteration boundary with a checkpoint,
    and nothing is left running."""
    out = tmp_path / "sw"
    args = [
        "--experiment",
        "bimodal",
        "--seeds",
        "0-1",
        "--set",
        "episodes=400000",
        "--set",
        "samples_per_iteration=20",
        "--out",
        str(out),
        "--workers",
        "2",
    ]
    p = subprocess.Popen(
        [sys.executable, "train.py", "sweep", "--no-progress", *args],
        cwd=ROOT,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    metrics = out / "bimodal" / "default" / "seed0" / "metrics.csv"
    deadline = time.time() + 120
    while time.time() < deadline and not (metrics.exists() and metrics.read_text().count("\n") > 2):
        time.sleep(0.05)
    if stop == "ctrl-c":
        os.killpg(p.pid, signal.SIGINT)  # what Ctrl-C in a terminal sends: the whole group
    else:
        p.send_signal(signal.SIGTERM if stop == "sigterm" else signal.SIGKILL)
    start = time.time()
    _, err = p.communicate(timeout=120)
    assert time.time() - start < 30, err
    assert p.returncode == {"ctrl-c": 130, "sigterm": 143, "kill -9": -9}[stop], err
    for _ in range(300):  # the multiprocessing resource tracker ends as its parent ends
        left = subprocess.run(["pgrep", "-g", str(p.pid)], capture_output=True, text=True).stdout
        if not left.split():
            break
        time.sleep(0.1)
    assert not left.split(), f"processes left behind: {left}"
    assert (out / "bimodal" / "default" / "seed0" / "checkpoint.pt").is_file()
    if stop == "kill -9":
        return
    assert "interrupted: the sweep stopped" in err
    assert "Run the same command again" in err
    assert (out / "bimodal" / "default" / "seed0" / "checkpoint.pt").is_file()


@pytest.mark.parametrize(
    "extra",
    [
        ["--workers", "0"],
        ["--ray-address", "127.0.0.1:6379"],  # with the local backend
        ["--grid", "checkpoint_every=0,1"],  # a run option only the run checks
        ["--grid", "device=cuda:99,cpu"],  # a device present on no machine
    ],
    ids=["workers", "ray-address", "checkpoint-every", "device"],
)
def test_a_refused_sweep_writes_nothing(tmp_path, extra):
    """In process (``train.main`` raises what ``train.py`` prints as ``error:``)."""
    import train

    out = tmp_path / "sw"
    base = ["--experiment", "bimodal", "--seeds", "0", "--set", "episodes=400", "--out", str(out)]
    with pytest.raises(ValueError):
        train.main(["sweep", "--no-progress", *base, *extra])
    assert not out.exists()


def test_an_out_that_cannot_be_a_directory_is_named(tmp_path):
    import train

    (tmp_path / "file").write_text("mine")
    args = ["sweep", "--no-progress", "--experiment", "bimodal", "--seeds", "0"]
    with pytest.raises(OSError, match=r"--out .*file: cannot create .*file/bimodal \(Not a dir"):
        train.main([*args, "--out", str(tmp_path / "file")])
    assert (tmp_path / "file").read_text() == "mine"


@pytest.mark.parametrize("damage", ["{bad", "[1]", "{}", '{"final_return": "x"}', ""])
def test_a_damaged_summary_of_a_finished_run_is_named(tmp_path, damage):
    from hireps_torch.experiments.sweep import DamagedSummary, _finished_summary

    run = plan("bimodal", {"default": {}}, [0], tmp_path)[0]
    run.run_dir.mkdir(parents=True)
    (run.run_dir / "summary.json").write_text(damage)
    with pytest.raises(DamagedSummary, match=f"{run.run_dir / 'summary.json'} is damaged"):
        _finished_summary(run)


def test_a_finished_run_without_its_metrics_is_named(tmp_path):
    """The sweep's curves read metrics.csv (before: a bare FileNotFoundError ended the sweep
    after every run, with no table)."""
    from hireps_torch.experiments.sweep import DamagedSummary, _finished_summary

    run = plan("bimodal", {"default": {}}, [0], tmp_path)[0]
    run.run_dir.mkdir(parents=True)
    (run.run_dir / "summary.json").write_text('{"final_return": 1.0}')
    (run.run_dir / "metrics.csv").mkdir()
    with pytest.raises(DamagedSummary, match=f"{run.run_dir} finished but its metrics.csv is"):
        _finished_summary(run)
    (run.run_dir / "metrics.csv").rmdir()
    (run.run_dir / "metrics.csv").write_text("episodes,eval_return\n")
    assert _finished_summary(run) == {"final_return": 1.0}


def test_a_finished_run_with_a_damaged_summary_fails_alone(tmp_path):
    """Seed 0's summary.json is damaged: the sweep names it, seed 1 still runs, no
    traceback (before: a KeyError in the table, or an unnamed JSON error, and nothing ran)."""
    out = tmp_path / "sw"
    args = ["--experiment", "bimodal", "--seeds", "0-1", "--set", "episodes=400", "--out", str(out)]
    from hireps_torch.experiments import EXPERIMENTS

    config_cls, run = EXPERIMENTS["bimodal"].config, EXPERIMENTS["bimodal"].run
    bad = out / "bimodal" / "default" / "seed0" / "summary.json"
    run(config_cls(episodes=400, seed=0, run_dir=bad.parent, progress=False))
    bad.write_text("{}")
    p = _sweep(args)
    assert p.returncode == 2, p.stderr
    assert f"{bad} is damaged" in p.stderr and "Traceback" not in p.stderr
    assert (out / "bimodal" / "default" / "seed1" / "summary.json").is_file()
    assert bad.read_text() == "{}"


def test_a_sweep_whose_every_run_failed_points_to_no_table(tmp_path):
    from hireps_torch.experiments.sweep import SweepConfig, main

    out = tmp_path / "sw"
    (out / "bimodal").mkdir(parents=True)
    (out / "bimodal" / "default").write_text("x")  # where the runs' directories would go
    cfg = SweepConfig(
        experiment="bimodal", seeds="0-1", set=("episodes=400",), out=out, progress=False
    )
    with pytest.raises(ValueError) as failed:
        main(cfg)
    assert "run(s) of the sweep failed" in str(failed.value)
    assert "sweep.md" not in str(failed.value) and not (out / "bimodal" / "sweep.md").exists()


# ---- populations (--members) ---------------------------------------------------------------


def test_plan_runs_each_configurations_seeds_as_populations_of_at_most_members(tmp_path):
    configs = {"a": {"episodes": 400}, "b": {}}
    runs = plan("bimodal", configs, [3, 4, 5, 6, 7], tmp_path, members=3)
    assert [(r.name, r.seeds) for r in runs] == [
        ("a", (3, 4)),
        ("a", (5, 6, 7)),
        ("b", (3, 4)),
        ("b", (5, 6, 7)),
    ]
    assert runs[1].run_dir == tmp_path / "bimodal" / "a" / "seeds5-7" and runs[1].seed == 5
    assert [(m.seed, m.run_dir, m.seeds) for m in runs[1].members()] == [
        (s, runs[1].run_dir / f"seed{s}", ()) for s in (5, 6, 7)
    ]
    from hireps_torch.experiments.bimodal import BimodalConfig

    cfg = runs[1].config(BimodalConfig, progress=False)
    assert (cfg.seeds, cfg.seed, cfg.episodes) == ("5-7", 0, 400)
    mixed = plan("bimodal", {"a": {}}, [7, 3, 5, 0, 9], tmp_path, members=3)
    assert [(r.seeds, r.seed, r.run_dir.name) for r in mixed] == [
        ((3, 7), 3, "seeds3,7"),  # the order given splits, each population sorted
        ((0, 5, 9), 0, "seeds0,5,9"),
    ]
    assert seeds_text([9, 0, 1, 2, 5, -3, -2]) == "-3--2,0-2,5,9"
    assert parse_seeds(seeds_text([9, 0, 1, 2, 5, -3, -2])) == [-3, -2, 0, 1, 2, 5, 9]
    many = [
        plan("bimodal", {"a": {}}, list(range(0, k, 2)), tmp_path, members=99)[0] for k in (80, 82)
    ]
    names = [r.run_dir.name for r in many]  # long texts: first and last seed and a hash
    assert names[0].startswith("seeds0-78_") and names[1].startswith("seeds0-80_")
    assert len(set(names)) == 2 and all(len(n) < 40 for n in names)
    other = plan("bimodal", {"a": {}}, list(range(0, 80, 2)) + [1], tmp_path, members=99)[0]
    assert other.run_dir.name.startswith("seeds0-78_") and other.run_dir.name != names[0]
    one = plan("bimodal", configs, [3, 4], tmp_path, members=1)
    assert [(r.seed, r.seeds, r.run_dir.name) for r in one][:2] == [
        (3, (), "seed3"),
        (4, (), "seed4"),
    ]
    assert one[0].members() == [one[0]]
    assert [r.seeds for r in plan("bimodal", configs, [1, 2], tmp_path, members=9)] == [(1, 2)] * 2
    for bad in (0, -1, True, 2.0):
        with pytest.raises(ValueError, match=f"members must be an integer >= 1, got {bad!r}"):
            plan("bimodal", configs, [1], tmp_path, members=bad)


def test_a_sweep_of_populations_writes_the_runs_of_separate_seeds_and_reuses_them(tmp_path):
    """Each member of a population writes, bit for bit, the metrics.csv of its seed's own run;
    the table and sweep.json are per seed; a second sweep reuses the populations."""
    configs = parse_grid("bimodal", ["n_options=1,3"], ["episodes=400"])
    separate = plan("bimodal", configs, [0, 1, 2], tmp_path / "separate")
    pops = plan("bimodal", configs, [0, 1, 2], tmp_path / "pops", members=2)
    seen = []
    expected = run_sweep(separate, progress=False)
    results = run_sweep(pops, progress=False, on_result=lambda r, s: seen.append((r.name, r.seed)))
    assert set(results) == set(expected) == set(seen) and len(seen) == 6
    members = [m for r in pops for m in r.members()]
    for m, r in zip(members, separate, strict=True):
        assert (m.name, m.seed) == (r.name, r.seed)
        assert (m.run_dir / "metrics.csv").read_bytes() == (r.run_dir / "metrics.csv").read_bytes()
        assert (
            results[(m.name, m.seed)]["final_return"] == expected[(r.name, r.seed)]["final_return"]
        )
    table = summarize(
        members, results, tmp_path / "pops" / "bimodal", "final_return", "eval_return"
    )
    assert "| n_options=3 | 3 |" in table and "2: " in table
    stamps = [(r.run_dir / "summary.json").stat().st_mtime_ns for r in pops]
    again = run_sweep(pops, progress=False)
    assert set(again) == set(results) and all(v.get("reused") for v in again.values())
    assert stamps == [(r.run_dir / "summary.json").stat().st_mtime_ns for r in pops]


def test_an_unfinished_population_of_a_sweep_resumes_to_the_same_members(tmp_path):
    pops = plan("bimodal", {"default": {"episodes": 400}}, [0, 1], tmp_path, members=2)
    run_sweep(pops, progress=False)
    before = {m.seed: (m.run_dir / "metrics.csv").read_bytes() for m in pops[0].members()}
    (pops[0].run_dir / "summary.json").unlink()  # as if stopped before its end
    again = run_sweep(pops, progress=False)
    assert not any(v.get("reused") for v in again.values())
    assert before == {m.seed: (m.run_dir / "metrics.csv").read_bytes() for m in pops[0].members()}


def test_a_finished_population_with_other_options_is_refused_naming_the_option(tmp_path):
    """A population finished with the KL bound held is not reused by a sweep that asks for
    the schedule (nor the other way round): the error names the option, nothing changes."""
    held = plan("pendulum", {"d": {"episodes": 40, "epsilon_end": None}}, [0, 1], tmp_path, 2)
    run_sweep(held, progress=False)
    summary = (held[0].run_dir / "summary.json").read_bytes()
    scheduled = plan("pendulum", {"d": {"episodes": 40}}, [0, 1], tmp_path, 2)
    with pytest.raises(ValueError, match="other options than this sweep asks for: epsilon_end"):
        run_sweep(scheduled, progress=False)
    assert (held[0].run_dir / "summary.json").read_bytes() == summary


def test_a_population_whose_member_summary_is_damaged_fails_alone_named_by_its_folder(tmp_path):
    from hireps_torch.experiments.sweep import DamagedSummary, _finished_summary

    pops = plan("bimodal", {"default": {"episodes": 400}}, [0, 1, 2, 3], tmp_path, members=2)
    run_sweep(pops, progress=False)
    bad = pops[0].run_dir / "seed1" / "summary.json"
    metrics = (bad.parent / "metrics.csv").read_bytes()
    bad.write_text("{}")
    advice = f"move {pops[0].run_dir / 'summary.json'} away: the population then writes it again"
    with pytest.raises(DamagedSummary, match=f"{bad} is damaged .*; {advice}"):
        _finished_summary(pops[0])
    with pytest.raises(SweepFailed, match=r"default/seeds0-1: DamagedSummary: .*seed1") as failed:
        run_sweep(pops, progress=False)
    assert set(failed.value.results) == {("default", 2), ("default", 3)}
    (pops[0].run_dir / "summary.json").rename(tmp_path / "away.json")  # as the error advises
    again = run_sweep(pops, progress=False)
    assert again[("default", 1)]["final_return"] == json.loads(bad.read_text())["final_return"]
    assert (bad.parent / "metrics.csv").read_bytes() == metrics
    (bad.parent / "metrics.csv").unlink()  # the same advice for a member's missing metrics
    with pytest.raises(SweepFailed, match=f"metrics.csv is missing; {advice}"):
        run_sweep(pops, progress=False)
    (pops[0].run_dir / "summary.json").unlink()
    run_sweep(pops, progress=False)
    assert (bad.parent / "metrics.csv").read_bytes() == metrics


def test_a_finished_population_whose_member_config_changed_is_refused_naming_it(tmp_path):
    pops = plan("bimodal", {"default": {"episodes": 400}}, [0, 1], tmp_path, members=2)
    run_sweep(pops, progress=False)
    config = pops[0].run_dir / "seed1" / "config.json"
    config.write_text(config.read_text().replace('"n_options": 10', '"n_options": 3'))
    with pytest.raises(ValueError, match=r"seeds0-1/seed1 holds a run with other options .*n_opt"):
        run_sweep(pops, progress=False)
    config.unlink()
    with pytest.raises(ValueError, match=r"seed1/config.json cannot be read"):
        run_sweep(pops, progress=False)


def test_local_workers_keep_to_cores_of_their_own_when_there_are_enough(monkeypatch):
    from hireps_torch.experiments.pool import core_sets

    for cores, workers, sets in [
        ({1, 0}, 2, [{0}, {1}]),
        ({0, 1, 2, 3, 4}, 2, [{0, 1}, {2, 3}]),
        ({0, 1}, 1, []),  # one worker keeps every core
        ({0, 1}, 3, []),  # too few to give each its own
    ]:
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid, cores=cores: cores)
        assert core_sets(workers) == sets


@pytest.mark.slow
def test_populations_in_two_workers_equal_populations_one_after_the_other(tmp_path):
    """Two configurations' pendulum populations, each in a worker process held to a core of
    its own, write the metrics they write one after the other in this process."""
    configs = {"learned-2": {"n_options": 2, "episodes": 40}, "d10": {"steps_per_decision": 10}}
    configs["d10"]["episodes"] = 40
    metrics = {}
    for workers in (1, 2):
        runs = plan("pendulum", configs, [0, 1], tmp_path / f"w{workers}", members=2)
        run_sweep(runs, workers=workers, progress=False)
        metrics[workers] = [
            (m.run_dir / "metrics.csv").read_text() for r in runs for m in r.members()
        ]
    assert metrics[1] == metrics[2]


def test_a_local_worker_takes_runs_one_after_the_other(tmp_path):
    """A worker process runs every run given to it (one import of torch for many runs), each
    outcome, a failed run included, back to the sweep; a run after others writes what it
    writes alone."""
    from hireps_torch.experiments import sweep
    from hireps_torch.experiments.pool import LocalPool

    runs = plan("bimodal", {"default": {"episodes": 400}}, [0, 1], tmp_path)
    bad = sweep.SweepRun("bimodal", "bad", 2, {"episodes": -1}, tmp_path / "bad")
    with LocalPool(1, runs=True) as pool:
        futures = [pool.submit(sweep._one_thread, run) for run in (runs[0], bad, runs[1])]
        first = futures[0].result()
        with pytest.raises(ValueError, match="episodes"):
            futures[1].result()
        last = futures[2].result()
    assert first["seed"] == 0 and last["seed"] == 1
    alone = plan("bimodal", {"default": {"episodes": 400}}, [1], tmp_path / "alone")
    run_sweep(alone, progress=False)
    summary = json.loads((alone[0].run_dir / "summary.json").read_text())
    assert last["final_return"] == summary["final_return"]
    assert (runs[1].run_dir / "metrics.csv").read_bytes() == (
        alone[0].run_dir / "metrics.csv"
    ).read_bytes()


def _worker_mkl() -> tuple[str | None, int | None]:
    import torch

    from hireps_torch.experiments.workers import _mkl_mode

    _ = torch.ones(3, 3, dtype=torch.float64) @ torch.ones(3, 3, dtype=torch.float64)
    return os.environ.get("MKL_CBWR"), _mkl_mode()


def test_pool_workers_compute_in_the_mkl_mode_of_the_command(monkeypatch):
    """Every worker (any experiment's sweep, hockey's episodes) runs MKL as hireps-train does,
    so that a member computed in a worker equals the same run by the command."""
    from hireps_torch.experiments.pool import MKL_MODE, LocalPool

    monkeypatch.delenv("MKL_CBWR", raising=False)
    with LocalPool(1, runs=True) as pool:
        variable, mode = pool.submit(_worker_mkl).result()
    assert variable == MKL_MODE
    assert mode in (None, 2, 3)  # None: a torch without MKL; 1 would be MKL's default
    assert "MKL_CBWR" not in os.environ  # the owner's environment as it was
