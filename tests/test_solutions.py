"""The tasks with several solutions as runs: every algorithm, the versatility columns and
summary fields, a population member equal to its ordinary run."""

import csv
import json
import math

import pytest

from hireps_torch.experiments.solutions import PlanarArmConfig, TetherballConfig, run

SHORT = {"episodes": 400, "samples_per_iteration": 50, "versatility_samples": 100}
FIELDS = ("success_rate", "solutions_found", "behaviour_entropy", "purity")


def _rows(path):
    return list(csv.DictReader((path / "metrics.csv").open()))


@pytest.mark.parametrize(
    "algorithm", ["hireps", "hireps-unbounded", "hireps-versatile", "reps", "cmaes"]
)
def test_each_algorithm_writes_the_versatility_per_iteration_and_in_its_summary(
    tmp_path, algorithm
):
    summary = run(
        PlanarArmConfig(algorithm=algorithm, run_dir=tmp_path, progress=False, seed=11, **SHORT)
    )
    saved = json.loads((tmp_path / "summary.json").read_text())
    rows = _rows(tmp_path)
    assert len(rows) == 8 and summary["algorithm"] == saved["algorithm"] == algorithm
    for key in FIELDS:
        assert key in saved and key in rows[-1]
        assert float(rows[-1][key]) == saved[key] or math.isnan(saved[key])
    assert 0 <= saved["success_rate"] <= 1 and 0 <= saved["behaviour_entropy"] <= 1
    assert saved["solutions_found"] in (0, 1, 2, 3, 4)
    if algorithm in ("reps", "cmaes"):
        assert saved["solutions_found"] <= 1  # one Gaussian holds one goal at most
        assert {r["n_active_options"] for r in rows} == {"1"}
    if algorithm == "hireps-unbounded":
        assert {r["xi"] for r in rows} == {"0.0"}  # no entropy bound: xi stays 0
        assert all(r["kappa"] == "nan" for r in rows)


@pytest.mark.parametrize("algorithm", ["hireps", "cmaes"])
def test_a_population_member_writes_its_ordinary_runs_metrics(tmp_path, algorithm):
    run(
        PlanarArmConfig(
            algorithm=algorithm, run_dir=tmp_path / "pop", seeds="3,5", progress=False, **SHORT
        )
    )
    run(
        PlanarArmConfig(
            algorithm=algorithm, run_dir=tmp_path / "one", seed=5, progress=False, **SHORT
        )
    )
    assert (tmp_path / "pop" / "seed5" / "metrics.csv").read_bytes() == (
        tmp_path / "one" / "metrics.csv"
    ).read_bytes()


def test_bad_options_are_named_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match="versatility_samples"):
        run(PlanarArmConfig(versatility_samples=0, run_dir=tmp_path / "r", progress=False))
    with pytest.raises(ValueError, match="base_std"):
        run(PlanarArmConfig(base_std=-1.0, run_dir=tmp_path / "r", progress=False))
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("algorithm", ["hireps", "hireps-unbounded", "hireps-versatile", "reps"])
def test_tetherball_runs_each_algorithm_and_writes_the_versatility(tmp_path, algorithm):
    options = {"episodes": 150, "samples_per_iteration": 50, "versatility_samples": 60}
    run(TetherballConfig(algorithm=algorithm, run_dir=tmp_path, progress=False, **options))
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert len(_rows(tmp_path)) == 3 and saved["experiment"] == "tetherball"
    assert all(key in saved for key in FIELDS) and saved["solutions_found"] <= 2


def test_tetherball_members_equal_their_runs_and_cmaes_is_refused(tmp_path):
    options = {"episodes": 100, "samples_per_iteration": 50, "versatility_samples": 60}
    run(TetherballConfig(run_dir=tmp_path / "pop", seeds="1,2", progress=False, **options))
    run(TetherballConfig(run_dir=tmp_path / "one", seed=2, progress=False, **options))
    assert (tmp_path / "pop" / "seed2" / "metrics.csv").read_bytes() == (
        tmp_path / "one" / "metrics.csv"
    ).read_bytes()
    with pytest.raises(ValueError, match="algorithm .* must be one of .*got 'cmaes'"):
        run(TetherballConfig(algorithm="cmaes", run_dir=tmp_path / "c", progress=False))


@pytest.mark.parametrize(
    "algorithm", ["hireps", "hireps-unbounded", "hireps-versatile", "reps", "cmaes"]
)
def test_the_two_gaussians_log_the_versatility_for_every_algorithm(tmp_path, algorithm):
    from hireps_torch.experiments.bimodal import BimodalConfig
    from hireps_torch.experiments.bimodal import run as run_bimodal

    options = {"episodes": 400, "samples_per_iteration": 100, "versatility_samples": 100}
    run_bimodal(BimodalConfig(algorithm=algorithm, run_dir=tmp_path, progress=False, **options))
    saved = json.loads((tmp_path / "summary.json").read_text())
    rows = _rows(tmp_path)
    assert saved["algorithm"] == algorithm and len(rows) == 4
    for key in FIELDS:
        assert key in saved and key in rows[-1]
    if algorithm in ("reps", "cmaes"):
        assert saved["solutions_found"] <= 1


def test_cmaes_on_the_contextual_two_gaussians_is_refused_naming_why(tmp_path):
    from hireps_torch.experiments.bimodal import BimodalConfig
    from hireps_torch.experiments.bimodal import run as run_bimodal

    with pytest.raises(ValueError, match="cmaes searches one parameter vector"):
        run_bimodal(
            BimodalConfig(
                algorithm="cmaes", contextual=True, run_dir=tmp_path / "r", progress=False
            )
        )
    assert not (tmp_path / "r").exists()


def test_hireps_versatile_reports_its_floor_and_a_floor_outside_zero_to_one_is_refused(tmp_path):
    run(
        PlanarArmConfig(
            algorithm="hireps-versatile", run_dir=tmp_path / "a", progress=False, seed=4, **SHORT
        )
    )
    rows = _rows(tmp_path / "a")
    expected = 0.5 * math.log(20)  # the default floor: half the entropy of 20 equal options
    assert all(float(r["entropy_floor"]) <= expected + 1e-12 for r in rows)
    assert all(float(r["prior_entropy"]) >= float(r["entropy_floor"]) - 1e-4 for r in rows)
    assert {"lambda", "prior_entropy"} <= set(rows[0])
    with pytest.raises(ValueError, match="entropy_floor must be in"):
        run(PlanarArmConfig(entropy_floor=1.5, run_dir=tmp_path / "b", progress=False))


def test_load_run_reads_a_cmaes_run_back_with_its_mean(tmp_path):
    import torch

    from hireps_torch import load_run

    run(PlanarArmConfig(algorithm="cmaes", run_dir=tmp_path, progress=False, **SHORT))
    loaded = load_run(tmp_path)
    mean = loaded.algorithm.policy.sub_policies[0].bias.reshape(-1)
    assert torch.equal(loaded.mean_action(2), mean.expand(2, -1))
    assert torch.equal(loaded.mean_action(torch.zeros(3, 0, dtype=torch.float64))[0], mean)
    with pytest.raises(ValueError, match="CMA-ES takes no context"):
        loaded.algorithm.mean_action(torch.zeros(1, 2, 1, dtype=torch.float64))
