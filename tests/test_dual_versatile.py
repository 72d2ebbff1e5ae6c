"""The options' prior-entropy floor: its dual against scipy on the primal, and its limits."""

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from hireps_torch.algorithms import EpisodicHiREPS
from hireps_torch.dual.episodic import episodic_solution
from hireps_torch.dual.solver import LbfgsSettings
from hireps_torch.dual.versatile import entropy_floor_solution, prior_entropy


def _primal(R, lr, eps, kappa, h, phi, starts):
    """max sum P R  s.t. KL(P || q p~) <= eps, E_P[-log p~] <= kappa, H(m) >= h, features
    kept, P a distribution: SLSQP over the N x O table from each of ``starts``; the best
    point that meets every constraint (to 1e-7)."""
    N, O = lr.shape
    logq = (lr - math.log(N)).reshape(-1)

    def H(P):
        m = P.reshape(N, O).sum(0)
        return -np.sum(m * np.log(np.maximum(m, 1e-300)))

    cons = [
        {"type": "eq", "fun": lambda P: P.sum() - 1},
        {"type": "ineq", "fun": lambda P: eps - np.sum(P * (np.log(np.maximum(P, 1e-300)) - logq))},
        {"type": "ineq", "fun": lambda P: H(P) - h},
    ]
    if kappa is not None:
        cons.append({"type": "ineq", "fun": lambda P: kappa + np.sum(P * lr.reshape(-1))})
    if phi is not None:
        D = phi - phi.mean(0)
        cons.append({"type": "eq", "fun": lambda P: P.reshape(N, O).sum(1) @ D})
    best = None
    for x0 in starts:
        res = minimize(
            lambda P: -np.sum(P.reshape(N, O) * R[:, None]),
            x0.reshape(-1),
            constraints=cons,
            bounds=[(0, 1)] * (N * O),
            method="SLSQP",
            options={"ftol": 1e-12, "maxiter": 3000},
        )
        feasible = all(
            (c["fun"](res.x) >= -1e-7)
            if c["type"] == "ineq"
            else np.all(abs(c["fun"](res.x)) < 1e-7)
            for c in cons
        )
        if feasible and (best is None or res.fun < best.fun):
            best = res
    assert best is not None, "no start gave a feasible point"
    return best.x.reshape(N, O), -best.fun


def _problem(seed, N=10, O=3):
    g = torch.Generator().manual_seed(seed)
    R = torch.randn(1, N, generator=g, dtype=torch.float64) * 2
    lr = torch.log_softmax(torch.randn(1, N, O, generator=g, dtype=torch.float64) * 2, -1)
    phi = torch.randn(1, N, 2, generator=g, dtype=torch.float64)
    return R, lr, phi


@pytest.mark.parametrize("seed", [3, 4])
@pytest.mark.parametrize("kappa, features", [(None, False), (0.5, False), (None, True)])
def test_the_floored_dual_matches_scipy_on_the_primal(seed, kappa, features):
    R, lr, phi = _problem(seed)
    phi = phi if features else None
    eps = torch.full((1, 1), 0.8, dtype=torch.float64)
    k = None if kappa is None else torch.full((1, 1), kappa, dtype=torch.float64)
    plain = episodic_solution(R, lr, eps, phi, k, LbfgsSettings())
    H0 = float(prior_entropy(plain.weights[0, 0]))
    h = H0 + 0.5 * (math.log(3) - H0)  # above the ordinary solution's entropy
    sol, lam, H, used = entropy_floor_solution(
        R, lr, eps, phi, k, torch.tensor([h], dtype=torch.float64), plain
    )
    ours = sol.weights[0, 0].numpy()
    reference, best = _primal(
        R[0].numpy(),
        lr[0].numpy(),
        0.8,
        kappa,
        h,
        None if phi is None else phi[0].numpy(),
        starts=[np.exp(lr[0].numpy()) / 10],  # from q p~: independent of our solution
    )
    assert bool(sol.converged[0]) and float(used[0]) == h
    assert float((ours.sum(1) * R[0].numpy()).sum()) == pytest.approx(best, abs=1e-6)
    np.testing.assert_allclose(ours, reference, atol=1e-4)
    assert float(H[0]) == pytest.approx(h, abs=1e-5)  # the floor is active
    assert float(lam[0]) > 0 and float(sol.kl[0, 0]) <= 0.8 * (1 + 1e-6)


def test_a_floor_met_already_leaves_the_ordinary_solution_bit_for_bit():
    R, lr, _ = _problem(5)
    eps = torch.full((1, 1), 0.5, dtype=torch.float64)
    plain = episodic_solution(R, lr, eps, None, None, LbfgsSettings())
    for h in (0.0, float(prior_entropy(plain.weights[0, 0]))):
        sol, lam, _, _ = entropy_floor_solution(
            R, lr, eps, None, None, torch.tensor([h], dtype=torch.float64), plain
        )
        assert torch.equal(sol.weights, plain.weights) and float(lam[0]) == 0.0


def test_a_floor_of_zero_is_the_papers_hireps_exactly():
    def run(floor):
        algo = EpisodicHiREPS.create(2, n_options=4, seed=[1, 2], prior_entropy_floor=floor)
        f = lambda t: -((t - 1) ** 2).sum(-1)  # noqa: E731
        for _ in range(4):
            theta = algo.ask(30)
            algo.tell(None, theta, f(theta))
        return algo.policy.state_dict()

    plain, zero = run(None), run(0.0)
    assert all(torch.equal(plain[k], zero[k]) for k in plain)


def test_pruned_options_stay_empty_and_the_floor_is_reported():
    algo = EpisodicHiREPS.create(
        2, n_options=6, seed=[0], prior_entropy_floor=1.0, init_std=2.0, kappa_rel=0.8
    )
    modes = torch.tensor([[-2.0, -2.0], [2.0, 2.0]], dtype=torch.float64)

    def reward(t):
        return torch.exp(-0.5 * ((t[..., None, :] - modes) ** 2).sum(-1)).sum(-1)

    for _ in range(25):
        theta = algo.ask(200)
        diag = algo.tell(None, theta, reward(theta))
    assert {"lambda", "prior_entropy", "entropy_floor"} <= set(diag)
    prior = algo.policy.gating.probs(torch.zeros(1, 1, 0, dtype=torch.float64))[0, 0]
    assert torch.all(prior[~algo.policy.active[0]] == 0)
    assert diag["prior_entropy"][0] >= diag["entropy_floor"][0] - 1e-4


def test_a_floor_outside_zero_to_one_is_refused():
    with pytest.raises(ValueError, match="prior_entropy_floor must be in"):
        EpisodicHiREPS.create(2, n_options=3, prior_entropy_floor=1.5)
    with pytest.raises(ValueError, match="prior_entropy_floor"):
        EpisodicHiREPS.create(2, n_options=3, prior_entropy_floor=-0.1)
