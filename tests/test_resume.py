"""Checkpoints and resume: a run interrupted by SIGINT/SIGTERM at any iteration and resumed
ends exactly as the uninterrupted run (metrics.csv, summary.json, final policy)."""

import csv
import dataclasses
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
TIMING = ("wall_seconds", "seconds_per_shot")  # measured times: the only fields that differ


def train(*args, timeout=300):
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )


def in_process(name, run_dir, **options):
    """Run experiment ``name`` in this process (no interpreter start-up)."""
    from hireps_torch.experiments import EXPERIMENTS

    config_cls, run = EXPERIMENTS[name].config, EXPERIMENTS[name].run
    return run(config_cls(progress=False, run_dir=run_dir, **options))


def resume_in_process(name, run_dir):
    """What ``train.py NAME --resume RUN_DIR`` does, in this process."""
    from hireps_torch.experiments import EXPERIMENTS, run_experiment
    from hireps_torch.experiments.checkpoint import saved_config

    cfg = saved_config(EXPERIMENTS[name].config, name, run_dir)
    return run_experiment(dataclasses.replace(cfg, progress=False))


def in_subprocess(args):
    """``train.py args`` in a fresh interpreter (hockey runs in MKL's reproducible mode,
    which train.py chooses before torch starts and this process cannot switch to)."""
    out = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args, "--no-progress"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        check=False,
    )
    assert out.returncode == 0, out.stderr[-3000:]


def cli(options):
    """``{"episodes": 160}`` as ``["--episodes", "160"]``."""
    return [x for k, v in options.items() for x in ("--" + k.replace("_", "-"), str(v))]


def rows(run):
    return list(csv.DictReader((run / "metrics.csv").open()))


@dataclasses.dataclass
class Stopped:
    code: int
    err: str
    seconds: float  # from the signal to the end
    pid: int  # also the process group's id with ``group``


def stop_run(args, run, after_rows, sig=signal.SIGINT, *, watch=None, group=False, when=None):
    """Start ``train.py args --run-dir run``; once ``watch`` (``run/metrics.csv`` by default)
    holds ``after_rows`` rows (or ``when(process)`` holds), send ``sig``, to the whole process
    group with ``group`` (what Ctrl-C in a terminal does)."""
    p = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *args, "--run-dir", str(run), "--no-progress"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        start_new_session=group,
    )
    m = watch or run / "metrics.csv"
    deadline = time.time() + 240
    while p.poll() is None and time.time() < deadline:
        if when(p) if when else m.exists() and len(m.read_text().splitlines()) > after_rows:
            break
        time.sleep(0.002)
    if group:
        os.killpg(p.pid, sig)
    else:
        p.send_signal(sig)
    start = time.time()
    _, err = p.communicate(timeout=240)
    return Stopped(p.returncode, err, time.time() - start, p.pid)


def interrupt(args, run, after_rows, sig=signal.SIGINT):
    """:func:`stop_run`'s (returncode, stderr)."""
    out = stop_run(args, run, after_rows, sig)
    return out.code, out.err


def same_tree(a, b):
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return (
            isinstance(b, dict) and a.keys() == b.keys() and all(same_tree(a[k], b[k]) for k in a)
        )
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same_tree(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def _cma_state(blob):
    """What a pickled pycma strategy learned and draws next (its timers measure wall time)."""
    es = pickle.loads(blob)
    return [es.mean, es.sigma, es.C, es.countiter, es.opts["randn"].rng.bit_generator.state]


def same_algorithm(a, b):
    """Checkpointed algorithm states equal (CMA-ES: its strategies' learned state)."""
    if "strategies" in a:
        a, b = dict(a), dict(b)
        ea, eb = ([_cma_state(x) for x in d.pop("strategies")] for d in (a, b))
        for x, y in zip(sum(ea, []), sum(eb, []), strict=True):
            if not (x == y if isinstance(x, dict) else np.array_equal(x, y)):
                return False
    return same_tree(a, b)


def assert_same_run(run, reference, checkpoint=True):
    assert (run / "metrics.csv").read_bytes() == (reference / "metrics.csv").read_bytes()
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (run, reference))
    for key in TIMING:
        sa.pop(key, None), sb.pop(key, None)
    assert sa == sb
    assert not list(run.glob(".*.tmp")), "a temporary file was left behind"
    if not checkpoint:
        return
    ca, cb = (torch.load(d / "checkpoint.pt") for d in (run, reference))  # weights_only=True
    assert same_algorithm(ca["algorithm"], cb["algorithm"])
    assert ca["finished"] and cb["finished"]
    assert not list(run.glob(".*.tmp")), "a temporary file was left behind"


CASES = {
    "bimodal": ({"episodes": 3000, "samples_per_iteration": 100}, 3),
    "pendulum": ({"episodes": 120, "episode_seconds": 2.0, "eval_rollouts": 1}, 2),
    "ball-on-beam": ({"episodes": 15, "eval_episodes": 2}, 2),
    "hockey-sequential": ({"episodes": 12, "episodes_per_iteration": 3}, 2),
    "planar-arm": ({"episodes": 3000, "samples_per_iteration": 50, "algorithm": "cmaes"}, 3),
    "tetherball": ({"episodes": 500, "samples_per_iteration": 50, "versatility_samples": 50}, 3),
}
SLOW = {"hockey-sequential"}  # three pybullet processes: in make test-slow


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in CASES]
)
def test_interrupted_and_resumed_run_equals_the_uninterrupted_run(tmp_path, name):
    """SIGINT to a train.py subprocess mid-run, then --resume: byte-identical ending."""
    if name.startswith("hockey"):
        pytest.importorskip("pybullet")
    options, after = CASES[name]
    options = {**options, "seed": 7}
    hockey = name.startswith("hockey")
    if hockey:
        in_subprocess([name, *cli(options), "--run-dir", str(tmp_path / "full")])
    else:
        in_process(name, tmp_path / "full", **options)
    run = tmp_path / "run"
    code, err = interrupt([name, *cli(options)], run, after)
    assert code == 130, err
    assert "--resume" in err
    ckpt = torch.load(run / "checkpoint.pt")
    total = len(rows(tmp_path / "full"))
    assert 0 < ckpt["iteration"] < total and not ckpt["finished"]
    assert len(rows(run)) == ckpt["iteration"]  # the interrupted run stopped at its checkpoint
    assert not (run / "summary.json").exists()
    if hockey:
        in_subprocess([name, "--resume", str(run)])
    else:
        resume_in_process(name, run)
    assert_same_run(run, tmp_path / "full")


def test_a_ball_on_beam_run_from_before_option_goal_offset_resumes_as_it_was(tmp_path):
    """A run with options linear in the position (the behaviour before option_goal_offset
    existed, whose config.json has no such key) resumed with a bare --resume ends as the
    uninterrupted run: it is not switched to today's default."""
    options = {"episodes": 15, "eval_episodes": 2, "seed": 3}
    in_process("ball-on-beam", tmp_path / "full", option_goal_offset=False, **options)
    run = tmp_path / "run"
    code, err = interrupt(["ball-on-beam", *cli(options), "--no-option-goal-offset"], run, 2)
    assert code == 130, err
    assert "option_goal_offset" not in json.loads((run / "config.json").read_text())
    resume_in_process("ball-on-beam", run)
    assert_same_run(run, tmp_path / "full")


def test_a_pendulum_run_from_before_epsilon_end_resumes_with_the_bound_held(tmp_path):
    """A pendulum run with the KL bound held (the behaviour before epsilon_end existed, whose
    config.json has no such key) resumed with a bare --resume ends as the uninterrupted run,
    at the bound 0.5 in every update: it is not switched to today's schedule."""
    options = {"episodes": 120, "episode_seconds": 2.0, "eval_rollouts": 1, "seed": 4}
    in_process("pendulum", tmp_path / "full", epsilon_end=None, **options)
    run = tmp_path / "run"
    code, err = interrupt(["pendulum", *cli(options), "--epsilon-end", "None"], run, 2)
    assert code == 130, err
    assert "epsilon_end" not in json.loads((run / "config.json").read_text())
    resume_in_process("pendulum", run)
    assert_same_run(run, tmp_path / "full")
    assert [float(r["kl"]) for r in rows(run)] == pytest.approx([0.5] * 6, rel=1e-4)


def test_sigterm_with_sparse_checkpoints_resumes_from_the_last_iteration(tmp_path):
    options = {"episodes": 3000, "samples_per_iteration": 100, "seed": 2}
    in_process("bimodal", tmp_path / "full", **options)
    run = tmp_path / "run"
    args = ["bimodal", *cli(options), "--checkpoint-every", "1000"]
    code, err = interrupt(args, run, 4, sig=signal.SIGTERM)
    assert code == 143, err  # 128 + SIGTERM
    ckpt = torch.load(run / "checkpoint.pt")
    assert ckpt["iteration"] >= 4  # written on the signal, not only every 1000 iterations
    resume_in_process("bimodal", run)
    assert_same_run(run, tmp_path / "full")


def test_resume_after_a_crash_drops_rows_logged_after_the_checkpoint(tmp_path):
    """A run killed hard (no handler runs) resumes from its last checkpoint; metrics.csv is
    cut back to it, so nothing is logged twice."""
    options = {"episodes": 3000, "samples_per_iteration": 100, "seed": 5}
    in_process("bimodal", tmp_path / "full", **options)
    run = tmp_path / "run"
    args = ["bimodal", *cli(options), "--checkpoint-every", "3"]
    code, _ = interrupt(args, run, 5, sig=signal.SIGKILL)
    assert code == -signal.SIGKILL
    ckpt = torch.load(run / "checkpoint.pt")
    assert ckpt["iteration"] % 3 == 0
    resume_in_process("bimodal", run)
    assert_same_run(run, tmp_path / "full")


def test_resuming_a_finished_run_says_so_and_changes_nothing(tmp_path):
    run = tmp_path / "run"
    in_process("bimodal", run, episodes=400)
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    again = train("bimodal", "--resume", str(run), "--no-progress")
    assert again.returncode == 0
    assert "already finished" in again.stderr
    other = train("bimodal", "--resume", str(run), "--epsilon", "0.3", "--no-progress")
    assert other.returncode == 2 and "epsilon (run: 1.0, now: 0.3)" in other.stderr  # not "done"
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before


def test_resuming_with_changed_options_is_refused_and_names_them(tmp_path):
    run = tmp_path / "run"
    in_process("bimodal", run, episodes=400)
    (run / "summary.json").unlink()  # as if stopped before its end
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    p = train("bimodal", "--resume", str(run), "--epsilon", "0.3", "--seed", "9", "--no-progress")
    assert p.returncode == 2
    assert "epsilon (run: 1.0, now: 0.3)" in p.stderr and "seed (run: 0, now: 9)" in p.stderr
    assert {q.name: q.read_bytes() for q in run.iterdir()} == before
    from hireps_torch.experiments import EXPERIMENTS
    from hireps_torch.experiments.checkpoint import saved_config

    with pytest.raises(ValueError, match="'bimodal' run, not 'pendulum'"):
        saved_config(EXPERIMENTS["pendulum"].config, "pendulum", run)  # what --resume parses
    with pytest.raises(ValueError, match="no config.json"):
        saved_config(EXPERIMENTS["bimodal"].config, "bimodal", tmp_path / "nowhere")
    assert {q.name: q.read_bytes() for q in run.iterdir()} == before


def test_seeds_compare_by_the_seeds_they_name():
    """``--seeds 0-2`` and ``--seeds 0,1,2`` name one population: a resume with either agrees;
    other seeds (or another order: another member order) differ."""
    from hireps_torch.experiments.checkpoint import changed_options

    assert changed_options({"seeds": "0-2"}, {"seeds": "0, 1,2"}) == []
    assert changed_options({"seeds": "0-2"}, {"seeds": "0-3"}) == ["seeds (run: '0-2', now: '0-3')"]
    assert changed_options({"seeds": "0-2"}, {"seeds": "2,1,0"}) != []
    assert changed_options({"seeds": "0-2"}, {}) == ["seeds (run: '0-2', now: '<absent>')"]


def test_an_option_left_out_of_config_json_is_shown_at_the_value_it_meant():
    """config.json leaves an option out at its ABSENT_MEANS value (a run written before the
    option existed): a changed one is shown at that value, not as '<absent>'."""
    from hireps_torch.experiments.checkpoint import changed_options

    said = changed_options({"experiment": "pendulum"}, {"experiment": "pendulum", "device": "cuda"})
    assert said == ["device (run: 'cpu', now: 'cuda')"]
    assert changed_options({}, {"device": "cpu:0"}) == []  # the same device


def test_the_final_checkpoint_loads_with_weights_only_and_gives_the_same_actions(tmp_path):
    """A finished run's checkpoint restores the policy: the same noise-free actions."""
    from hireps_torch.experiments import bimodal

    summary = bimodal.run(
        bimodal.BimodalConfig(contextual=True, episodes=600, progress=False, run_dir=tmp_path / "r")
    )
    ckpt = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
    assert ckpt["iteration"] == summary["iterations"] == 3 and ckpt["finished"]
    task = bimodal.ContextualTwoGaussians(width=1.0)  # the config's bump_width
    algo = bimodal._make_algorithm(bimodal.BimodalConfig(contextual=True), task, [0])
    algo.load_state_dict(ckpt["algorithm"])  # a population of one member
    ctx = torch.linspace(-1, 1, 21, dtype=torch.float64)[:, None]  # the evaluation grid
    acts = algo.act(ctx[None])[0]
    assert float(task(ctx, acts).mean()) == pytest.approx(summary["final_return"], abs=0.0)


@pytest.mark.parametrize("keep", [100, 0], ids=["truncated", "empty"])
def test_an_unreadable_checkpoint_is_named_and_nothing_changes(tmp_path, keep):
    run = tmp_path / "run"
    in_process("bimodal", run, episodes=600)
    (run / "summary.json").unlink()  # as if stopped before its end
    ckpt = run / "checkpoint.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:keep])  # a truncated or a zero-byte file
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    with pytest.raises(ValueError, match=f"{ckpt} cannot be read"):
        resume_in_process("bimodal", run)
    assert {q.name: q.read_bytes() for q in run.iterdir()} == before


@pytest.mark.slow
def test_a_run_with_worker_processes_resumes_with_a_warning_and_exits_cleanly(tmp_path):
    """MultiSyncCollector with 2 workers: interrupted, then resumed. The environments live in
    the workers and are not restored: the resumed run finishes, says it is not
    bit-identical, logs every iteration exactly once, and both interpreters exit."""
    args = ["pendulum", "--workers", "2", "--episodes", "80", "--episode-seconds", "2"]
    run = tmp_path / "run"
    code, err = interrupt([*args, "--eval-rollouts", "1"], run, 2)
    assert code == 130, err
    resumed = train("pendulum", "--resume", str(run), "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert "not bit-identical" in resumed.stderr
    assert [int(r["iteration"]) for r in rows(run)] == list(range(1, 5))
    assert (run / "summary.json").is_file()


def test_a_write_that_fails_is_named_and_keeps_the_previous_file(tmp_path):
    from hireps_torch.experiments.rundir import atomic_write

    path = tmp_path / "checkpoint.pt"
    path.write_bytes(b"the previous checkpoint")

    def full_disk(tmp):
        tmp.write_bytes(b"half")
        raise RuntimeError("[enforce fail at inline_container.cc] . unexpected pos")

    with pytest.raises(
        OSError, match=r"cannot write .*checkpoint.pt .*previous checkpoint.pt is kept"
    ):
        atomic_write(path, full_disk)
    assert path.read_bytes() == b"the previous checkpoint"
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]  # no temporary left


def test_a_file_size_limit_during_the_checkpoint_ends_the_run_with_a_message(tmp_path):
    import resource

    run = tmp_path / "run"
    limit = 27 * 1024  # `ulimit -f 27`: config.json and metrics.csv fit, a checkpoint does not

    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            "bimodal",
            "--episodes",
            "400",
            "--run-dir",
            str(run),
            "--no-progress",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        preexec_fn=limited,
    )
    assert out.returncode == 2, out.stderr[-2000:]
    assert "cannot write" in out.stderr and "checkpoint.pt" in out.stderr
    assert "Traceback" not in out.stderr
    assert not any(p.name.endswith(".tmp") for p in run.iterdir())


def _unfinished(tmp_path, name, **options):
    """A finished bimodal run with its summary.json removed: as if stopped before its end."""
    run = tmp_path / name
    in_process("bimodal", run, episodes=600, **options)
    (run / "summary.json").unlink()
    return run


def _files(run):
    return {p.name: (p.read_bytes() if p.is_file() else "dir") for p in run.iterdir()}


def test_a_resume_with_other_torch_threads_than_the_checkpoint_warns_how_to_match(tmp_path):
    """Round-off moves with torch's thread count: a resume computing with another one than the
    run was written with says so; the same count is silent (before: nothing said, and the run
    went another way)."""
    ours = torch.get_num_threads()
    for name, threads in (("other", ours + 6), ("same", ours)):
        run = _unfinished(tmp_path, name)
        ckpt = torch.load(run / "checkpoint.pt")
        assert ckpt["threads"] == ours
        ckpt["threads"] = threads
        torch.save(ckpt, run / "checkpoint.pt")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            resume_in_process("bimodal", run)
        said = [str(w.message) for w in caught if "thread(s)" in str(w.message)]
        if threads == ours:
            assert said == []
        else:
            assert len(said) == 1 and f"computed with {threads} thread(s)" in said[0]
            assert f"this run computes with {ours}" in said[0] and "OMP_NUM_THREADS" in said[0]


def test_a_checkpoint_of_another_run_is_refused_naming_what_differs(tmp_path):
    run, other = _unfinished(tmp_path, "run"), _unfinished(tmp_path, "other", seed=7)
    (run / "checkpoint.pt").write_bytes((other / "checkpoint.pt").read_bytes())
    before = _files(run)
    with pytest.raises(ValueError, match=r"seed \(checkpoint.pt: 7, config.json: 0\)"):
        resume_in_process("bimodal", run)
    assert _files(run) == before


def test_a_config_edited_after_the_interrupt_is_refused_naming_what_differs(tmp_path):
    run = _unfinished(tmp_path, "run")
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "epsilon": 0.3}))
    before = _files(run)
    p = train("bimodal", "--resume", str(run), "--no-progress")
    assert p.returncode == 2
    assert "epsilon (checkpoint.pt: 1.0, config.json: 0.3)" in p.stderr
    assert _files(run) == before


@pytest.mark.parametrize("damage", ["deleted", "a directory"])
def test_rows_without_a_checkpoint_are_refused_and_kept(tmp_path, damage):
    run = _unfinished(tmp_path, "run")
    (run / "checkpoint.pt").unlink()
    if damage == "a directory":
        (run / "checkpoint.pt").mkdir()
    before = _files(run)
    what = "is not a file" if damage == "a directory" else r"holds 3 row\(s\) but there is no"
    with pytest.raises(ValueError, match=what):
        resume_in_process("bimodal", run)
    assert _files(run) == before
    assert len(rows(run)) == 3


def test_a_run_directory_has_one_writer_and_a_crash_leaves_no_lock(tmp_path):
    """A resume of a directory that another process is writing is refused and changes
    nothing; once that process is gone (here: its lock dropped, as a crash drops it) the
    resume goes ahead."""
    from hireps_torch.experiments.rundir import DirectoryLock

    run = _unfinished(tmp_path, "run")
    before = _files(run)
    held = DirectoryLock(run)  # what a running train.py holds
    p = train("bimodal", "--resume", str(run), "--no-progress")
    assert p.returncode == 2
    assert "is being written by another process" in p.stderr
    assert _files(run) == before
    with pytest.raises(BlockingIOError, match="being written by another process"):
        resume_in_process("bimodal", run)
    assert _files(run) == before
    held.release()
    resume_in_process("bimodal", run)
    assert (run / "summary.json").is_file()
    assert [int(r["iteration"]) for r in rows(run)] == [1, 2, 3]


def test_two_resumes_at_once_log_every_iteration_once(tmp_path):
    """Two ``--resume`` of the same directory started together: one runs, the other is
    refused; metrics.csv holds every iteration once, in order."""
    run = _unfinished(tmp_path, "run", samples_per_iteration=20)
    (run / "checkpoint.pt").unlink()
    (run / "metrics.csv").unlink()
    cmd = [sys.executable, str(ROOT / "train.py"), "bimodal", "--resume", str(run), "--no-progress"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = [
        subprocess.Popen(cmd, cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True) for _ in "ab"
    ]
    outs = [(p.wait(timeout=240), p.stderr.read()) for p in procs]
    refused = [err for code, err in outs if code == 2]
    late = [err for code, err in outs if code == 0 and "already finished" in err]
    assert sorted(code for code, _ in outs) in ([0, 2], [0, 0]), outs
    assert len(refused + late) == 1, outs  # the other one ran it
    assert all("being written by another process" in err for err in refused), outs
    assert [int(r["iteration"]) for r in rows(run)] == list(range(1, 31))


def test_a_resume_of_a_directory_another_process_writes_is_refused_before_reading_it(tmp_path):
    # the other writer may be between two writes (rows logged, checkpoint not yet): the
    # refusal must be the lock's, not a complaint about what it reads
    from hireps_torch.experiments.rundir import DirectoryLock

    run = _unfinished(tmp_path, "run", samples_per_iteration=20)
    (run / "checkpoint.pt").unlink()  # as if the writer had logged rows and not checkpointed
    before = _files(run)
    held = DirectoryLock(run)
    try:
        with pytest.raises(BlockingIOError, match="being written by another process"):
            resume_in_process("bimodal", run)
    finally:
        held.release()
    assert _files(run) == before
    with pytest.raises(ValueError, match="no .*checkpoint.pt to continue them from"):
        resume_in_process("bimodal", run)  # the lock released: the files' own complaint


POPULATIONS = {
    "pendulum": ({"episodes": 120, "episode_seconds": 1.0, "eval_rollouts": 1}, 2),
    "planar-arm": ({"episodes": 2000, "samples_per_iteration": 50}, 3),
    "ball-on-beam": ({"episodes": 15, "eval_episodes": 2}, 2),
    "hockey-sequential": ({"episodes": 12, "episodes_per_iteration": 3}, 2),
}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in POPULATIONS]
)
def test_an_interrupted_and_resumed_population_equals_the_uninterrupted_one(tmp_path, name):
    """SIGINT to a population of three seeds mid-run, then --resume of its directory: every
    member's metrics.csv, summary.json (but its wall time) and final policy, and the
    population's checkpoint, as without the interruption."""
    hockey = name.startswith("hockey")
    if hockey:
        pytest.importorskip("pybullet")
    options, after = POPULATIONS[name]
    options = {**options, "seeds": "4,7,9"}
    if hockey:
        in_subprocess([name, *cli(options), "--run-dir", str(tmp_path / "full")])
    else:
        in_process(name, tmp_path / "full", **options)
    run = tmp_path / "run"
    out = stop_run([name, *cli(options)], run, after, watch=run / "seed9" / "metrics.csv")
    assert out.code == 130, out.err
    assert f"--resume {run}" in out.err
    ckpt = torch.load(run / "checkpoint.pt")
    assert 0 < ckpt["iteration"] < len(rows(tmp_path / "full" / "seed4"))
    assert not (run / "summary.json").exists()
    if hockey:
        in_subprocess([name, "--resume", str(run)])
    else:
        resume_in_process(name, run)
    for seed in (4, 7, 9):
        assert_same_run(run / f"seed{seed}", tmp_path / "full" / f"seed{seed}", checkpoint=False)
    ca, cb = (torch.load(d / "checkpoint.pt") for d in (run, tmp_path / "full"))
    assert same_tree(ca["algorithm"], cb["algorithm"]) and ca["finished"]
    assert (run / "population.md").is_file()
    ends = []  # the population's summary.json, but its wall time and its directory's name
    for d in (run, tmp_path / "full"):
        end = json.loads((d / "summary.json").read_text())
        for key in TIMING:
            end.pop(key, None)
        ends.append(json.dumps(end).replace(str(d), "<run>"))
    assert ends[0] == ends[1]


def test_resuming_a_member_of_a_population_points_to_the_population(tmp_path):
    """--resume of a member directory (it has no checkpoint of its own) names the
    population's directory to resume instead, and changes nothing."""
    run = tmp_path / "pop"
    args = ["bimodal", "--seeds", "0-1", "--episodes", "200000", "--samples-per-iteration", "20"]
    out = stop_run(args, run, 2, watch=run / "seed1" / "metrics.csv")
    assert out.code == 130, out.err
    before = _files(run), _files(run / "seed1")
    with pytest.raises(ValueError, match=rf"member of the population in .*{run.name}; resume"):
        resume_in_process("bimodal", run / "seed1")
    assert (_files(run), _files(run / "seed1")) == before
    # stopped before the population's first checkpoint (its config.json names the seeds): the
    # member is refused all the same (it ran on as a run of its own, and the population was lost)
    from hireps_torch.experiments import EXPERIMENTS
    from hireps_torch.experiments.checkpoint import saved_config
    from hireps_torch.experiments.runner import resume_point

    def resume(d):
        return resume_point(
            EXPERIMENTS["bimodal"], saved_config(EXPERIMENTS["bimodal"].config, "bimodal", d)
        )

    for name in ("checkpoint.pt", "seed0/metrics.csv", "seed1/metrics.csv"):
        (run / name).unlink()
    with pytest.raises(ValueError, match=rf"member of the population in .*{run.name}; resume"):
        resume(run / "seed1")
    point = resume(run)
    assert point is not None and point.checkpoint is None  # the population starts over
    # a run of seed 7 moved into the population's directory is no member of it: named as such
    shutil.copytree(run / "seed1", run / "seed7")
    config = json.loads((run / "seed7" / "config.json").read_text())
    (run / "seed7" / "config.json").write_text(json.dumps(config | {"seed": 7}))
    with pytest.raises(ValueError, match=r"seed7 is inside the population .* not one of its"):
        resume(run / "seed7")


def test_a_resume_rewrites_a_deleted_member_directory_and_a_copied_member_is_named(tmp_path):
    """A member directory deleted from an unfinished population comes back on --resume with
    its config.json and metrics.csv; a member copied out of its population is refused by
    load_run with the reason (its policy is in the population's checkpoint)."""
    from hireps_torch import load_run

    run = tmp_path / "pop"
    in_process("bimodal", run, seeds="0-1", episodes=600)
    kept = {n: (run / "seed1" / n).read_bytes() for n in ("config.json", "metrics.csv")}
    copy = tmp_path / "copy"
    shutil.copytree(run / "seed1", copy)
    with pytest.raises(ValueError, match="member's policy is in its population's checkpoint"):
        load_run(copy)
    for summary in run.rglob("summary.json"):
        summary.unlink()  # as if stopped before its end
    shutil.rmtree(run / "seed1")
    resume_in_process("bimodal", run)
    assert {n: (run / "seed1" / n).read_bytes() for n in kept} == kept
    iterations = len(kept["metrics.csv"].splitlines()) - 1
    assert load_run(run / "seed1").iteration == load_run(run / "seed0").iteration == iterations


def test_ctrl_c_while_the_command_starts_ends_it_without_a_traceback(tmp_path):
    """SIGINT while train.py still imports (or any time before its first iteration): the
    one-line message and exit code 130, as later."""
    p = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), "pendulum", "--run-dir", str(tmp_path / "r")],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    time.sleep(1.0)  # importing torch (``import hireps_torch`` alone takes ~0.2 s)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=240)
    assert p.returncode == 130, err[-2000:]
    assert "Traceback" not in err and "interrupted" in err


WORKER_RUNS = {
    "pendulum": "pendulum --workers 2 --episodes 20000 --episode-seconds 1 --eval-rollouts 2",
    "hockey-local": "hockey-sequential --workers 2 --episodes 3000 --episodes-per-iteration 6",
    "hockey-ray": "hockey-sequential --workers 2 --episodes 3000 --episodes-per-iteration 6 "
    "--backend ray",
}


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(WORKER_RUNS))
def test_ctrl_c_of_a_run_with_workers_ends_it_cleanly_every_time(tmp_path, kind):
    """SIGINT to the process group (what Ctrl-C in a terminal sends) of a run with two
    workers (TorchRL collector workers, a local process pool, Ray tasks), three times: each
    ends within seconds with the checkpoint written, no traceback and no process left
    (before: hangs, or TorchRL's "At least one process failed" when a worker died of it)."""
    for attempt in range(3):
        run = tmp_path / f"run{attempt}"
        out = stop_run(WORKER_RUNS[kind].split(), run, 1, group=True)
        err = out.err
        assert out.seconds < 30, err
        assert out.code == 130, err
        assert "Traceback" not in err and "checkpoint written" in err, err
        assert torch.load(run / "checkpoint.pt")["iteration"] >= 1
        assert_no_process_left(out.pid)


def assert_no_process_left(group):
    """No process of process group ``group`` is alive within 10 s."""
    for _ in range(50):
        left = subprocess.run(["pgrep", "-g", str(group)], capture_output=True, text=True)
        if not left.stdout.split():
            return
        time.sleep(0.2)
    raise AssertionError(f"processes left behind: {left.stdout}")


def _spawned_children(pid):
    """The multiprocessing workers (spawned) of process ``pid``."""
    found = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            spawned = b"spawn_main" in (proc / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid and spawned:
            found.append(int(proc.name))
    return found


@pytest.mark.slow
def test_ctrl_c_while_the_collectors_workers_start_ends_the_run_cleanly(tmp_path):
    """Ctrl-C (SIGINT to the group) while ``pendulum --workers 2`` waits for its collector's
    workers to start (they import torch for seconds): exit 130 without a traceback, no process
    left (before: the parent ignored SIGINT then, and the run played on to its end)."""
    run = tmp_path / "run"

    def starting(p):
        return len(_spawned_children(p.pid)) >= 2

    out = stop_run(WORKER_RUNS["pendulum"].split(), run, 0, group=True, when=starting)
    assert not (run / "metrics.csv").exists()  # it was still starting
    assert out.code == 130, out.err
    assert "Traceback" not in out.err and "interrupted" in out.err, out.err
    assert_no_process_left(out.pid)


@pytest.mark.parametrize(
    "damage",
    ["rows cut", "iteration ahead", "iteration negative", "iteration text"],
)
def test_a_checkpoint_whose_rows_and_iteration_disagree_is_refused(tmp_path, damage):
    run = _unfinished(tmp_path, "run")
    path = run / "checkpoint.pt"
    ckpt = torch.load(path)
    if damage == "rows cut":
        ckpt["rows"] = []
    else:
        ckpt["iteration"] = {"iteration ahead": 7, "iteration negative": -1}.get(damage, "x")
    torch.save(ckpt, path)
    before = _files(run)
    with pytest.raises(ValueError, match=f"{path} is damaged"):
        resume_in_process("bimodal", run)
    assert _files(run) == before


@pytest.mark.parametrize("kind", ["not utf-8", "a directory"])
def test_a_damaged_metrics_csv_is_named_on_resume(tmp_path, kind):
    run = _unfinished(tmp_path, "run")
    (run / "checkpoint.pt").unlink()
    (run / "metrics.csv").unlink()
    if kind == "a directory":
        (run / "metrics.csv").mkdir()
    else:
        (run / "metrics.csv").write_bytes(b"a\n\xff\xfe\n")
    before = _files(run)
    p = train("bimodal", "--resume", str(run), "--no-progress")
    assert p.returncode == 2, p.stderr
    assert "metrics.csv" in p.stderr and "Traceback" not in p.stderr
    assert _files(run) == before


def test_a_run_dir_that_is_a_dangling_link_is_named(tmp_path):
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "missing")
    p = train("bimodal", "--episodes", "400", "--run-dir", str(link), "--no-progress")
    assert p.returncode == 2
    assert "is a link to" in p.stderr and "which does not exist" in p.stderr
    assert not (tmp_path / "missing").exists()


def test_a_signal_while_the_stop_handler_is_installed_is_not_lost(monkeypatch):
    """A SIGINT landing after stop_on_signals began but before its handler is in place goes to
    the early handler (EARLY); the stop request must still see it."""
    from hireps_torch.experiments import checkpoint

    install = signal.signal

    def signal_lands_first(sig, handler):
        if sig == signal.SIGINT:
            checkpoint.EARLY.signame = "SIGINT"  # what record_early_stops' handler does
        return install(sig, handler)

    monkeypatch.setattr(checkpoint.EARLY, "signame", None)
    monkeypatch.setattr(checkpoint.signal, "signal", signal_lands_first)
    with checkpoint.stop_on_signals() as stop:
        assert stop.signame == "SIGINT"


def test_a_stop_asked_from_another_thread_is_taken_at_the_boundary_and_a_signal_after_it_is_first():
    """request_stop (a sweep worker's watcher thread) asks for what a first signal asks for; a
    SIGINT after it is still a first (no stop at once), a second one stops at once."""
    from hireps_torch.experiments import checkpoint

    with checkpoint.stop_on_signals() as stop:
        assert checkpoint.ACTIVE is stop
        watcher = threading.Thread(target=checkpoint.request_stop, args=("the sweep's stop",))
        watcher.start()
        watcher.join()
        assert stop.signame == "the sweep's stop"
        os.kill(os.getpid(), signal.SIGINT)  # handled here: a first signal only asks to stop
        with pytest.raises(KeyboardInterrupt, match="second SIGINT: stopping now"):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)  # the handler runs at the next bytecode
    assert checkpoint.ACTIVE is None


def test_a_pools_run_stops_at_its_boundary_when_the_pool_stops(tmp_path):
    """A run in a worker process that never saw the Ctrl-C stops at its next iteration boundary
    once the pool's owner stops the pool (a sweep's Ctrl-C, SIGTERM or end), with its
    checkpoint, and says so; the worker then ends (the sweep's kill -9: the slow sweep test)."""
    from hireps_torch.experiments import sweep
    from hireps_torch.experiments.pool import LocalPool

    options = {"episodes": 400000, "samples_per_iteration": 20}
    run = sweep.SweepRun("bimodal", "default", 0, options, tmp_path / "seed0")
    metrics = tmp_path / "seed0" / "metrics.csv"
    with LocalPool(1, runs=True) as pool:
        future = pool.submit(sweep.run_one, run)
        deadline = time.time() + 120
        while time.time() < deadline and not (
            metrics.exists() and metrics.read_text().count("\n") > 2
        ):
            time.sleep(0.05)
        pool.stop()
        with pytest.raises(
            KeyboardInterrupt, match=r"the pool's stop: stopped after iteration \d+;"
        ):
            future.result(timeout=120)
    assert (tmp_path / "seed0" / "checkpoint.pt").is_file()


def test_a_population_with_an_edited_or_linked_member_directory_is_refused_and_kept(tmp_path):
    """--resume of a population refuses a member whose config.json is no longer its own
    (which load_run would refuse after) and a member directory that is a link (its files would
    be written into the directory it points to); neither directory changes."""
    run, other = tmp_path / "pop", tmp_path / "other"
    for d, seeds in ((run, "0-1"), (other, "3-4")):
        in_process("bimodal", d, seeds=seeds, episodes=600)
        for summary in d.rglob("summary.json"):
            summary.unlink()  # as if stopped before its end
    config = run / "seed1" / "config.json"
    config.write_text(config.read_text().replace('"n_options": 10', '"n_options": 4'))
    before = _files(run / "seed1")
    with pytest.raises(ValueError, match=r"seed1/config.json is not its member's config: n_opt"):
        resume_in_process("bimodal", run)
    assert _files(run / "seed1") == before
    config.write_text("{")
    before = _files(run / "seed1")
    with pytest.raises(ValueError, match=r"cannot be read as JSON .* delete it to have it written"):
        resume_in_process("bimodal", run)
    assert _files(run / "seed1") == before
    shutil.rmtree(run / "seed1")
    (run / "seed1").symlink_to(other / "seed3")
    before = _files(other / "seed3")
    with pytest.raises(ValueError, match=r"member directory .*seed1 is a link to .*seed3"):
        resume_in_process("bimodal", run)
    assert _files(other / "seed3") == before


def test_options_that_do_not_change_a_run_may_differ_on_resume(tmp_path):
    # hockey's episodes are played by index (any number of workers gives the same run), a CPU
    # is a CPU whatever its index; the pendulum's collector workers draw differently: refused
    import json

    from hireps_torch.experiments import EXPERIMENTS
    from hireps_torch.experiments.options import config_dict
    from hireps_torch.experiments.runner import resume_point

    def started(name, **options):
        cfg = EXPERIMENTS[name].config(run_dir=tmp_path / name, progress=False, **options)
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.json").write_text(json.dumps(config_dict(name, cfg)))
        return lambda **now: resume_point(
            EXPERIMENTS[name],
            EXPERIMENTS[name].config(resume=tmp_path / name, progress=False, **now),
        )

    hockey = started("hockey-sequential", workers=1)
    assert hockey(workers=2).checkpoint is None
    pendulum = started("pendulum", workers=1)
    assert pendulum(device="cpu:0").checkpoint is None
    with pytest.raises(ValueError, match=r"workers \(run: 1, now: 2\)"):
        pendulum(workers=2)


def test_a_run_killed_before_its_first_checkpoint_starts_over_and_ends_as_a_fresh_run(tmp_path):
    """kill -9 before the first checkpoint was due (--checkpoint-every 1000): --resume starts
    the run over, says so, and ends as an uninterrupted run; atomic_write's temporary files of
    the killed session go (before: refused, 'restore the checkpoint', with none ever written)."""
    options = {"episodes": 3000, "samples_per_iteration": 100, "seed": 4}
    in_process("bimodal", tmp_path / "full", **options)
    run = tmp_path / "run"
    stopped = stop_run(
        ["bimodal", *cli(options), "--checkpoint-every", "1000"], run, 3, signal.SIGKILL
    )
    assert stopped.code == -signal.SIGKILL
    assert not (run / "checkpoint.pt").exists() and len(rows(run)) >= 3
    stale = run / ".checkpoint.pt.a1b2c3d4.tmp"
    stale.write_bytes(b"half a checkpoint")
    with pytest.warns(UserWarning, match=r"no checkpoint.pt .* starts over, playing the \d+"):
        resume_in_process("bimodal", run)
    assert not stale.exists()
    assert_same_run(run, tmp_path / "full")


def test_a_checkpoint_holds_each_members_metrics_as_one_text(tmp_path):
    """The rows go into a checkpoint as metrics.csv's text (before: as dicts, whose pickling
    made every checkpoint of a long run slower: 23.5 ms at 2000 rows against 1.4 ms without)."""
    run = tmp_path / "run"
    in_process("bimodal", run, episodes=400, samples_per_iteration=20)
    ckpt = torch.load(run / "checkpoint.pt")
    assert ckpt["format"] == 3 and ckpt["iteration"] == 20
    assert ckpt["rows"] == [(run / "metrics.csv").read_bytes().decode()]
    ckpt["rows"] = ["iteration,kl\r\n1,0.5,7\r\n"]  # a row longer than the header
    torch.save(ckpt, run / "checkpoint.pt")
    (run / "summary.json").unlink()
    with pytest.raises(ValueError, match="checkpoint.pt is damaged: its metrics row 1 does not"):
        resume_in_process("bimodal", run)


def test_a_checkpoint_of_format_2_with_its_rows_inside_resumes_as_before(tmp_path):
    """Run directories written before the checkpoints counted their rows still resume."""
    options = {"episodes": 3000, "samples_per_iteration": 100, "seed": 5}
    in_process("bimodal", tmp_path / "full", **options)
    run = tmp_path / "run"
    code, err = interrupt(["bimodal", *cli(options)], run, 4)
    assert code == 130, err
    path = run / "checkpoint.pt"
    ckpt = torch.load(path)
    kept = list(csv.DictReader(ckpt["rows"][0].splitlines()))
    assert len(kept) == ckpt["iteration"]
    ckpt["rows"] = [[{k: _typed(v) for k, v in r.items()} for r in kept]]
    ckpt["format"] = 2
    torch.save(ckpt, path)
    (run / "metrics.csv").write_text("iteration\n")  # format 2 rewrites it from its rows
    resume_in_process("bimodal", run)
    assert_same_run(run, tmp_path / "full")


def _typed(text):
    if text in ("True", "False"):
        return text == "True"
    try:
        return int(text)
    except ValueError:
        return float(text)


def test_a_run_directory_that_cannot_be_written_is_named_on_resume(tmp_path, monkeypatch):
    """A resume into a directory where no file can be made (read-only, immutable) names the
    file it would write, not the hidden temporary name (before: '[Errno 1] Operation not
    permitted: .../.metrics.csv.i1fdoaj7.tmp'), and changes nothing."""
    import tempfile

    run = _unfinished(tmp_path, "run")
    before = _files(run)

    def refuse(*args, **kwargs):
        raise PermissionError(1, "Operation not permitted", kwargs.get("dir"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(OSError, match=r"cannot write .*metrics.csv \(Operation not permitted\)"):
        resume_in_process("bimodal", run)
    monkeypatch.undo()
    assert _files(run) == before


def test_a_second_sigterm_stops_at_once_and_says_it_was_sigterm():
    """A second SIGTERM ends the run as one (hireps-train exits 143, as for the first), not as
    a Ctrl-C (130 before)."""
    from hireps_torch.experiments import checkpoint

    with checkpoint.stop_on_signals():
        os.kill(os.getpid(), signal.SIGTERM)  # a first only asks to stop
        with pytest.raises(KeyboardInterrupt, match="second SIGTERM: stopping now") as second:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)  # the handler runs at the next bytecode
    assert second.value.signame == "SIGTERM"
