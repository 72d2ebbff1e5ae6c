"""Linear-Gaussian sub-policy: theta ~ N(W psi + b, L L^T)."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from hireps_torch.checks import as_finite_f64, check_positive

__all__ = ["LinearGaussian", "weighted_least_squares"]


def weighted_least_squares(
    inputs: Tensor, targets: Tensor, weights: Tensor, ridge: float = 0.0
) -> tuple[Tensor, Tensor]:
    """Weighted least squares with an (unpenalised) bias, in float64.

    Args:
        inputs: (N, F) regressors (F may be 0).
        targets: (N, D).
        weights: (N,) non-negative sample weights, not all zero.
        ridge: Tikhonov penalty on the slopes (not the bias), relative to the weight sum.

    Returns:
        (weight (D, F), bias (D,)) minimising sum_i w_i ||y_i - W x_i - b||^2 + ridge ||W||^2.
    """
    X = torch.cat(
        [torch.ones(inputs.shape[0], 1, dtype=torch.float64), inputs.to(torch.float64)], 1
    )
    Y = targets.to(torch.float64)
    w = weights.to(torch.float64)
    A = X.T @ (w[:, None] * X)
    if ridge > 0 and X.shape[1] > 1:
        reg = torch.full((X.shape[1],), ridge * float(w.sum()), dtype=torch.float64)
        reg[0] = 0.0
        A = A + torch.diag(reg)
    B = X.T @ (w[:, None] * Y)
    try:
        beta = torch.linalg.solve(A, B)
    except RuntimeError:  # singular (fewer effective samples than regressors): least-norm fit
        beta = torch.linalg.lstsq(A, B, driver="gelsd").solution
    return beta[1:].T.contiguous(), beta[0].contiguous()


class LinearGaussian(nn.Module):
    """Gaussian with a mean linear in the features and a full covariance held by its Cholesky
    factor: ``theta ~ N(weight @ psi + bias, chol @ chol.T)``.

    Shapes: ``features: (N, F)``, ``theta: (N, D)``. ``F = 0`` gives a context-free Gaussian.
    Parameters are ``nn.Parameter``s without gradients (the fit is closed form), so they travel
    with ``state_dict`` and TorchRL weight updates.

    Args:
        in_features: F, number of input features.
        action_dim: D, dimension of theta.
        init_mean: (D,) initial mean (bias); zeros by default.
        init_std: initial standard deviation (scalar or (D,)).
        min_variance: floor on the covariance after every fit: a float floors its eigenvalues;
            a (D,) tensor m floors the eigenvalues of ``diag(m)^-1/2 Sigma diag(m)^-1/2`` at 1
            (per-dimension floors for parameters in different units).
        covariance_prior: k, pseudo-samples of a prior centred on the current covariance: a
            refit returns ``(n_eff S + k Sigma_old) / (n_eff + k)`` with S the weighted residual
            covariance and ``n_eff = (sum w)^2 / sum w^2`` the effective number of samples (the
            MAP estimate under an inverse-Wishart-type prior). It keeps exploration from
            collapsing when an option has fewer effective samples than dimensions; 0 (default)
            is plain weighted maximum likelihood.
        dtype: parameter dtype (float64 by default: parameter spaces are small).
    """

    def __init__(
        self,
        in_features: int,
        action_dim: int,
        init_mean: Tensor | None = None,
        init_std: float | Tensor = 1.0,
        min_variance: float | Tensor = 1e-8,
        dtype: torch.dtype = torch.float64,
        covariance_prior: float = 0.0,
    ) -> None:
        super().__init__()
        if action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {action_dim}")
        if in_features < 0:
            raise ValueError(f"in_features must be >= 0, got {in_features}")
        floor = torch.as_tensor(min_variance, dtype=torch.float64).detach().clone()
        if floor.dim() == 0:
            floor = floor.expand(action_dim).clone()
        if (
            floor.shape != (action_dim,)
            or not bool(torch.isfinite(floor).all())
            or bool((floor <= 0).any())
        ):
            raise ValueError(
                f"min_variance must be > 0 (a float or a ({action_dim},) tensor), got "
                f"{torch.as_tensor(min_variance).tolist()}"
            )
        if not (math.isfinite(covariance_prior) and covariance_prior >= 0):
            raise ValueError(f"covariance_prior must be finite and >= 0, got {covariance_prior}")
        self.covariance_prior = float(covariance_prior)
        std = torch.as_tensor(init_std, dtype=dtype).expand(action_dim).clone()
        check_positive("init_std", std)
        mean = (
            torch.zeros(action_dim, dtype=dtype)
            if init_mean is None
            else torch.as_tensor(init_mean, dtype=dtype).clone()
        )
        if mean.shape != (action_dim,):
            raise ValueError(f"init_mean must have shape ({action_dim},), got {tuple(mean.shape)}")
        self.in_features = in_features
        self.action_dim = action_dim
        self.min_variance = floor  # (D,) float64, a float given is broadcast
        self.weight = nn.Parameter(torch.zeros(action_dim, in_features, dtype=dtype), False)
        self.bias = nn.Parameter(mean, requires_grad=False)
        self.chol = nn.Parameter(torch.diag(std), requires_grad=False)

    # ---- distribution ---------------------------------------------------------------------
    def _features(self, features: Tensor) -> Tensor:
        if features.dim() != 2 or features.shape[1] != self.in_features:
            raise ValueError(
                f"features must have shape (N, {self.in_features}), got {tuple(features.shape)}"
            )
        return features.to(self.bias.dtype)

    def mean(self, features: Tensor) -> Tensor:
        """features: (N, F) -> mean (N, D)."""
        x = self._features(features)
        return x @ self.weight.T + self.bias

    @property
    def covariance(self) -> Tensor:
        """(D, D) covariance chol @ chol.T."""
        return self.chol @ self.chol.T

    def sample(self, features: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """features: (N, F) -> theta (N, D)."""
        mu = self.mean(features)
        noise = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        return mu + noise @ self.chol.T

    def log_prob(self, features: Tensor, theta: Tensor) -> Tensor:
        """features: (N, F), theta: (N, D) -> log density (N,)."""
        mu = self.mean(features)
        if theta.shape != mu.shape:
            raise ValueError(f"theta must have shape {tuple(mu.shape)}, got {tuple(theta.shape)}")
        diff = (theta.to(mu.dtype) - mu).T  # (D, N)
        z: Tensor = torch.linalg.solve_triangular(self.chol, diff, upper=False)
        half_logdet = torch.log(torch.diagonal(self.chol)).sum()
        return -0.5 * (z**2).sum(0) - half_logdet - 0.5 * self.action_dim * math.log(2 * math.pi)

    def entropy(self) -> Tensor:
        """Differential entropy (scalar) of the Gaussian (independent of the features)."""
        half_logdet = torch.log(torch.diagonal(self.chol)).sum()
        return half_logdet + 0.5 * self.action_dim * (1.0 + math.log(2 * math.pi))

    # ---- weighted maximum likelihood --------------------------------------------------------
    @torch.no_grad()
    def weighted_fit(
        self, inputs: Tensor, targets: Tensor, weights: Tensor, ridge: float = 1e-6
    ) -> None:
        """Weighted maximum-likelihood refit of mean and covariance.

        The mean is the weighted least-squares fit of ``targets`` on ``[1, inputs]`` (ridge on
        the slopes); the covariance is the weighted covariance of the residuals
        ``sum_i w_i r_i r_i^T / sum_i w_i``, shrunk toward the current covariance when
        ``covariance_prior > 0``, then floored by ``min_variance`` (see the class docstring).

        Args:
            inputs: (N, F) features.
            targets: (N, D) parameters / actions.
            weights: (N,) non-negative, finite, not all zero.
            ridge: slope penalty relative to the weight sum (0 for plain WLS).
        """
        x = self._features(inputs)
        if targets.shape != (x.shape[0], self.action_dim):
            raise ValueError(
                f"targets must have shape ({x.shape[0]}, {self.action_dim}), got "
                f"{tuple(targets.shape)}"
            )
        w = weights.to(torch.float64)
        if w.shape != (x.shape[0],):
            raise ValueError(f"weights must have shape ({x.shape[0]},), got {tuple(w.shape)}")
        if not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or float(w.sum()) <= 0:
            raise ValueError("weights must be finite, non-negative and not all zero")
        as_finite_f64("targets", targets)
        W, b = weighted_least_squares(x, targets, w, ridge=ridge)
        resid = targets.to(torch.float64) - (x.to(torch.float64) @ W.T + b)
        cov = (w[:, None] * resid).T @ resid / w.sum()
        if self.covariance_prior > 0:
            n_eff = w.sum() ** 2 / (w**2).sum()
            k = self.covariance_prior
            cov = (n_eff * cov + k * self.covariance.to(torch.float64)) / (n_eff + k)
        self.weight.copy_(W.to(self.weight.dtype))
        self.bias.copy_(b.to(self.bias.dtype))
        self.set_covariance(cov)

    @torch.no_grad()
    def set_covariance(self, cov: Tensor) -> None:
        """Set the covariance (D, D), symmetrised and floored at ``min_variance``."""
        cov = cov.to(torch.float64)
        cov = 0.5 * (cov + cov.T)
        root = self.min_variance.sqrt()
        scale = root[:, None] * root[None, :]
        evals, evecs = torch.linalg.eigh(cov / scale)
        if bool((evals < 1.0).any()):
            cov = (evecs * evals.clamp_min(1.0)) @ evecs.T * scale
            cov = 0.5 * (cov + cov.T)
        self.chol.copy_(torch.linalg.cholesky(cov).to(self.chol.dtype))
