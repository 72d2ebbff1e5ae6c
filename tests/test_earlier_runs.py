"""Run directories an earlier version wrote (tests/data/earlier_runs) are refused by --resume and
load_run with a message that says why, and nothing in them changes."""

import shutil
from pathlib import Path

import pytest

from hireps_torch.cli import main
from hireps_torch.experiments.checkpoint import RunFinished
from hireps_torch.experiments.saved import load_run

EARLIER = Path(__file__).parent / "data" / "earlier_runs"
WHY_POPULATION = "an earlier version of this code ran, which wrote no checkpoint"


@pytest.fixture
def earlier(tmp_path):
    d = tmp_path / "earlier_runs"
    shutil.copytree(EARLIER, d)
    return d


def files(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize(
    "run, why",
    [
        ("population_interrupted", "If its seed<s>/ directories are the members of a population"),
        ("population_finished", "If its seed<s>/ directories are the members of a population"),
        ("population_interrupted/seed1", "If it is a member of a population"),
        ("run_interrupted", r"another version of this code \(format 1, expected 3\)"),
    ],
)
def test_resume_of_an_earlier_versions_run_is_refused_saying_why_and_changes_nothing(
    earlier, run, why
):
    before = files(earlier)
    with pytest.raises(ValueError, match=why) as refused:
        main(["bimodal", "--resume", str(earlier / run), "--no-progress"])
    assert "population" not in run or WHY_POPULATION in str(refused.value)
    assert files(earlier) == before


@pytest.mark.parametrize("run", ["run_finished", "population_finished/seed2"])
def test_resume_of_an_earlier_versions_finished_run_says_it_finished(earlier, run):
    before = files(earlier)
    with pytest.raises(RunFinished, match="already finished"):
        main(["bimodal", "--resume", str(earlier / run), "--no-progress"])
    assert files(earlier) == before


@pytest.mark.parametrize(
    "run, why",
    [
        ("run_finished", "can neither resume nor load it"),
        ("population_finished", WHY_POPULATION),
        ("population_finished/seed1", WHY_POPULATION),
    ],
)
def test_load_run_of_an_earlier_versions_run_is_refused_saying_why(earlier, run, why):
    before = files(earlier)
    with pytest.raises(ValueError, match=why):
        load_run(earlier / run)
    assert files(earlier) == before


def test_resume_of_an_earlier_versions_hockey_run_is_refused_saying_why(earlier):
    """An ordinary hockey run of dab85ff held its policies without a member dimension."""
    pytest.importorskip("pybullet")
    before = files(earlier)
    with pytest.raises(
        ValueError,
        match="an earlier version of this code wrote it: it cannot be resumed; run it again",
    ):
        main(
            ["hockey-sequential", "--resume", str(earlier / "hockey_interrupted"), "--no-progress"]
        )
    assert files(earlier) == before


def test_load_run_of_an_earlier_versions_hockey_run_names_the_missing_member_dimension(earlier):
    pytest.importorskip("pybullet")
    before = files(earlier)
    with pytest.raises(ValueError, match="it holds one run without a member dimension"):
        load_run(earlier / "hockey_interrupted")
    assert files(earlier) == before


def test_resume_of_a_folder_of_runs_or_of_nothing_says_what_it_is(tmp_path):
    short = ["--episodes", "400", "--samples-per-iteration", "200", "--no-progress"]
    main(["bimodal", *short, "--seed", "0", "--run-dir", str(tmp_path / "sweep" / "seed0")])
    before = files(tmp_path)
    with pytest.raises(ValueError, match="seed<s>/ directories are runs of their own"):
        main(["bimodal", "--resume", str(tmp_path / "sweep"), "--no-progress"])
    with pytest.raises(ValueError, match="It does not exist"):
        main(["bimodal", "--resume", str(tmp_path / "nothing"), "--no-progress"])
    assert files(tmp_path) == before
