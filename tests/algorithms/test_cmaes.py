"""The CMA-ES adapter: pycma behind ask/tell, seeded per member, checkpointed."""

import numpy as np
import pytest
import torch

from hireps_torch.algorithms.cmaes import CMAES


def _sphere(theta):
    return -((theta - 1.0) ** 2).sum(-1)


def _steps(algo, n):
    for _ in range(n):
        theta = algo.ask(None)
        diag = algo.tell(None, theta, _sphere(theta))
    return theta, diag


def test_ask_and_tell_shapes_and_the_policy_mirrors_pycmas_distribution():
    algo = CMAES.create(3, popsize=8, init_std=torch.tensor([1.0, 0.5, 0.25]), seed=0)
    torch.testing.assert_close(
        algo.policy.sub_policies[0].covariance,
        torch.diag(torch.tensor([1.0, 0.25, 0.0625], dtype=torch.float64)),
    )
    theta, diag = _steps(algo, 40)
    assert theta.shape == (8, 3) and theta.dtype == torch.float64
    assert diag["iteration"] == 40 and diag["n_active_options"] == 1
    assert set(diag) >= {"sigma", "policy_entropy", "mean_return", "max_return"}
    es = algo.strategies[0]
    opt = algo.policy.sub_policies[0]
    torch.testing.assert_close(opt.bias, torch.as_tensor(es.mean))
    # pycma's own candidates scatter as the mirrored Gaussian says
    draws = np.concatenate([np.asarray(es.ask()) for _ in range(400)])
    torch.testing.assert_close(
        torch.as_tensor(np.cov(draws.T)), opt.covariance, rtol=0.15, atol=1e-12
    )
    assert algo.act(2).shape == (2, 3)
    assert torch.equal(algo.act(1)[0], opt.bias)


def test_the_same_seed_gives_the_same_run_and_a_member_its_ordinary_run():
    a, b = CMAES.create(4, popsize=6, seed=3), CMAES.create(4, popsize=6, seed=3)
    assert torch.equal(_steps(a, 5)[0], _steps(b, 5)[0])
    population = CMAES.create(4, popsize=6, seed=[1, 3])
    theta, diag = _steps(population, 5)
    assert theta.shape == (2, 6, 4) and diag["iteration"] == [5, 5]
    assert torch.equal(theta[1], _steps(CMAES.create(4, popsize=6, seed=3), 5)[0])
    assert not torch.equal(theta[0], theta[1])


def test_numpys_global_generator_is_left_alone():
    before = np.random.get_state()[1].copy()  # noqa: NPY002
    _steps(CMAES.create(3, popsize=5, seed=0), 3)
    assert np.array_equal(np.random.get_state()[1], before)  # noqa: NPY002


def test_a_state_dict_round_trip_continues_exactly_and_a_wrong_one_changes_nothing():
    algo = CMAES.create(3, popsize=5, seed=2)
    _steps(algo, 4)
    state = algo.state_dict()
    after = _steps(algo, 3)[0]
    again = CMAES.create(3, popsize=5, seed=9)
    again.load_state_dict(state)
    assert torch.equal(_steps(again, 3)[0], after) and again.iteration == 7
    other = CMAES.create(4, popsize=5, seed=2)
    mean = other.policy.sub_policies[0].bias.clone()
    with pytest.raises(ValueError, match="do not fit D = 4"):
        other.load_state_dict(state)
    assert torch.equal(other.policy.sub_policies[0].bias, mean) and other.iteration == 0


def test_tell_refuses_other_candidates_or_returns_and_changes_nothing():
    algo = CMAES.create(3, popsize=5, seed=0)
    with pytest.raises(ValueError, match="needs the candidates of an ask"):
        algo.tell(None, torch.zeros(5, 3), torch.zeros(5))
    theta = algo.ask(5)
    with pytest.raises(ValueError, match="candidates of the last ask, unchanged"):
        algo.tell(None, theta + 1, _sphere(theta))
    with pytest.raises(ValueError, match=r"returns must have shape \(5,\)"):
        algo.tell(None, theta, torch.zeros(4))
    with pytest.raises(ValueError, match="returns"):
        algo.tell(None, theta, torch.full((5,), float("nan")))
    assert algo.iteration == 0
    algo.tell(None, theta, _sphere(theta))  # the ask still stands
    with pytest.raises(ValueError, match="popsize 5 candidates, not 4"):
        algo.ask(4)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"param_dim": 1, "popsize": 5}, "param_dim"),
        ({"param_dim": 3, "popsize": 1}, "popsize"),
        ({"param_dim": 3, "popsize": 5, "init_std": 0.0}, "init_std must be finite and > 0"),
        ({"param_dim": 3, "popsize": 5, "init_mean": torch.zeros(2)}, r"init_mean must have"),
    ],
)
def test_bad_settings_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CMAES.create(**kwargs)


def test_a_member_stopped_by_pycma_keeps_its_distribution_and_stays_representable():
    algo = CMAES.create(2, popsize=6, init_std=2.0, seed=[1, 2])
    for _ in range(1500):  # far past convergence on an exact optimum
        theta = algo.ask(None)
        diag = algo.tell(None, theta, _sphere(theta))
    assert diag["stopped"] == [True, True]
    cov = algo.policy.sub_policies[0].covariance
    assert bool(torch.all(torch.linalg.eigvalsh(cov) > 0))  # no underflow to zero
    before = [es.mean.copy() for es in algo.strategies]
    theta = algo.ask(None)
    algo.tell(None, theta, _sphere(theta))
    assert all(np.array_equal(b, es.mean) for b, es in zip(before, algo.strategies, strict=True))
