"""train.py as a user runs it (a subprocess that writes a run directory), and the experiments
package behind it."""

import csv
import dataclasses
import json
import platform
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def train(*args, cwd=ROOT):
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


def check_run_dir(run, files=(), keys=()):
    """Every run directory holds these files and summary keys; returns the summary."""
    for name in (
        "config.json",
        "metrics.csv",
        "summary.json",
        "checkpoint.pt",
        "learning_curve.png",
        *files,
    ):
        assert (run / name).is_file(), name
    summary = json.loads((run / "summary.json").read_text())
    for key in ("experiment", "seed", "episodes", "final_return", "wall_seconds", *keys):
        assert key in summary
    return summary


def test_bimodal_subprocess_writes_the_run_directory(tmp_path):
    run = tmp_path / "run"
    p = train("bimodal", "--episodes", "600", "--run-dir", str(run), "--no-progress")
    assert p.returncode == 0, p.stderr
    summary = check_run_dir(run, files=("options.png",))
    assert summary["experiment"] == "bimodal" and summary["episodes"] == 600
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    assert len(rows) == 3  # 600 episodes / 200 per iteration
    for key in ("eta", "xi", "kl", "cross_entropy", "effective_sample_size", "policy_entropy"):
        assert key in rows[0]
    assert json.loads((run / "config.json").read_text())["episodes"] == 600
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert "policy" in ckpt["algorithm"]
    assert (run / "learning_curve.png").read_bytes()[:4] == b"\x89PNG"


def in_process(name, tmp_path, run_name, **options):
    """Run experiment ``name`` in this process (no interpreter start-up) into tmp_path/run_name."""
    from hireps_torch.experiments import EXPERIMENTS

    config_cls, run = EXPERIMENTS[name].config, EXPERIMENTS[name].run
    return run(config_cls(progress=False, run_dir=tmp_path / run_name, **options))


def test_same_seed_gives_the_same_run(tmp_path):
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        in_process("bimodal", tmp_path, name, episodes=600, seed=seed, contextual=True)
    a, b, c = ((tmp_path / n / "metrics.csv").read_text() for n in "abc")
    assert a == b and c != a


def test_existing_run_directory_is_never_overwritten(tmp_path):
    run = tmp_path / "mine"
    run.mkdir()
    (run / "notes.txt").write_text("my notes")
    p = train("bimodal", "--episodes", "200", "--run-dir", str(run), "--no-progress")
    assert p.returncode == 2
    assert "already exists" in p.stderr
    assert (run / "notes.txt").read_text() == "my notes"
    assert sorted(x.name for x in run.iterdir()) == ["notes.txt"]


@pytest.mark.parametrize(
    "options,message",
    [
        ({"samples_per_iteration": 1}, "samples_per_iteration must be in 2..1000000000, got 1"),
        ({"episodes": 50}, "episodes (50) must be at least samples_per_iteration"),
        # they were a torch overflow (10**23 samples) and ~5e20 iterations (10**23 episodes)
        (
            {"samples_per_iteration": 10**23, "episodes": 10**23},
            f"samples_per_iteration must be in 2..1000000000, got {10**23}",
        ),
        ({"episodes": 10**23}, f"episodes must be in 1..1000000000, got {10**23}"),
    ],
    ids=["samples 1", "episodes < samples", "samples 1e23", "episodes 1e23"],
)
def test_bad_config_gives_a_clear_error(tmp_path, options, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        in_process("bimodal", tmp_path, "r", **options)
    assert not (tmp_path / "r").exists()


def test_bad_option_on_the_command_line_exits_with_code_2_and_the_message(tmp_path):
    p = train("bimodal", "--epsilon", "-1", "--run-dir", str(tmp_path / "r"), "--no-progress")
    assert p.returncode == 2
    assert "epsilon must be finite and > 0, got -1.0" in p.stderr


def test_pendulum_subprocess_writes_the_run_directory(tmp_path):
    run = tmp_path / "run"
    p = train(
        "pendulum",
        "--episodes",
        "40",
        "--episode-seconds",
        "3",
        "--eval-rollouts",
        "5",
        "--run-dir",
        str(run),
        "--no-progress",
    )
    assert p.returncode == 0, p.stderr
    summary = check_run_dir(run, keys=("success_rate", "time_to_upright"))
    assert summary["episodes"] == 40
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    assert len(rows) == 2
    assert abs(float(rows[0]["kl"]) - 0.5) < 1e-3


@pytest.mark.parametrize("gating", ["constant", "flat"])
def test_pendulum_baselines_run(tmp_path, gating):
    summary = in_process(
        "pendulum", tmp_path, "r", gating=gating, n_options=20, episodes=20, eval_rollouts=2
    )
    assert json.loads((tmp_path / "r" / "summary.json").read_text()) == summary
    assert summary["gating"] == gating
    assert summary["n_options"] == (1 if gating == "flat" else 20)


def run_in_process(tmp_path, name, experiment, **cfg):
    """Run ``experiment`` ("pendulum" / "ball_on_beam") in this process into tmp_path/name;
    returns (metrics.csv text, the checkpointed policy state)."""
    from hireps_torch.experiments import ball_on_beam, pendulum

    config_cls, run = {
        "pendulum": (pendulum.PendulumConfig, pendulum.run),
        "ball_on_beam": (ball_on_beam.BallOnBeamConfig, ball_on_beam.run),
    }[experiment]
    run(config_cls(progress=False, run_dir=tmp_path / name, **cfg))
    ck = torch.load(tmp_path / name / "checkpoint.pt", weights_only=False)
    return (tmp_path / name / "metrics.csv").read_text(), ck["algorithm"]["policy"]


def test_pendulum_same_seed_same_run(tmp_path):
    a = run_in_process(
        tmp_path, "r0", "pendulum", episodes=40, episode_seconds=3.0, eval_rollouts=3, seed=3
    )
    b = run_in_process(
        tmp_path, "r1", "pendulum", episodes=40, episode_seconds=3.0, eval_rollouts=3, seed=3
    )
    assert a[0] == b[0]
    assert all(torch.equal(a[1][k], b[1][k]) for k in a[1])


def test_ball_on_beam_subprocess_writes_the_run_directory(tmp_path):
    run = tmp_path / "run"
    p = train("ball-on-beam", "--episodes", "6", "--run-dir", str(run), "--no-progress")
    assert p.returncode == 0, p.stderr
    summary = check_run_dir(run, keys=("success_rate", "episodes_to_success"))
    assert summary["experiment"] == "ball-on-beam" and summary["episodes"] == 6
    assert 0.0 <= summary["success_rate"] <= 1.0
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    assert len(rows) == 2  # 3 episodes per iteration
    from hireps_torch.experiments.ball_on_beam import BallOnBeamConfig

    assert abs(float(rows[0]["kl"]) - BallOnBeamConfig.epsilon) < 1e-3  # the bound is met
    for key in ("eta", "xi", "effective_sample_size", "policy_entropy", "falls", "eval_return"):
        assert key in rows[0]


def test_ball_on_beam_same_seed_same_run(tmp_path):
    runs = [
        run_in_process(tmp_path, name, "ball_on_beam", episodes=6, eval_episodes=2, seed=seed)[0]
        for name, seed in (("r0", 4), ("r1", 4), ("other", 5))
    ]
    assert runs[0] == runs[1]
    assert runs[2] != runs[0]


@pytest.mark.slow
def test_hockey_sequential_subprocess_writes_the_run_directory(tmp_path):
    pytest.importorskip("pybullet")
    run = tmp_path / "run"
    p = train(
        "hockey-sequential",
        *("--episodes", "40", "--episodes-per-iteration", "20"),  # two iterations
        *("--run-dir", str(run), "--no-progress"),
    )
    assert p.returncode == 0, p.stderr
    summary = check_run_dir(run, keys=("final_average_reward", "zone3_share"))
    assert summary["experiment"] == "hockey-sequential" and summary["episodes"] == 40
    assert 0.0 <= summary["zone3_share"] <= 1.0
    assert -10.0 < summary["final_average_reward"] <= 3.0
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    assert len(rows) == 2
    for k in (1, 2, 3):  # per-shot dual diagnostics
        assert abs(float(rows[0][f"kl_{k}"]) - 1.0) < 1e-3
        for key in ("eta", "xi", "cross_entropy", "effective_sample_size", "policy_entropy"):
            assert f"{key}_{k}" in rows[0]


@pytest.mark.slow
def test_hockey_same_seed_same_run(tmp_path):
    pytest.importorskip("pybullet")
    from hireps_torch.experiments import hockey

    def run(name, cls, seed):
        cfg = cls(
            episodes=6,
            episodes_per_iteration=3,
            seed=seed,
            progress=False,
            run_dir=tmp_path / name,
        )
        summary = hockey.run(cfg)
        return (tmp_path / name / "metrics.csv").read_text(), summary

    seq = hockey.HockeySequentialConfig
    (a, sa), (b, sb), (c, _) = run("a", seq, 1), run("b", seq, 1), run("c", seq, 2)
    assert a == b and a != c
    # the final policy's evaluation (3 fresh episodes each way) is part of the same run
    keys = ("eval_average_reward", "eval_zone3_share", "final_policy_average_reward")
    assert all(sa[k] == sb[k] and -10.0 < sa[k] <= 3.0 for k in keys)
    epi, se = run("e", hockey.HockeyEpisodicConfig, 1)
    assert "average_reward" in epi and "eval_average_reward" in se


def test_hockey_exploration_floor_moves_linearly_to_its_end_value():
    """The options' variance floor is (f std)^2 with f going from exploration_floor at the
    first update to exploration_floor_end at the last, linearly; None keeps it constant; it
    never goes below min_variance."""
    from hireps_torch.experiments.hockey import HockeySequentialConfig, variance_floor

    std = torch.tensor([0.02, 0.3], dtype=torch.float64)
    cfg = HockeySequentialConfig(exploration_floor=0.25, exploration_floor_end=0.1)
    first, mid, last = (variance_floor(cfg, std, i, 51) for i in (0, 25, 50))
    torch.testing.assert_close(first, (0.25 * std) ** 2)
    torch.testing.assert_close(mid, (0.175 * std) ** 2)
    torch.testing.assert_close(last, (0.1 * std) ** 2)
    torch.testing.assert_close(variance_floor(cfg, std, 99, 51), last)  # past the end: held
    const = HockeySequentialConfig(exploration_floor=0.25, exploration_floor_end=None)
    torch.testing.assert_close(variance_floor(const, std, 50, 51), first)
    low = HockeySequentialConfig(exploration_floor=0.0, exploration_floor_end=0.0)
    torch.testing.assert_close(
        variance_floor(low, std, 0, 51), torch.full((2,), 1e-6, dtype=torch.float64)
    )


def test_hockey_sets_the_floor_of_each_update_before_learning(tmp_path, monkeypatch):
    """The loop puts variance_floor(update) on every option of every shot's policy before
    algo.learn fits them (so a resumed run continues the schedule from its checkpoint)."""
    from hireps_torch.experiments import hockey

    seen = []
    learn = hockey.TimeIndexedHiREPS.learn

    def recording(self, experience):
        seen.append([o.min_variance.clone() for p in self.policies for o in p.sub_policies])
        return learn(self, experience)

    monkeypatch.setattr(hockey.TimeIndexedHiREPS, "learn", recording)
    cfg = hockey.HockeySequentialConfig(
        n_options=2,
        episodes=6,
        episodes_per_iteration=2,
        exploration_floor_end=0.1,
        final_eval_episodes=0,
        run_dir=tmp_path / "r",
        progress=False,
    )
    hockey.run(cfg)
    demo = torch.as_tensor(hockey.demo_action(hockey.hockey_params(cfg)), dtype=torch.float64)
    std = hockey._exploration_std(cfg, 1, demo)
    assert len(seen) == 3
    for it, floors in enumerate(seen):
        for v in floors:
            torch.testing.assert_close(v, hockey.variance_floor(cfg, std, it, 3))


def test_run_hockey_refuses_the_base_config(tmp_path):
    from hireps_torch.experiments import hockey

    with pytest.raises(ValueError, match="HockeySequentialConfig or HockeyEpisodicConfig"):
        hockey.run(hockey.HockeyConfig(run_dir=tmp_path / "r"))
    assert not (tmp_path / "r").exists()


def test_pendulum_policy_and_value_features_follow_the_config():
    import math

    from hireps_torch.experiments import pendulum

    cfg = pendulum.PendulumConfig(n_options=4)
    pol = pendulum.build_pendulum_policy(cfg, torch.Generator().manual_seed(0))
    means = [float(o.bias) for o in pol.sub_policies]
    assert means == pytest.approx([-1.5 * math.pi, -0.5 * math.pi, 0.5 * math.pi, 1.5 * math.pi])
    assert all(float(o.weight.abs().max()) == 0.0 for o in pol.sub_policies)
    x = torch.tensor([[0.3, -4.0]], dtype=torch.float64)
    both = pendulum.pendulum_value_features(cfg)
    assert both.out_features == 48 + 5
    assert torch.allclose(
        both(x)[0, 48:],
        torch.tensor([0.3 / math.pi, -0.4, 0.0091189, -0.0381972, 0.16], dtype=torch.float64),
        atol=1e-6,
    )
    plain = dataclasses.replace(cfg, value_features="fourier", init_means="random")
    assert pendulum.pendulum_value_features(plain).out_features == 48
    rand = pendulum.build_pendulum_policy(plain, torch.Generator().manual_seed(0))
    assert len({float(o.bias) for o in rand.sub_policies}) == 4


def test_a_populations_batch_splits_into_members_and_their_mirrored_decisions():
    """A batch of a population of two: each member's decisions (its systems, after the
    other's in the batch), then, mirrored, their mirror images."""
    from hireps_torch.envs.pendulum import PendulumSwingUpBatchEnv, mirror_decisions, mirror_states
    from hireps_torch.rollout import member_transitions

    env = PendulumSwingUpBatchEnv(4, seed=0)  # two members of two pendulums
    batch = env.rollout(3, break_when_any_done=False)
    batch["option"] = torch.zeros(4, 3, dtype=torch.int64)
    collected = member_transitions(batch, 2)
    assert [tuple(x.shape) for x in collected] == [(2, 6, 2), (2, 6, 1), (2, 6), (2, 6, 2), (2, 6)]
    s, a, r, s_next, term = mirror_decisions(*collected)
    assert s.shape == (2, 12, 2) and a.shape == (2, 12, 1) and term.shape == (2, 12)
    states = batch["state"].to(torch.float64).reshape(2, 6, 2)  # member after member
    assert torch.equal(s[:, :6], states) and torch.equal(s[:, 6:], mirror_states(states))
    assert torch.equal(a[:, 6:], -a[:, :6]) and torch.equal(r[:, 6:], r[:, :6])
    assert torch.equal(s_next[:, 6:], mirror_states(s_next[:, :6]))


def test_every_experiment_is_registered_with_its_config_and_run():
    import typing

    from hireps_torch.experiments import EXPERIMENTS, run_experiment

    assert set(EXPERIMENTS) == {
        "bimodal",
        "pendulum",
        "ball-on-beam",
        "hockey-sequential",
        "hockey-episodic",
        "hockey-fixed-start",
        "planar-arm",
        "tetherball",
    }
    for name, entry in EXPERIMENTS.items():
        config_cls, run = entry.config, entry.run
        cfg = config_cls()
        assert dataclasses.is_dataclass(cfg), name
        hints = typing.get_type_hints(config_cls)
        for field in ("seed", "run_dir", "progress", "logger"):
            assert field in hints, (name, field)
        assert callable(run)
    with pytest.raises(TypeError, match="no experiment takes a dict"):
        run_experiment({})
    # train.py is the command line only
    assert len((ROOT / "train.py").read_text().splitlines()) < 100


def test_unknown_or_missing_logger_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    from hireps_torch.experiments.rundir import RunWriter, make_logger

    with pytest.raises(ValueError, match="logger must be one of csv, tensorboard, wandb, got 'tb'"):
        make_logger("tb", tmp_path / "r", "x")
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else real(name, *a)
    )
    with pytest.raises(ImportError, match=r"wandb package.*\.\[wandb\]"):
        RunWriter(tmp_path / "q" / "r", {"experiment": "x"}, logger="wandb")
    assert not (tmp_path / "q").exists()  # nor the parent it made
    (tmp_path / "keep").mkdir()  # the user's: through "new/..", only "new" and "run" are made
    with pytest.raises(ImportError, match="wandb package"):
        RunWriter(tmp_path / "new" / ".." / "keep" / "run", {"experiment": "x"}, logger="wandb")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep"]
    (tmp_path / "keep").rmdir()
    # a population (its root's config.json was written before) and a new nested directory
    # (its parents were left) are refused with nothing written either
    for name, options in (("pop", {"seeds": "0-1"}), ("a/b", {})):
        with pytest.raises(ImportError, match="wandb package"):
            in_process("bimodal", tmp_path, name, episodes=400, logger="wandb", **options)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    monkeypatch.setattr(importlib.util, "find_spec", real)
    monkeypatch.setattr("importlib.metadata.version", lambda name: "0.18.3")
    with pytest.raises(ImportError, match=r"needs wandb >= 0.19.10, got 0.18.3"):
        make_logger("wandb", tmp_path / "r", "x")


def test_tensorboard_logger_writes_event_files_that_read_back(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    in_process("bimodal", tmp_path, "run", episodes=600, logger="tensorboard")
    run = tmp_path / "run"
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    events = list(run.rglob("events.out.tfevents.*"))
    assert events, sorted(str(x) for x in run.rglob("*"))
    acc = EventAccumulator(str(events[0].parent))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    for key in ("kl", "eta", "mean_return", "eval_return", "effective_sample_size"):
        assert key in tags
    kl = acc.Scalars("kl")
    assert [e.step for e in kl] == [1, 2, 3]
    assert [e.value for e in kl] == pytest.approx([float(r["kl"]) for r in rows], rel=1e-6)


def test_wandb_logger_runs_offline_without_an_account(tmp_path, monkeypatch):
    # a population's members log to a W&B run each (not all into member 0's)
    pytest.importorskip("wandb")
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_API_KEY", "")
    run = tmp_path / "run"
    argv = ["bimodal", "--episodes", "400", "--logger", "wandb", "--seeds", "0-1"]
    p = train(*argv, "--run-dir", str(run), "--no-progress")
    assert p.returncode == 0, p.stderr
    names = set()
    for member in ("seed0", "seed1"):
        offline = list((run / member / "wandb").glob("offline-run-*/run-*.wandb"))
        assert len(offline) == 1 and offline[0].stat().st_size > 0, member
        names.add(offline[0].name)
        assert (run / member / "summary.json").is_file()
    assert len(names) == 2, names


@pytest.mark.parametrize(
    "name,options,message",
    [
        ("pendulum", {"eval_rollouts": 0}, "eval_rollouts (--eval-rollouts) must be an integer"),
        ("pendulum", {"episode_seconds": -1.0}, "episode_seconds (--episode-seconds) must be"),
        ("pendulum", {"episode_seconds": float("nan")}, "got nan"),
        ("pendulum", {"restart_probability": 0.0}, "restart_probability (--restart-probability)"),
        ("bimodal", {"bump_width": 0.0}, "bump_width (--bump-width) must be finite and > 0"),
        ("bimodal", {"n_options": 0}, "n_options (--n-options) must be an integer >= 1"),
        ("ball-on-beam", {"fourier_bases": 0}, "fourier_bases (--fourier-bases)"),
        ("hockey-sequential", {"init_std_velocity": float("inf")}, "init_std_velocity"),
        ("hockey-episodic", {"covariance_prior": -1.0}, "covariance_prior"),
        ("hockey-sequential", {"mean_prior": -1.0}, "mean_prior (--mean-prior) must be"),
        ("hockey-episodic", {"final_eval_episodes": -1}, "final_eval_episodes (--final-eval-"),
        ("bimodal", {"checkpoint_every": 0}, "checkpoint_every must be >= 1, got 0"),
        ("bimodal", {"seed": 2**70}, "seed must be an integer in"),
    ],
)
def test_bad_option_values_are_named_before_anything_is_written(tmp_path, name, options, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        in_process(name, tmp_path, "r", **options)
    assert not (tmp_path / "r").exists()


def test_the_pendulums_restart_probability_reaches_its_envs_and_its_dual(tmp_path):
    """--restart-probability sets 1 - gamma per decision for the pendulums and the dual (None:
    the paper's 0.02 / d), and config.json leaves it out at None, as runs before it."""
    import json

    from hireps_torch.experiments.pendulum import PendulumConfig, _checked, _make_algorithm

    for given, d, restart in ((None, 2, 0.01), (0.0008, 1, 0.0008)):
        cfg = PendulumConfig(restart_probability=given, steps_per_decision=d)
        params, _ = _checked(cfg)
        assert params.restart == restart and params.gamma == 1.0 - restart
        algo = _make_algorithm(cfg, params, [0])
        assert algo.gamma == 1.0 - restart
    short = {"episodes": 20, "episode_seconds": 1.0, "eval_rollouts": 1}
    in_process("pendulum", tmp_path, "paper", **short)
    in_process("pendulum", tmp_path, "held", restart_probability=0.5, **short)
    paper, held = [
        json.loads((tmp_path / n / "config.json").read_text()) for n in ("paper", "held")
    ]
    assert "restart_probability" not in paper and held["restart_probability"] == 0.5


def test_ball_on_beam_value_features_couple_position_and_velocity_and_skip_the_angle():
    """The default value features: 4 x 4 - 1 coupled Fourier terms of (x, x') that do not
    change with the beam angle; ``value_beam_angle`` brings the angle in."""
    from hireps_torch.experiments.ball_on_beam import BallOnBeamConfig, value_features

    phi = value_features(BallOnBeamConfig(value_goal_bowl=False))
    assert phi.in_features == 3 and phi.out_features == 15
    s = torch.tensor([[0.2, 0.3, 0.0], [0.2, 0.3, 0.1], [-0.2, 0.3, 0.0], [0.2, -0.3, 0.0]])
    f = phi(s)
    torch.testing.assert_close(f[0], f[1], rtol=0, atol=0)  # the angle changes nothing
    # a coupled term: the value can tell a ball rolling toward the centre from one rolling away
    # even where the uncoupled terms of x and of x' agree (f(x, v) - f(-x, v) - f(x, -v) ...)
    mixed = f[0] - f[2] - f[3] + phi(torch.tensor([[-0.2, -0.3, 0.0]]))[0]
    assert float(mixed.abs().max()) > 0.1
    with_angle = value_features(BallOnBeamConfig(value_beam_angle=True, value_goal_bowl=False))
    assert with_angle.out_features == 4**3 - 1
    assert not torch.equal(with_angle(s)[0], with_angle(s)[1])
    # the default: the same 15 terms, then the goal bowl's 3
    full = value_features(BallOnBeamConfig())
    assert full.out_features == 18
    torch.testing.assert_close(full(s)[:, :15], f, rtol=0, atol=0)


def test_ball_on_beam_goal_bowl_features_are_the_quadratic_form_around_the_closer_goal():
    """[e^2, e v, v^2] with e the offset from the closer goal over the half length and v the
    velocity over max_velocity, against values computed by hand; zero at rest on either goal,
    equal on mirrored states, the angle ignored; a bad max_velocity is refused by name."""
    from hireps_torch.envs.ball_on_beam import BeamParams
    from hireps_torch.experiments.ball_on_beam import GoalBowlFeatures

    phi = GoalBowlFeatures(BeamParams(), max_velocity=2.0)
    s = torch.tensor(
        [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.1], [0.3, 0.5, 0.0], [-0.3, -0.5, 0.0], [0.0, 1.0, 0.0]],
        dtype=torch.float64,
    )
    f = phi(s)
    assert f.shape == (5, 3)
    # exactly: the goal is 0.1 in float64, not a float32 0.1 (1.5e-9 off)
    torch.testing.assert_close(f[0], torch.zeros(3, dtype=torch.float64), rtol=0, atol=0)
    torch.testing.assert_close(f[1], torch.zeros(3, dtype=torch.float64), rtol=0, atol=0)
    e, v = 0.2 / 0.5, 0.5 / 2.0  # 0.3 m is 0.2 m right of the goal at +0.1
    torch.testing.assert_close(f[2], torch.tensor([e * e, e * v, v * v], dtype=torch.float64))
    torch.testing.assert_close(f[3], f[2])  # the mirrored state
    # x = 0 counts from the goal at +0.1: e = -0.2
    torch.testing.assert_close(f[4], torch.tensor([0.04, -0.2 * 0.5, 0.25], dtype=torch.float64))
    with pytest.raises(ValueError, match="max_velocity"):
        GoalBowlFeatures(BeamParams(), max_velocity=0.0)


def test_ball_on_beam_goal_offset_features_are_the_state_seen_from_the_closer_goal():
    """[x - g, x', alpha] with g the goal on the ball's side (+goal at x = 0): zero offset at
    either goal, mirrored states give mirrored features; the default beam policy's options are
    linear in them, --no-option-goal-offset in the state itself."""
    from hireps_torch.envs.ball_on_beam import BeamParams
    from hireps_torch.experiments.ball_on_beam import (
        BallOnBeamConfig,
        GoalOffsetFeatures,
        build_ball_on_beam_policy,
    )
    from hireps_torch.features import IdentityFeatures

    phi = GoalOffsetFeatures(BeamParams())
    s = torch.tensor(
        [[0.1, 0.2, 0.05], [-0.1, -0.2, -0.05], [0.45, 0.0, 0.0], [0.0, 0.3, 0.01]],
        dtype=torch.float64,
    )
    f = phi(s)
    want = torch.tensor(
        [[0.0, 0.2, 0.05], [0.0, -0.2, -0.05], [0.35, 0.0, 0.0], [-0.1, 0.3, 0.01]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(f, want, rtol=0, atol=1e-15)
    assert f.shape == (4, 3) and phi.out_features == 3
    assert isinstance(
        build_ball_on_beam_policy(BallOnBeamConfig()).policy_features, GoalOffsetFeatures
    )
    plain = build_ball_on_beam_policy(BallOnBeamConfig(option_goal_offset=False))
    assert isinstance(plain.policy_features, IdentityFeatures)


def test_old_ball_on_beam_run_directories_resume_with_options_linear_in_the_position(tmp_path):
    """A config.json written before option_goal_offset existed (no such key) resumes with it
    off, the behaviour of that time, although the default is now on; a new run saves it."""
    import json

    from hireps_torch.experiments.ball_on_beam import BallOnBeamConfig
    from hireps_torch.experiments.checkpoint import saved_config
    from hireps_torch.experiments.options import config_dict

    new = config_dict("ball_on_beam", BallOnBeamConfig())
    assert new["option_goal_offset"] is True
    old = config_dict("ball_on_beam", BallOnBeamConfig(option_goal_offset=False))
    assert "option_goal_offset" not in old
    (tmp_path / "config.json").write_text(json.dumps(old))
    cfg = saved_config(BallOnBeamConfig, "ball-on-beam", tmp_path)
    assert cfg.option_goal_offset is False and cfg.resume == tmp_path


def test_old_hockey_run_directories_resume_with_a_constant_exploration_floor(tmp_path):
    """A hockey config.json from before exploration_floor_end existed resumes with the floor
    constant (None), although the default now anneals it to 0.1; a new run saves 0.1."""
    import json

    from hireps_torch.experiments.checkpoint import saved_config
    from hireps_torch.experiments.hockey import HockeySequentialConfig
    from hireps_torch.experiments.options import config_dict

    assert (
        config_dict("hockey_sequential", HockeySequentialConfig())["exploration_floor_end"] == 0.1
    )
    old = config_dict("hockey_sequential", HockeySequentialConfig(exploration_floor_end=None))
    assert "exploration_floor_end" not in old
    (tmp_path / "config.json").write_text(json.dumps(old))
    cfg = saved_config(HockeySequentialConfig, "hockey-sequential", tmp_path)
    assert cfg.exploration_floor_end is None


def test_pendulum_evaluates_every_k_iterations_and_reports_the_first_success(tmp_path):
    """eval_every = 2: evaluation columns filled on iterations 2 and 4 (nan elsewhere), equal
    to an evaluation of the policy at that point (the last one to the summary's final
    evaluation, same seed); episodes_to_success is the first row reaching 0.9, or None."""
    import math

    short = dict(episode_seconds=2.0, eval_rollouts=4, seed=1)
    metrics, _ = run_in_process(tmp_path, "r", "pendulum", episodes=80, eval_every=2, **short)
    rows = list(csv.DictReader(metrics.splitlines()))
    assert [r["iteration"] for r in rows] == ["1", "2", "3", "4"]
    for r in rows:
        filled = int(r["iteration"]) % 2 == 0
        assert math.isnan(float(r["eval_success_rate"])) != filled
        assert math.isnan(float(r["eval_return"])) != filled
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert float(rows[-1]["eval_success_rate"]) == summary["success_rate"]
    assert float(rows[-1]["eval_return"]) == summary["final_return"]
    first = next((int(r["episodes"]) for r in rows if float(r["eval_success_rate"]) >= 0.9), None)
    assert summary["episodes_to_success"] == first
    # eval_every = 0: no evaluation during training, the columns stay nan; and evaluating
    # after every iteration (1) draws nothing from the training's random streams
    runs = {}
    for k in (0, 1):
        text, _ = run_in_process(tmp_path, f"e{k}", "pendulum", episodes=80, eval_every=k, **short)
        runs[k] = list(csv.DictReader(text.splitlines()))
    assert all(math.isnan(float(r["eval_success_rate"])) for r in runs[0])
    assert not any(math.isnan(float(r["eval_success_rate"])) for r in runs[1])
    for key in ("average_return", "eta", "kl", "effective_sample_size"):
        assert [r[key] for r in runs[0]] == [r[key] for r in runs[1]] == [r[key] for r in rows]


def test_old_pendulum_run_directories_resume_with_a_constant_kl_bound(tmp_path):
    """A pendulum config.json from before epsilon_end existed is read with epsilon held
    (None), although the default now moves it to 0.1; a new run saves the end value (the
    resumed run itself: tests/test_resume.py)."""
    import json

    from hireps_torch.experiments.checkpoint import saved_config
    from hireps_torch.experiments.options import config_dict
    from hireps_torch.experiments.pendulum import PendulumConfig

    assert config_dict("pendulum", PendulumConfig())["epsilon_end"] == 0.1
    old = config_dict("pendulum", PendulumConfig(epsilon_end=None))
    assert "epsilon_end" not in old
    (tmp_path / "config.json").write_text(json.dumps(old))
    cfg = saved_config(PendulumConfig, "pendulum", tmp_path)
    assert cfg.epsilon_end is None and cfg.epsilon == 0.5


def test_pendulum_kl_bound_moves_linearly_from_epsilon_to_epsilon_end(tmp_path):
    """epsilon_at: epsilon at the first update, epsilon_end at the last, linear in between,
    held past the end, constant with None; a run realises the scheduled bound at every update
    (the kl column; that a resumed run continues the schedule: tests/test_resume.py)."""
    from hireps_torch.experiments import pendulum

    PendulumConfig, epsilon_at = pendulum.PendulumConfig, pendulum.epsilon_at
    cfg = PendulumConfig(epsilon=0.6, epsilon_end=0.2)
    assert [epsilon_at(cfg, i, 5) for i in range(5)] == pytest.approx([0.6, 0.5, 0.4, 0.3, 0.2])
    assert epsilon_at(cfg, 9, 5) == epsilon_at(cfg, 4, 5) == pytest.approx(0.2)  # then held
    assert epsilon_at(PendulumConfig(), 49, 50) == pytest.approx(0.1)
    assert epsilon_at(cfg, 0, 1) == 0.6
    assert epsilon_at(PendulumConfig(epsilon=0.6, epsilon_end=None), 4, 5) == 0.6
    short = dict(episode_seconds=1.0, eval_rollouts=2, eval_every=0, seed=2)
    text, _ = run_in_process(
        tmp_path, "r", "pendulum", episodes=60, epsilon=0.6, epsilon_end=0.2, **short
    )
    kl = [float(r["kl"]) for r in csv.DictReader(text.splitlines())]
    assert kl == pytest.approx([0.6, 0.4, 0.2], rel=1e-4)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["pendulum", "--workers", "100000000000000000000"], "workers must be in 1..1024"),
        (["pendulum", "--episodes", str(2**70)], "episodes must be in 1..1000000000"),
        (["ball-on-beam", "--episodes", str(2**70)], "episodes must be in 1..1000000000"),
        (["pendulum", "--seeds", "0-99999"], "a range hold at most 10000 seeds"),
        (["bimodal", "--seeds", "0-6000,7000-12000"], "names more than 10000 seeds"),
        (["bimodal", "--min-variance", "5e-324"], "min_variance (--min-variance) must be in"),
        (["bimodal", "--min-variance", "2.3e-308"], "min_variance (--min-variance) must be in"),
        (["pendulum", "--min-variance", "1e308"], "min_variance (--min-variance) must be in"),
        (["ball-on-beam", "--min-variance", "0"], "min_variance (--min-variance) must be in"),
    ],
)
def test_absurd_counts_and_floors_are_refused_before_anything_is_written(tmp_path, args, message):
    """In process (``train.main`` raises what ``train.py`` prints as ``error:``)."""
    import train as entry

    run = tmp_path / "run"
    with pytest.raises(ValueError) as refused:
        entry.main([*args, "--run-dir", str(run), "--no-progress"])
    assert message in str(refused.value)
    assert not run.exists()


@pytest.mark.slow
def test_the_installed_command_runs_an_experiment(tmp_path):
    command = Path(sys.executable).with_name("hireps-train")
    if not command.is_file():
        pytest.skip("hireps-train is not installed next to this interpreter")
    run = tmp_path / "run"
    p = subprocess.run(
        [str(command), "bimodal", "--episodes", "200", "--run-dir", str(run), "--no-progress"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr
    assert json.loads((run / "summary.json").read_text())["episodes"] == 200
    bad = subprocess.run(
        [str(command), "bimodal", "--episodes", "-3"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert bad.returncode == 2 and "episodes" in bad.stderr and "Traceback" not in bad.stderr


def test_the_command_puts_every_run_in_reproducible_mkl_before_torch_computes():
    code = (
        "import os, sys\n"
        "os.environ.pop('MKL_CBWR', None)\n"
        "sys.argv = ['hireps-train', 'pendulum', '--episodes', '-1']\n"
        "from hireps_torch.cli import entry\n"
        "try:\n"
        "    entry()\n"
        "except SystemExit as stop:\n"
        "    assert stop.code == 2, stop.code\n"
        "from hireps_torch.experiments.workers import _mkl_mode\n"
        "print(os.environ.get('MKL_CBWR'), _mkl_mode())\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    variable, mode = p.stdout.split()
    assert variable == "COMPATIBLE"
    assert mode in ("None", "2", "3")  # None: a torch without MKL; 1 would be MKL's default


@pytest.mark.slow
def test_a_hockey_run_whose_process_started_mkl_first_says_it_differs_from_the_command(tmp_path):
    """main() from Python after torchrl's import (MKL in its default mode): the run warns that it
    can differ from hireps-train's run of the same seed (before: only with workers)."""
    pytest.importorskip("pybullet")
    run = str(tmp_path / "run")
    code = (
        "import os, warnings\n"
        "os.environ.pop('MKL_CBWR', None)\n"
        "from hireps_torch.cli import main\n"
        "from hireps_torch.experiments.workers import _mkl_mode\n"
        "if _mkl_mode() is None: print('NO MKL'); raise SystemExit\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    main(['hockey-sequential', '--episodes', '2', '--episodes-per-iteration', '2',\n"
        f"          '--final-eval-episodes', '1', '--no-progress', '--run-dir', {run!r}])\n"
        "print('WARNED' if any('hireps-train' in str(x.message) for x in w) else 'SILENT')\n"
    )
    env = {**__import__("os").environ, "OMP_NUM_THREADS": "1"}
    env.pop("MKL_CBWR", None)
    p = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert p.returncode == 0, p.stderr[-3000:]
    if "NO MKL" in p.stdout:
        pytest.skip("torch without MKL")
    assert p.stdout.split()[-1] == "WARNED", p.stderr[-3000:]


def test_calling_main_in_a_process_leaves_its_environment_alone(tmp_path, monkeypatch):
    import train

    monkeypatch.delenv("MKL_CBWR", raising=False)
    with pytest.raises(ValueError, match="episodes"):
        train.main(["hockey-sequential", "--episodes", "-1"])
    assert "MKL_CBWR" not in __import__("os").environ


def test_runs_keep_freed_memory_where_the_c_library_is_glibc():
    from hireps_torch.experiments.runner import keep_freed_memory

    glibc = platform.libc_ver()[0] == "glibc"
    assert keep_freed_memory() is glibc
    assert keep_freed_memory(0) is glibc


def test_a_run_keeps_freed_memory_while_it_runs_and_hands_it_back_after(tmp_path, monkeypatch):
    """In a process that goes on after a run (a notebook, a sweep's runs one after another) the
    heap kept for the run is handed back (before: 1 GiB of pad for the rest of the process;
    ~850 MB resident after a 20-seed pendulum population against ~450 MB)."""
    from hireps_torch.experiments import runner

    calls = []

    class Libc:
        def mallopt(self, option, value):
            calls.append(("mallopt", option, value))
            return 1

        def malloc_trim(self, pad):
            calls.append(("malloc_trim", pad))
            return 1

    import train as entry

    monkeypatch.setattr(runner.ctypes, "CDLL", lambda name: Libc())
    entry.main(["bimodal", "--episodes", "400", "--run-dir", str(tmp_path / "r"), "--no-progress"])
    assert calls == [("mallopt", -2, 1 << 30), ("mallopt", -2, 128 * 1024), ("malloc_trim", 0)]


def test_learning_curves_of_members_share_a_figure_but_not_its_limits(tmp_path, monkeypatch):
    """One figure is redrawn per member: each PNG shows that member's data range, and a member
    with nothing finite gets a fresh figure's limits, not its predecessor's."""
    import types

    from matplotlib.figure import Figure

    from hireps_torch.experiments.rundir import plot_learning_curves

    nan, seen = float("nan"), []
    save = Figure.savefig

    def recording(fig, path, **kw):
        seen.append((fig.axes[0].get_xlim(), fig.axes[0].get_ylim()))
        return save(fig, path, **kw)

    monkeypatch.setattr(Figure, "savefig", recording)
    rows = {
        "wide": [{"episodes": e, "ret": -1e5 + e, "ev": nan} for e in (0, 1000, 2000)],
        "diverged": [{"episodes": 20, "ret": nan, "ev": nan}],
        "small": [{"episodes": 1, "ret": 0.5, "ev": 0.25}, {"episodes": 2, "ret": 1.0, "ev": 0.75}],
    }
    writers = []
    for name, r in rows.items():
        (tmp_path / name).mkdir()
        writers.append(types.SimpleNamespace(rows=r, dir=tmp_path / name))
    plot_learning_curves(writers, "episodes", ["ret", "ev"], "t")
    assert all((tmp_path / n / "learning_curve.png").stat().st_size > 0 for n in rows)
    (wide_x, wide_y), (div_x, div_y), (small_x, small_y) = seen
    assert wide_x[0] <= 0 and wide_x[1] >= 2000 and wide_y[0] <= -1e5 < -98000 <= wide_y[1]
    assert div_x == pytest.approx((-0.055, 0.055)) and div_y == pytest.approx((-0.055, 0.055))
    assert small_x[0] <= 1 < 2 <= small_x[1] < 3 and small_y[0] <= 0.25 < 1.0 <= small_y[1] < 2


def test_a_second_ctrl_c_in_the_clean_up_keeps_the_resume_instructions(monkeypatch, capsys):
    # the first signal stopped the run at an iteration boundary (checkpoint written); a second
    # one while the collector shuts down must not hide where to resume from
    import hireps_torch.cli as cli
    from hireps_torch.experiments.checkpoint import RunInterrupted

    def stopped_twice() -> None:
        try:
            raise RunInterrupted(Path("runs/x"), 9, "SIGTERM")
        finally:
            raise KeyboardInterrupt  # noqa: B012 (what a Ctrl-C in the finally raises)

    monkeypatch.setattr(cli, "main", stopped_twice)
    with pytest.raises(SystemExit) as stop:
        cli.entry()
    err = capsys.readouterr().err
    assert stop.value.code == 143
    assert "stopped after iteration 9" in err and "Continue with: --resume runs" in err, err


@pytest.mark.parametrize(
    ("name", "options", "message"),
    [
        ("pendulum", {"episodes": 30}, r"episodes \(30\) is not a multiple of episodes_per_it"),
        ("ball-on-beam", {"episodes": 10}, r"plays 3 iteration\(s\), 9 episodes"),
        ("bimodal", {"episodes": 500}, r"samples_per_iteration \(200\): the run plays 2 itera"),
        ("hockey-fixed-start", {"episodes": 25}, r"plays 2 iteration\(s\), 20 episodes"),
    ],
)
def test_episodes_that_leave_part_of_an_iteration_over_are_said(name, options, message):
    """A run whose budget is not a whole number of iterations is rounded down, with a warning
    (where the run starts: resume_point) that says how many episodes it plays; whole budgets,
    and building the algorithm alone (load_run, a sweep's checks), warn nothing."""
    from hireps_torch.experiments import EXPERIMENTS
    from hireps_torch.experiments.runner import resume_point

    config_cls = EXPERIMENTS[name].config
    with pytest.warns(UserWarning, match=message):
        assert resume_point(EXPERIMENTS[name], config_cls(**options)) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        resume_point(EXPERIMENTS[name], config_cls())
        EXPERIMENTS[name].algorithm(config_cls(**options))


def test_a_run_leaves_the_callers_matplotlib_backend_alone(tmp_path):
    """Plots are drawn on pyplot-free figures: a notebook's inline backend stays (before: every
    run switched the process to Agg)."""
    code = (
        "import matplotlib; matplotlib.use('svg'); import train; "
        f"train.main(['bimodal', '--seeds', '0-1', '--episodes', '400', '--no-progress', "
        f"'--run-dir', {str(tmp_path / 'r')!r}]); "
        "print('BACKEND', matplotlib.get_backend())"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "BACKEND svg" in out.stdout
    assert (tmp_path / "r" / "seed0" / "options.png").stat().st_size > 0
    assert (tmp_path / "r" / "population.png").stat().st_size > 0
