import math

import numpy as np
import pytest
import torch

from hireps_torch.policies import LinearGaussian, weighted_least_squares


def test_sample_and_log_prob_match_torch_distribution(gen):
    pol = LinearGaussian(2, 3, init_mean=torch.tensor([1.0, -1.0, 0.5]), init_std=0.7)
    pol.weight.data = torch.randn(3, 2, generator=gen, dtype=torch.float64)
    pol.set_covariance(torch.tensor([[1.0, 0.3, 0.0], [0.3, 2.0, 0.4], [0.0, 0.4, 0.5]]))
    x = torch.randn(500, 2, generator=gen, dtype=torch.float64)
    th = pol.sample(x, gen)
    ref = torch.distributions.MultivariateNormal(pol.mean(x), covariance_matrix=pol.covariance)
    assert torch.allclose(pol.log_prob(x, th), ref.log_prob(th), atol=1e-10)
    assert float(pol.entropy()) == pytest.approx(float(ref.entropy()[0]), abs=1e-10)


def test_weighted_fit_equals_closed_form(gen):
    N, F, D = 200, 3, 2
    x = torch.randn(N, F, generator=gen, dtype=torch.float64)
    W_true = torch.randn(D, F, generator=gen, dtype=torch.float64)
    y = x @ W_true.T + 0.3 * torch.randn(N, D, generator=gen, dtype=torch.float64) + 2.0
    w = torch.rand(N, generator=gen, dtype=torch.float64)

    pol = LinearGaussian(F, D)
    pol.weighted_fit(x, y, w, ridge=0.0)

    # closed form with numpy: beta = (X^T W X)^-1 X^T W Y, Sigma = sum w r r^T / sum w
    X = np.hstack([np.ones((N, 1)), x.numpy()])
    Wd = np.diag(w.numpy())
    beta = np.linalg.solve(X.T @ Wd @ X, X.T @ Wd @ y.numpy())
    resid = y.numpy() - X @ beta
    cov = (w.numpy()[:, None] * resid).T @ resid / w.numpy().sum()
    np.testing.assert_allclose(pol.bias.detach().numpy(), beta[0], atol=1e-10)
    np.testing.assert_allclose(pol.weight.detach().numpy(), beta[1:].T, atol=1e-10)
    np.testing.assert_allclose(pol.covariance.detach().numpy(), cov, atol=1e-10)


def test_context_free_fit_is_weighted_mean_and_covariance(gen):
    th = torch.randn(50, 2, generator=gen, dtype=torch.float64)
    w = torch.rand(50, generator=gen, dtype=torch.float64)
    pol = LinearGaussian(0, 2)
    pol.weighted_fit(torch.zeros(50, 0), th, w)
    wn = w / w.sum()
    mu = (wn[:, None] * th).sum(0)
    cov = (wn[:, None] * (th - mu)).T @ (th - mu)
    assert torch.allclose(pol.bias, mu, atol=1e-12)
    assert torch.allclose(pol.covariance, cov, atol=1e-12)


def test_variance_floor_keeps_collapsed_fit_finite():
    pol = LinearGaussian(0, 2, min_variance=1e-4)
    th = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    pol.weighted_fit(torch.zeros(2, 0), th, torch.tensor([1.0, 0.0]))  # one sample: zero cov
    evals = torch.linalg.eigvalsh(pol.covariance)
    assert bool(torch.isfinite(pol.chol).all())
    assert float(evals.min()) == pytest.approx(1e-4, rel=1e-6)
    assert torch.allclose(pol.bias, torch.tensor([1.0, 2.0], dtype=torch.float64))


def test_few_samples_many_features_stays_finite(gen):
    pol = LinearGaussian(10, 2)
    x = torch.randn(3, 10, generator=gen)
    pol.weighted_fit(x, torch.randn(3, 2, generator=gen), torch.ones(3))
    assert bool(torch.isfinite(pol.weight).all()) and bool(torch.isfinite(pol.chol).all())


def test_wls_ridge_shrinks_slopes_only(gen):
    x = torch.randn(100, 2, generator=gen, dtype=torch.float64)
    x = x - x.mean(0)  # centred inputs: the unpenalised bias is mean(y) whatever the slopes
    y = 3.0 * x[:, :1] + 5.0
    W0, b0 = weighted_least_squares(x, y, torch.ones(100))
    W1, b1 = weighted_least_squares(x, y, torch.ones(100), ridge=10.0)
    assert float(W0[0, 0]) == pytest.approx(3.0, abs=1e-10)
    assert float(b0[0]) == pytest.approx(5.0, abs=1e-10)
    assert float(W1.abs().sum()) < 0.5 * float(W0.abs().sum())  # the slopes shrink ...
    assert float(b1[0]) == pytest.approx(5.0, abs=1e-10)  # ... the bias does not


def test_bad_inputs_raise():
    pol = LinearGaussian(2, 3)
    with pytest.raises(ValueError, match=r"features must have shape \(N, 2\)"):
        pol.mean(torch.zeros(4, 3))
    with pytest.raises(ValueError, match=r"theta must have shape \(4, 3\)"):
        pol.log_prob(torch.zeros(4, 2), torch.zeros(4, 2))
    with pytest.raises(ValueError, match="not all zero"):
        pol.weighted_fit(torch.zeros(4, 2), torch.zeros(4, 3), torch.zeros(4))
    with pytest.raises(ValueError, match="non-finite"):
        pol.weighted_fit(torch.zeros(4, 2), torch.full((4, 3), math.nan), torch.ones(4))
    with pytest.raises(ValueError, match="init_std"):
        LinearGaussian(0, 2, init_std=-1.0)


def test_state_dict_round_trip(gen):
    pol = LinearGaussian(2, 2)
    pol.weighted_fit(
        torch.randn(20, 2, generator=gen),
        torch.randn(20, 2, generator=gen),
        torch.rand(20, generator=gen),
    )
    other = LinearGaussian(2, 2)
    other.load_state_dict(pol.state_dict())
    for k, v in pol.state_dict().items():
        assert torch.equal(v, other.state_dict()[k])


def test_covariance_prior_shrinks_the_refit_toward_the_old_covariance():
    gen = torch.Generator().manual_seed(0)
    D, N = 5, 40
    x = torch.randn(N, 0, dtype=torch.float64, generator=gen)
    theta = torch.randn(N, D, dtype=torch.float64, generator=gen)
    w = torch.zeros(N, dtype=torch.float64)
    w[:3] = torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64)  # 3 samples for 5 dimensions
    plain = LinearGaussian(0, D, init_std=0.7, min_variance=1e-8)
    plain.weighted_fit(x, theta, w)
    assert torch.linalg.eigvalsh(plain.covariance).min() < 1e-7  # collapsed onto a plane

    k = 5.0
    shrunk = LinearGaussian(0, D, init_std=0.7, min_variance=1e-8, covariance_prior=k)
    old = shrunk.covariance.clone()
    shrunk.weighted_fit(x, theta, w)
    n_eff = float(w.sum() ** 2 / (w**2).sum())
    expected = (n_eff * plain.covariance + k * old) / (n_eff + k)
    assert torch.allclose(shrunk.covariance, expected, atol=1e-10)
    assert torch.linalg.eigvalsh(shrunk.covariance).min() > k / (n_eff + k) * 0.49 - 1e-9
    with pytest.raises(ValueError, match="covariance_prior must be finite and >= 0, got -1"):
        LinearGaussian(0, D, covariance_prior=-1.0)


def test_per_dimension_variance_floor_keeps_each_parameter_exploring():
    gen = torch.Generator().manual_seed(1)
    floor = torch.tensor([1e-4, 1e-4, 0.09], dtype=torch.float64)  # rad^2, rad^2, (rad/s)^2
    pol = LinearGaussian(0, 3, init_std=torch.tensor([0.02, 0.02, 0.3]), min_variance=floor)
    theta = torch.randn(30, 3, dtype=torch.float64, generator=gen) * 1e-4  # nearly one point
    pol.weighted_fit(torch.zeros(30, 0, dtype=torch.float64), theta, torch.ones(30))
    cov = pol.covariance
    assert torch.all(cov.diagonal() >= floor * (1 - 1e-9))
    scaled = cov / (floor.sqrt()[:, None] * floor.sqrt()[None, :])
    assert torch.linalg.eigvalsh(scaled).min() >= 1 - 1e-9
    with pytest.raises(
        ValueError, match=r"min_variance must be in \[1e-100, 1e\+100\] \(a float or a \(3,\)"
    ):
        LinearGaussian(0, 3, min_variance=torch.tensor([1.0, 0.0, 1.0]))


def test_the_variance_floor_travels_with_the_state_dict():
    """A policy saved with floor 0.5 and loaded into a default one refits with 0.5; a
    checkpoint written before the floor was saved keeps the loading module's floor."""
    saved = LinearGaussian(0, 2, min_variance=0.5)
    loaded = LinearGaussian(0, 2)
    loaded.load_state_dict(saved.state_dict())
    theta = torch.zeros(5, 2, dtype=torch.float64)  # no spread: the floor is the covariance
    new = loaded.fit_parameters(torch.zeros(5, 0), theta, torch.ones(5, dtype=torch.float64))
    torch.testing.assert_close(
        new["chol"] @ new["chol"].mT, 0.5 * torch.eye(2, dtype=torch.float64)
    )
    old = saved.state_dict()
    del old["min_variance"]
    kept = LinearGaussian(0, 2, min_variance=0.3)
    kept.load_state_dict(old)
    assert kept.min_variance.tolist() == [0.3, 0.3]
    bad = saved.state_dict()
    bad["min_variance"] = torch.tensor([0.5, 5e-324], dtype=torch.float64)
    with pytest.raises(ValueError, match="min_variance must be in"):
        LinearGaussian(0, 2).load_state_dict(bad)


def test_a_subnormal_variance_floor_is_refused_naming_it():
    with pytest.raises(ValueError, match=r"must be in \[1e-100, 1e\+100\] .* got 5e-324"):
        LinearGaussian(0, 2, min_variance=5e-324)
