"""Checkpoints and resume: a run interrupted by SIGINT/SIGTERM at any iteration and resumed
ends exactly as the uninterrupted run (metrics.csv, summary.json, final policy)."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

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


def rows(run):
    return list(csv.DictReader((run / "metrics.csv").open()))


def interrupt(args, run, after_rows, sig=signal.SIGINT):
    """Start ``train.py args --run-dir run``; once metrics.csv holds ``after_rows`` rows,
    send ``sig``. Returns (returncode, stderr)."""
    p = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *args, "--run-dir", str(run), "--no-progress"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    deadline = time.time() + 240
    while p.poll() is None and time.time() < deadline:
        m = run / "metrics.csv"
        if m.exists() and len(m.read_text().splitlines()) > after_rows:
            break
        time.sleep(0.002)
    p.send_signal(sig)
    _, err = p.communicate(timeout=240)
    return p.returncode, err


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


def assert_same_run(run, reference):
    assert (run / "metrics.csv").read_bytes() == (reference / "metrics.csv").read_bytes()
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (run, reference))
    for key in TIMING:
        sa.pop(key, None), sb.pop(key, None)
    assert sa == sb
    ca, cb = (torch.load(d / "checkpoint.pt") for d in (run, reference))  # weights_only=True
    assert same_tree(ca["algorithm"], cb["algorithm"])
    assert ca["finished"] and cb["finished"]
    assert not list(run.glob(".*.tmp")), "a temporary file was left behind"


CASES = {
    "bimodal": (["bimodal", "--episodes", "3000", "--samples-per-iteration", "100"], 3),
    "pendulum": (["pendulum", "--episodes", "160", "--eval-rollouts", "3"], 3),
    "ball-on-beam": (["ball-on-beam", "--eval-episodes", "2"], 4),
    "hockey-sequential": (
        ["hockey-sequential", "--episodes", "100", "--episodes-per-iteration", "10"],
        2,
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_interrupted_and_resumed_run_equals_the_uninterrupted_run(tmp_path, name):
    if name.startswith("hockey"):
        pytest.importorskip("pybullet")
    args, after = CASES[name]
    args = [*args, "--seed", "7"]
    full = train(*args, "--run-dir", str(tmp_path / "full"), "--no-progress")
    assert full.returncode == 0, full.stderr
    run = tmp_path / "run"
    code, err = interrupt(args, run, after)
    assert code == 130, err
    assert "--resume" in err
    ckpt = torch.load(run / "checkpoint.pt")
    total = len(rows(tmp_path / "full"))
    assert 0 < ckpt["iteration"] < total and not ckpt["finished"]
    assert len(rows(run)) == ckpt["iteration"]  # the interrupted run stopped at its checkpoint
    assert not (run / "summary.json").exists()
    resumed = train(name, "--resume", str(run), "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert_same_run(run, tmp_path / "full")


def test_sigterm_with_sparse_checkpoints_resumes_from_the_last_iteration(tmp_path):
    args = ["bimodal", "--episodes", "3000", "--samples-per-iteration", "100", "--seed", "2"]
    full = train(*args, "--run-dir", str(tmp_path / "full"), "--no-progress")
    assert full.returncode == 0, full.stderr
    run = tmp_path / "run"
    code, err = interrupt([*args, "--checkpoint-every", "1000"], run, 4, sig=signal.SIGTERM)
    assert code == 130, err
    ckpt = torch.load(run / "checkpoint.pt")
    assert ckpt["iteration"] >= 4  # written on the signal, not only every 1000 iterations
    resumed = train("bimodal", "--resume", str(run), "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert_same_run(run, tmp_path / "full")


def test_resume_after_a_crash_drops_rows_logged_after_the_checkpoint(tmp_path):
    """A run killed hard (no handler runs) resumes from its last checkpoint; metrics.csv is
    cut back to it, so nothing is logged twice."""
    args = ["bimodal", "--episodes", "3000", "--samples-per-iteration", "100", "--seed", "5"]
    full = train(*args, "--run-dir", str(tmp_path / "full"), "--no-progress")
    run = tmp_path / "run"
    code, _ = interrupt([*args, "--checkpoint-every", "3"], run, 5, sig=signal.SIGKILL)
    assert code == -signal.SIGKILL
    ckpt = torch.load(run / "checkpoint.pt")
    assert ckpt["iteration"] % 3 == 0
    resumed = train("bimodal", "--resume", str(run), "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert_same_run(run, tmp_path / "full")
    assert full.returncode == 0


def test_resuming_a_finished_run_says_so_and_changes_nothing(tmp_path):
    run = tmp_path / "run"
    assert (
        train("bimodal", "--episodes", "400", "--run-dir", str(run), "--no-progress").returncode
        == 0
    )
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    again = train("bimodal", "--resume", str(run), "--no-progress")
    assert again.returncode == 0
    assert "already finished" in again.stderr
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before


def test_resuming_with_changed_options_is_refused_and_names_them(tmp_path):
    run = tmp_path / "run"
    code, err = interrupt(
        ["bimodal", "--episodes", "3000", "--samples-per-iteration", "100"], run, 2
    )
    assert code == 130, err
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    p = train("bimodal", "--resume", str(run), "--epsilon", "0.3", "--seed", "9", "--no-progress")
    assert p.returncode == 2
    assert "epsilon (run: 1.0, now: 0.3)" in p.stderr and "seed (run: 0, now: 9)" in p.stderr
    assert {q.name: q.read_bytes() for q in run.iterdir()} == before
    wrong = train("pendulum", "--resume", str(run), "--no-progress")
    assert wrong.returncode == 2 and "'bimodal' run, not 'pendulum'" in wrong.stderr
    missing = train("bimodal", "--resume", str(tmp_path / "nowhere"), "--no-progress")
    assert missing.returncode == 2 and "no config.json" in missing.stderr


def test_the_final_checkpoint_loads_with_weights_only_and_gives_the_same_actions(tmp_path):
    """A finished run's checkpoint restores the policy: the same noise-free actions."""
    from experiments import bimodal

    summary = bimodal.run(
        bimodal.BimodalConfig(contextual=True, episodes=600, progress=False, run_dir=tmp_path / "r")
    )
    ckpt = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
    assert ckpt["iteration"] == summary["iterations"] == 3 and ckpt["finished"]
    task = bimodal.ContextualTwoGaussians(width=1.0)  # the config's bump_width
    algo = bimodal._make_algorithm(bimodal.BimodalConfig(contextual=True), task)
    algo.load_state_dict(ckpt["algorithm"])
    ctx = torch.linspace(-1, 1, 21, dtype=torch.float64)[:, None]  # the evaluation grid
    assert float(task(ctx, algo.act(ctx)).mean()) == pytest.approx(summary["final_return"], abs=0.0)


def test_checkpoint_every_must_be_positive(tmp_path):
    p = train(
        "bimodal", "--checkpoint-every", "0", "--run-dir", str(tmp_path / "r"), "--no-progress"
    )
    assert p.returncode == 2 and "checkpoint_every must be >= 1, got 0" in p.stderr
    assert not (tmp_path / "r").exists()


def test_an_unreadable_checkpoint_is_named_and_nothing_changes(tmp_path):
    run = tmp_path / "run"
    code, err = interrupt(
        ["bimodal", "--episodes", "3000", "--samples-per-iteration", "100"], run, 2
    )
    assert code == 130, err
    ckpt = run / "checkpoint.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:100])  # a truncated file
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    p = train("bimodal", "--resume", str(run), "--no-progress")
    assert p.returncode == 2 and f"{ckpt} cannot be read" in p.stderr
    assert {q.name: q.read_bytes() for q in run.iterdir()} == before


def test_a_seed_out_of_range_is_refused(tmp_path):
    p = train("bimodal", "--seed", str(2**70), "--run-dir", str(tmp_path / "r"), "--no-progress")
    assert p.returncode == 2 and "seed must be an integer in" in p.stderr
    assert not (tmp_path / "r").exists()


def test_a_run_with_worker_processes_resumes_with_a_warning(tmp_path):
    """The environments live in the workers and are not restored: the resumed run finishes,
    says it is not bit-identical, and logs every iteration exactly once."""
    args = ["pendulum", "--workers", "2", "--episodes", "160", "--eval-rollouts", "2"]
    run = tmp_path / "run"
    code, err = interrupt(args, run, 2)
    assert code == 130, err
    resumed = train("pendulum", "--resume", str(run), "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert "not bit-identical" in resumed.stderr
    assert [int(r["iteration"]) for r in rows(run)] == list(range(1, 9))
