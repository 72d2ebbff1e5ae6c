"""``hireps_torch.load_run``: a run directory loaded back as its config and its algorithm,
for finished and interrupted runs of every experiment and for a member of a population."""

import csv
import dataclasses
import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

import hireps_torch
from hireps_torch.experiments import EXPERIMENTS
from hireps_torch.experiments.checkpoint import RunInterrupted

SHORT = {
    "bimodal": {"episodes": 600},
    "pendulum": {"episodes": 20, "episode_seconds": 2.0, "eval_rollouts": 2},
    "ball-on-beam": {"episodes": 6, "eval_episodes": 2},
    "hockey-sequential": {"episodes": 6, "episodes_per_iteration": 3, "final_eval_episodes": 1},
    "hockey-episodic": {"episodes": 6, "episodes_per_iteration": 3, "final_eval_episodes": 1},
}


def same_tree(a, b):
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same_tree(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same_tree(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def train(name, run_dir, **options):
    config_cls, run = EXPERIMENTS[name].config, EXPERIMENTS[name].run
    cfg = config_cls(progress=False, run_dir=run_dir, **{**SHORT[name], **options})
    run(cfg)
    return cfg


def states_for(loaded, n=5):
    return torch.zeros(n, loaded.algorithm.policies[0].context_dim, dtype=torch.float64)


@pytest.mark.parametrize("name", list(SHORT))
def test_a_finished_run_loads_back_as_its_config_and_its_saved_algorithm(tmp_path, name):
    if name.startswith("hockey"):
        pytest.importorskip("pybullet")
    run_dir = tmp_path / "run"
    cfg = train(name, run_dir)
    loaded = hireps_torch.load_run(run_dir)
    assert loaded.experiment == name and loaded.finished
    assert loaded.config == dataclasses.replace(cfg, run_dir=run_dir)
    ckpt = torch.load(run_dir / "checkpoint.pt")
    assert same_tree(loaded.algorithm.state_dict(), ckpt["algorithm"])
    assert loaded.iteration == ckpt["iteration"] == len(loaded.metrics)
    states = states_for(loaded)
    actions = loaded.mean_action(states)
    assert actions.shape[0] == 5 and torch.isfinite(actions).all()
    if loaded.algorithm.population is None:  # hockey: one ordinary algorithm
        expected = loaded.algorithm.mean_action(states)
    else:  # the batched experiments: a population of one
        assert loaded.algorithm.population == 1
        expected = loaded.algorithm.mean_action(states[None])[0]
    assert torch.equal(actions, expected)
    assert loaded.sample(states).shape == actions.shape


def test_config_json_round_trips_into_its_config_class(tmp_path):
    from hireps_torch.experiments.checkpoint import run_config

    cfg = train("bimodal", tmp_path / "run", seed=4, contextual=True, epsilon=0.7)
    again = run_config(EXPERIMENTS["bimodal"].config, "bimodal", tmp_path / "run")
    assert again == cfg
    assert json.loads((tmp_path / "run" / "config.json").read_text())["experiment"] == "bimodal"


def test_a_population_member_loads_as_its_part_of_the_population(tmp_path):
    root = tmp_path / "pop"
    train("bimodal", root, seeds="3,5,8")
    population = torch.load(root / "checkpoint.pt")
    loaded = hireps_torch.load_run(root / "seed5")
    assert loaded.config.seed == 5 and loaded.config.seeds is None
    state = loaded.algorithm.state_dict()
    assert state["policy"]["gating.weight"].shape[0] == 1
    for key, value in state["policy"].items():
        whole = population["algorithm"]["policy"][key]
        assert torch.equal(value, whole[1:2] if whole.shape != value.shape else whole), key
    with (root / "seed5" / "metrics.csv").open(newline="") as f:
        assert population["rows"][1] == f.read()  # the checkpoint holds each member's text
    with (root / "seed5" / "metrics.csv").open() as f:
        logged = list(csv.DictReader(f))
    assert len(logged) == population["iteration"]
    assert [{k: str(v) for k, v in r.items()} for r in loaded.metrics] == logged
    assert type(loaded.metrics[0]["iteration"]) is int and type(loaded.metrics[0]["kl"]) is float
    assert type(loaded.metrics[0]["dual_converged"]) is bool
    with pytest.raises(ValueError, match="is a population .*load one member"):
        hireps_torch.load_run(root)


class _Interrupting:
    """tqdm that sends this process SIGINT after ``after`` iterations, as Ctrl-C would."""

    def __init__(self, *args, after, **kwargs):
        self.after, self.n = after, 0

    def update(self, k):
        self.n += k
        if self.n == self.after:
            os.kill(os.getpid(), signal.SIGINT)

    def set_postfix(self, **_):
        """No bar to show."""

    def close(self):
        """Nothing to close."""


def test_an_interrupted_run_loads_at_its_last_checkpoint(tmp_path, monkeypatch):
    import hireps_torch.experiments.runner as loop

    monkeypatch.setattr(loop, "tqdm", lambda *a, **k: _Interrupting(after=2))
    with pytest.raises(RunInterrupted):
        train("pendulum", tmp_path / "run", episodes=40, episodes_per_iteration=10)
    loaded = hireps_torch.load_run(tmp_path / "run")
    assert not loaded.finished and loaded.iteration == 2 and len(loaded.metrics) == 2
    ckpt = torch.load(tmp_path / "run" / "checkpoint.pt")
    assert same_tree(loaded.algorithm.state_dict(), ckpt["algorithm"])


def test_directories_that_are_not_loadable_runs_get_a_clear_error(tmp_path):
    for bad in (None, 123, b"runs"):  # pathlib's own TypeError, not naming run_dir, before
        with pytest.raises(TypeError, match="run_dir must be a path"):
            hireps_torch.load_run(bad)
    with pytest.raises(ValueError, match="holds no config.json"):
        hireps_torch.load_run(tmp_path / "nowhere")
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"experiment": "chess"}))
    with pytest.raises(ValueError, match="names the experiment 'chess'"):
        hireps_torch.load_run(other)
    early = tmp_path / "early"
    early.mkdir()
    (early / "config.json").write_text(json.dumps({"experiment": "bimodal", "seed": 1}))
    with pytest.raises(ValueError, match="no checkpoint.pt: the run had not finished"):
        hireps_torch.load_run(early)
    before = sorted(p.name for p in early.iterdir())
    assert before == ["config.json"]  # loading wrote nothing
    train("bimodal", tmp_path / "moved")
    (tmp_path / "moved" / "checkpoint.pt").unlink()
    with pytest.raises(
        ValueError, match=r"row\(s\) and a summary.json: .* the checkpoint was moved away"
    ):
        hireps_torch.load_run(tmp_path / "moved")
    (tmp_path / "moved" / "summary.json").unlink()  # or not yet written in its first iteration
    with pytest.raises(ValueError, match=r"no checkpoint.pt but \d+ metrics row\(s\): the run "):
        hireps_torch.load_run(tmp_path / "moved")


def test_a_checkpoint_of_another_experiment_is_refused(tmp_path):
    train("bimodal", tmp_path / "run")
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    (tmp_path / "run" / "config.json").write_text(json.dumps({**config, "experiment": "pendulum"}))
    with pytest.raises(ValueError, match="checkpoint.pt is of a .bimodal. run, but"):
        hireps_torch.load_run(Path(tmp_path / "run"))


def _edit(path, **changes):
    data = json.loads(path.read_text())
    path.write_text(json.dumps({**data, **changes}))


def test_a_checkpoint_that_another_run_wrote_is_refused(tmp_path):
    import shutil

    train("bimodal", tmp_path / "a", seed=0)
    train("bimodal", tmp_path / "b", seed=3)
    shutil.copy(tmp_path / "b" / "checkpoint.pt", tmp_path / "a" / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"other options than .*seed \(checkpoint.pt: 3"):
        hireps_torch.load_run(tmp_path / "a")
    _edit(tmp_path / "b" / "config.json", epsilon=0.5)
    with pytest.raises(ValueError, match="epsilon"):
        hireps_torch.load_run(tmp_path / "b")


def test_a_member_directory_that_does_not_fit_its_population_is_named(tmp_path):
    root = tmp_path / "pop"
    train("bimodal", root, seeds="3,5")
    (root / "seed5").rename(root / "seed9")
    with pytest.raises(ValueError, match=r"inside the population .* not one of its members"):
        hireps_torch.load_run(root / "seed9")
    (root / "seed9").rename(root / "seed5")
    _edit(root / "seed5" / "config.json", epsilon=0.3)
    with pytest.raises(ValueError, match="does not match its population"):
        hireps_torch.load_run(root / "seed5")
    _edit(root / "config.json", seeds="5,3")
    with pytest.raises(ValueError, match="seeds"):
        hireps_torch.load_run(root / "seed3")


def test_options_of_the_wrong_type_in_config_json_name_the_file(tmp_path):
    train("bimodal", tmp_path / "run")
    _edit(tmp_path / "run" / "config.json", n_options="10")
    with pytest.raises(ValueError, match=r"config.json does not hold the options .*n_options"):
        hireps_torch.load_run(tmp_path / "run")


def test_acting_takes_the_ordinary_shapes_and_names_a_bad_one(tmp_path):
    train("bimodal", tmp_path / "bimodal")
    toy = hireps_torch.load_run(tmp_path / "bimodal")
    assert toy.mean_action(4).shape == (4, 2)  # no states: the number of samples
    assert toy.sample(3).shape == (3, 2)
    train("pendulum", tmp_path / "pendulum")
    run = hireps_torch.load_run(tmp_path / "pendulum")
    assert run.mean_action([[3.0, 0.0]]).shape == (1, 1)  # a list of states is fine
    with pytest.raises(
        ValueError, match=r"states must have shape \(N, 2\) with N >= 1, got \(3, 3"
    ):
        run.mean_action(torch.zeros(3, 3))
    with pytest.raises(ValueError, match=r"N >= 1, got \(0, 2\)"):
        run.mean_action(torch.zeros(0, 2))
    with pytest.raises(TypeError, match=r"states must be a tensor of numbers, got NoneType"):
        run.sample(None)
    with pytest.raises(TypeError, match=r"states must hold real numbers, got dtype torch.compl"):
        run.mean_action(torch.tensor([[3.14 + 5j, 9j]]))  # not its real part in silence
    assert toy.mean_action(np.int64(2)).shape == toy.sample(torch.tensor(2)).shape == (2, 2)
    for bad, error in [(0, ValueError), (-1, ValueError), (2.0, TypeError), (True, TypeError)]:
        with pytest.raises(error, match=f"N must be .*got .*{bad}"):
            toy.mean_action(bad)


def test_the_library_lists_load_run():
    assert "load_run" in dir(hireps_torch) and callable(hireps_torch.load_run)


def test_every_top_level_name_resolves_and_each_variants_dual_is_there():
    """``hireps_torch.__all__`` names what ``from hireps_torch import ...`` gives, the dual
    solver of each of the three variants among them."""
    from hireps_torch.dual import (
        solve_episodic_dual,
        solve_infinite_horizon_dual,
        solve_time_indexed_dual,
    )

    for name in hireps_torch.__all__:
        assert getattr(hireps_torch, name) is not None and name in dir(hireps_torch)
    assert hireps_torch.solve_episodic_dual is solve_episodic_dual
    assert hireps_torch.solve_time_indexed_dual is solve_time_indexed_dual
    assert hireps_torch.solve_infinite_horizon_dual is solve_infinite_horizon_dual
