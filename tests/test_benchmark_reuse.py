"""Benchmarks that reuse finished runs check their options first (nothing mixed in silently)."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from hireps_torch.experiments.options import config_dict
from hireps_torch.experiments.pendulum import PendulumConfig
from hireps_torch.experiments.sweep import SweepRun

ROOT = Path(__file__).resolve().parents[1]


def ablations():
    spec = importlib.util.spec_from_file_location(
        "pendulum_ablations", ROOT / "benchmarks" / "pendulum_ablations.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["pendulum_ablations"] = module
    spec.loader.exec_module(module)
    return module


def finished_population(root, seeds, **options):
    """A population folder as ``train.py pendulum --seeds`` leaves it (config, summary)."""
    for s in seeds:
        d = root / f"seed{s}"
        d.mkdir(parents=True)
        cfg = PendulumConfig(seed=s, run_dir=d, progress=False, **options)
        (d / "config.json").write_text(json.dumps(config_dict("pendulum", cfg)))
        (d / "summary.json").write_text(json.dumps({"seed": s, "success_rate": 1.0}))
    (root / "population.json").write_text(json.dumps({f"seed{s}": {} for s in seeds}))


def test_ablation_refuses_a_finished_population_with_other_options(tmp_path):
    """A population finished with the KL bound held (before epsilon_end existed) is not read
    into an ablation that now asks for the schedule: the error names the option."""
    module = ablations()
    root = tmp_path / "learned-5"
    finished_population(root, [0, 1], epsilon_end=None)
    runs = [SweepRun("pendulum", "learned-5", s, {}, root / f"seed{s}") for s in (0, 1)]
    seen = []
    with pytest.raises(ValueError, match="epsilon_end"):
        module.run_populations(runs, lambda r, summary: seen.append(r.seed))
    assert seen == []
    held = [
        SweepRun("pendulum", "learned-5", s, {"epsilon_end": None}, r.run_dir)
        for s, r in zip((0, 1), runs, strict=True)
    ]
    done = module.run_populations(held, lambda r, summary: seen.append(r.seed))
    assert seen == [0, 1] and done[("learned-5", 1)]["seed"] == 1


@pytest.mark.slow
def test_ablation_populations_side_by_side_equal_one_after_the_other(tmp_path, monkeypatch):
    """Two configurations' populations in two worker processes write the metrics they write one
    after the other in this process."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # the workers import the module
    import pendulum_ablations as module

    options = {
        "learned-2": {"n_options": 2, "episodes": 40},
        "d10": {"steps_per_decision": 10, "episodes": 40},
    }
    metrics = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        runs = [
            SweepRun("pendulum", name, 0, opts, out / name / "seed0")
            for name, opts in options.items()
        ]
        seen = []
        module.run_populations(runs, lambda r, summary, seen=seen: seen.append(r.name), workers, 1)
        assert seen == list(options)
        metrics[workers] = [(r.run_dir / "metrics.csv").read_text() for r in runs]
    assert metrics[1] == metrics[2]


def test_ablation_workers_keep_to_cores_of_their_own_when_there_are_enough():
    core_sets = ablations().core_sets
    assert core_sets([1, 0], 2, 1) == [{0}, {1}]
    assert core_sets([0, 1, 2, 3, 4], 2, 2) == [{0, 1}, {2, 3}]
    assert core_sets([0, 1], 1, 1) is None  # one worker keeps every core
    assert core_sets([0, 1, 2], 2, 2) is None  # too few to give each its own
