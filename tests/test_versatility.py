"""Versatility metrics on hand-built samples."""

import math

import pytest
import torch

from hireps_torch.versatility import versatility


def _t(values):
    return torch.tensor(values, dtype=torch.int64)


def test_two_pure_options_on_two_classes_give_two_solutions_entropy_one_purity_one():
    option = _t([0, 0, 0, 1, 1, 1])
    classes = _t([0, 0, 0, 1, 1, 1])
    out = versatility(option, classes, torch.tensor([0.5, 0.5]), n_classes=2)
    assert out == {
        "success_rate": [1.0],
        "purity": [1.0],
        "solutions_found": [2.0],
        "behaviour_entropy": [pytest.approx(1.0)],
    }


def test_a_mixed_option_holds_its_majority_class_and_is_impure():
    # option 0: 3 of class 0, 1 of class 1; option 1: all class 0 -> one family held
    option = _t([0, 0, 0, 0, 1, 1])
    classes = _t([0, 0, 0, 1, 0, 0])
    out = versatility(option, classes, torch.tensor([0.5, 0.5]), n_classes=4)
    assert out["solutions_found"] == [1.0]
    assert out["purity"] == [pytest.approx(0.5 * 0.75 + 0.5 * 1.0)]
    p = torch.tensor([5 / 6, 1 / 6], dtype=torch.float64)
    assert out["behaviour_entropy"] == [pytest.approx(float(-(p * p.log()).sum()) / math.log(4))]


def test_failures_hold_nothing_and_options_below_the_floor_are_not_counted():
    option = _t([0, 0, 0, 1, 1, 2, 2])
    classes = _t([-1, -1, 0, 1, 1, 2, 2])  # option 0 mostly fails; option 2 below the floor
    out = versatility(option, classes, torch.tensor([0.6, 0.38, 0.02]), n_classes=3)
    assert out["solutions_found"] == [1.0]  # only option 1's class 1
    assert out["success_rate"] == [pytest.approx(5 / 7)]
    assert out["purity"] == [pytest.approx((0.6 * 2 / 3 + 0.38 * 1.0) / 0.98)]


def test_half_successful_is_not_held_and_nothing_successful_has_zero_entropy():
    out = versatility(_t([0, 0]), _t([-1, 1]), torch.tensor([1.0]), n_classes=2)
    assert out["solutions_found"] == [0.0]
    none = versatility(_t([0, 0]), _t([-1, -1]), torch.tensor([1.0]), n_classes=2)
    assert none["behaviour_entropy"] == [0.0] and none["success_rate"] == [0.0]


def test_members_are_measured_apart():
    option = _t([[0, 1], [0, 0]])
    classes = _t([[0, 1], [1, 1]])
    out = versatility(option, classes, torch.tensor([[0.5, 0.5], [1.0, 0.0]]), n_classes=2)
    assert out["solutions_found"] == [2.0, 1.0]
    assert out["behaviour_entropy"] == [pytest.approx(1.0), 0.0]


def test_purity_is_nan_when_no_option_above_the_floor_drew_a_sample():
    out = versatility(_t([1]), _t([0]), torch.tensor([0.99, 0.01]), n_classes=2)
    assert math.isnan(out["purity"][0]) and out["solutions_found"] == [0.0]


@pytest.mark.parametrize(
    "option, classes, prior, n, match",
    [
        (_t([0, 1]), _t([0]), torch.ones(2), 2, "same|shape"),
        (_t([0]), _t([2]), torch.ones(1), 2, "-1 .. 1, got values from 2"),
        (_t([0]), _t([0]), torch.ones(1), 0, "n_classes must be an integer >= 1, got 0"),
        (_t([[0], [0]]), _t([[0], [0]]), torch.ones(3, 1), 1, "prior must have shape"),
    ],
)
def test_bad_inputs_are_named(option, classes, prior, n, match):
    with pytest.raises(ValueError, match=match):
        versatility(option, classes, prior, n_classes=n)


def test_a_policy_with_one_option_per_mode_holds_both_and_one_option_holds_one():
    from hireps_torch.envs.toy import TwoGaussians
    from hireps_torch.policies import HierarchicalPolicy
    from hireps_torch.versatility import policy_versatility

    task = TwoGaussians(width=0.5)
    both = HierarchicalPolicy.create(2, 0, 2, init_mean=task.modes.to(torch.float64), init_std=0.05)
    ctx = torch.zeros(400, 0, dtype=torch.float64)
    out = policy_versatility(both, task, ctx, torch.Generator().manual_seed(0))
    assert out["solutions_found"] == [2.0] and out["purity"] == [1.0]
    assert out["success_rate"] == [1.0] and out["behaviour_entropy"][0] > 0.95
    one = HierarchicalPolicy.create(
        2, 0, 2, init_mean=task.modes[[1, 1]].to(torch.float64), init_std=0.05
    )
    out = policy_versatility(one, task, ctx, torch.Generator().manual_seed(0))
    assert out["solutions_found"] == [1.0] and out["behaviour_entropy"] == [0.0]
