"""Linear-Gaussian sub-policy: theta ~ N(W psi + b, L L^T)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor, nn

from hireps_torch._linalg import matmul_each, min_norm_lstsq, reduce_each
from hireps_torch.checks import (
    FIX_SAMPLES,
    all_finite,
    as_checked,
    as_float_tensor,
    as_weights,
    check_count,
    check_float_dtype,
    check_nonnegative_float,
    check_positive,
)
from hireps_torch.policies._module import PolicyModule
from hireps_torch.policies._population import Generators, check_population_generators, normal

__all__ = [
    "FLOOR_RANGE",
    "LinearGaussian",
    "initial_std",
    "map_linear_regression",
    "power_of_two_scaled",
    "variance_floor",
    "weighted_least_squares",
]


def weighted_least_squares(
    inputs: Tensor, targets: Tensor, weights: Tensor, ridge: float = 0.0
) -> tuple[Tensor, Tensor]:
    """Weighted least squares with an unpenalised bias, in float64 (leading dims: batches).

    Args:
        inputs: (..., N, F) regressors (F may be 0).
        targets: (..., N, D).
        weights: (..., N) non-negative, not all zero.
        ridge: penalty on the slopes (not the bias), relative to the weight sum.

    Returns:
        (weight (..., D, F), bias (..., D)) minimising
        sum_i w_i ||y_i - W x_i - b||^2 + ridge ||W||^2.
    """
    x = inputs.to(torch.float64)
    Y = targets.to(torch.float64)
    w = weights.to(torch.float64)
    if x.shape[-1] == 0:  # no regressors: the weighted mean
        mean = matmul_each(w.unsqueeze(-2), Y).squeeze(-2) / reduce_each(w, "sum", -1, True)
        return Y.new_zeros(*Y.shape[:-2], Y.shape[-1], 0), mean
    X = torch.cat([x.new_ones(*x.shape[:-1], 1), x], -1)
    A = matmul_each(X.mT, w[..., None] * X)
    if ridge > 0 and X.shape[-1] > 1:
        reg = ridge * reduce_each(w, "sum", -1, True) * X.new_ones(X.shape[-1])
        reg[..., 0] = 0.0
        A = A + torch.diag_embed(reg)
    B = matmul_each(X.mT, w[..., None] * Y)
    beta, info = torch.linalg.solve_ex(A, B)
    singular = info != 0
    if bool(singular.any()):  # fewer effective samples than regressors: least-norm fit
        least_norm = min_norm_lstsq(A[singular], B[singular])
        beta = beta.clone()
        beta[singular] = least_norm
    return beta[..., 1:, :].mT.contiguous(), beta[..., 0, :].contiguous()


def power_of_two_scaled(w: Tensor, population: bool = False) -> Tensor:
    """``w`` times an exact power of 2 bringing its peak near 1, unless the peak is within
    2^-200 .. 2^200; with ``population`` each member (leading dim) on its own."""
    peak = w.flatten(1).amax(1).view(-1, *[1] * (w.dim() - 1)) if population else w.amax()
    far = (peak < 2.0**-200) | (peak > 2.0**200)
    if not bool(far.any()):
        return w
    exponent = torch.frexp(peak).exponent.to(torch.int64)
    return torch.where(far, torch.ldexp(w, -exponent), w)


def variance_floor(min_variance: float | Tensor, action_dim: int) -> Tensor:
    """``min_variance`` (a float or (D,)) checked, as a (D,) float64 tensor."""
    floor = as_float_tensor("min_variance", min_variance, allow_bool=False).clone()
    if floor.dim() == 0:
        floor = floor.expand(action_dim).clone()
    check_floor(floor, action_dim, torch.as_tensor(min_variance, dtype=torch.float64).tolist())
    return floor


FLOOR_RANGE = (1e-100, 1e100)
"""The variance floors :class:`LinearGaussian` takes (beyond them the fit or sampling overflows)."""


def check_floor(floor: Tensor, action_dim: int, given: object) -> None:
    """A ``ValueError`` naming ``given`` unless the (D,) floor is in :data:`FLOOR_RANGE`."""
    low, high = FLOOR_RANGE
    if (
        floor.shape != (action_dim,)
        or not all_finite(floor)
        or bool((floor < low).any() | (floor > high).any())
    ):
        raise ValueError(
            f"min_variance must be in [{low:g}, {high:g}] (a float or a ({action_dim},) "
            f"tensor), got {given}"
        )


def _matvec(A: Tensor, x: Tensor) -> Tensor:
    """A (..., D, F) @ x (..., F) -> (..., D)."""
    return A @ x if x.dim() == 1 else (A @ x[..., None])[..., 0]


def map_linear_regression(
    inputs: Tensor,
    targets: Tensor,
    weights: Tensor,
    prior_weight: Tensor,
    prior_bias: Tensor,
    prior_samples: float,
    ridge: float = 0.0,
) -> tuple[Tensor, Tensor]:
    """Weighted linear regression with a Gaussian prior on the coefficients (MAP), in float64.

    On standardised inputs ``z_i = [1, (x_i - m) / s]`` (weighted mean m, std s; s = 1 where
    an input has no spread), w normalised to sum 1 and ``n_eff = 1 / sum_i w_i^2``:

        beta = argmin  sum_i w_i ||y_i - beta^T z_i||^2 + (k / n_eff) ||beta - beta_old||^2
                       + ridge ||W||^2,

    beta_old from ``prior_weight``, ``prior_bias``; ``k = 0``: weighted least squares; leading
    dims are batches.

    Args:
        inputs: (..., N, F) regressors.
        targets: (..., N, D).
        weights: (..., N) non-negative, not all zero.
        prior_weight: (..., D, F) slopes the prior is centred on.
        prior_bias: (..., D) bias the prior is centred on.
        prior_samples: k >= 0.
        ridge: penalty on the slopes W, relative to the weight sum.

    Returns:
        (weight (..., D, F), bias (..., D)).
    """
    x = inputs.to(torch.float64)
    y = targets.to(torch.float64)
    w = weights.to(torch.float64)
    w = w / reduce_each(w, "sum", -1, True)
    n_eff = 1.0 / reduce_each(w**2, "sum", -1)
    m = reduce_each(w[..., None] * x, "sum", -2)
    s = reduce_each(w[..., None] * (x - m[..., None, :]) ** 2, "sum", -2).sqrt()
    magnitude = x.abs().amax(-2) if x.shape[-2] else torch.zeros_like(m)
    s = torch.where(s > 1e-12 * magnitude, s, torch.ones_like(s))
    ones = x.new_ones(*x.shape[:-1], 1, dtype=torch.float64)
    Z = torch.cat([ones, (x - m[..., None, :]) / s[..., None, :]], -1)
    W0 = prior_weight.to(torch.float64)
    centre = prior_bias.to(torch.float64) + _matvec(W0, m)
    beta0 = torch.cat([centre[..., None, :], (W0 * s[..., None, :]).mT], -2)
    lam = (prior_samples / n_eff)[..., None]
    diag = lam * Z.new_ones(Z.shape[-1])
    diag[..., 1:] = diag[..., 1:] + ridge / s**2
    A = matmul_each(Z.mT, w[..., None] * Z) + torch.diag_embed(diag)
    B = matmul_each(Z.mT, w[..., None] * y) + lam[..., None] * beta0
    beta = torch.linalg.solve(A, B)
    W = (beta[..., 1:, :] / s[..., :, None]).mT.contiguous()
    return W, (beta[..., 0, :] - _matvec(W, m)).contiguous()


def initial_std(init_std: float | Tensor, action_dim: int) -> Tensor:
    """``init_std`` (a float or (D,), > 0) as a (D,) float64 tensor."""
    std = as_float_tensor("init_std", init_std, allow_bool=False)
    if std.dim() == 0:
        std = std.expand(action_dim)
    if std.shape != (action_dim,):
        raise ValueError(
            f"init_std must be a float or a ({action_dim},) tensor, got shape {tuple(std.shape)}"
        )
    check_positive("init_std", std)
    return std.clone()


class LinearGaussian(PolicyModule):
    """Gaussian ``theta ~ N(weight @ psi + bias, chol @ chol.T)`` with a full covariance.

    Shapes: ``features: (N, F)`` (F = 0: context-free), ``theta: (N, D)``. Parameters are
    ``nn.Parameter``s without gradients (the fit is closed form). Bool, integer or floating
    inputs are converted to the parameter dtype; non-finite ones raise a ``ValueError``.

    Args:
        in_features: F.
        action_dim: D.
        init_mean: (D,) initial bias; zeros by default.
        init_std: initial standard deviation, scalar or (D,).
        min_variance: covariance floor after every fit: a float floors the eigenvalues; a (D,)
            tensor m floors those of ``diag(m)^-1/2 Sigma diag(m)^-1/2`` at 1.
        covariance_prior: k; a refit returns ``(n_eff Sigma_w + k Sigma_old) / (n_eff + k)``
            (Sigma_w the weighted residual covariance, ``n_eff = (sum w)^2 / sum w^2``).
        mean_prior: k of :func:`map_linear_regression`, centred on the current coefficients.
        dtype: parameter dtype.
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
        mean_prior: float = 0.0,
    ) -> None:
        super().__init__()
        action_dim = check_count("action_dim", action_dim, 1)
        in_features = check_count("in_features", in_features, 0)
        check_float_dtype(dtype)
        floor = variance_floor(min_variance, action_dim)
        self.covariance_prior = check_nonnegative_float("covariance_prior", covariance_prior)
        self.mean_prior = check_nonnegative_float("mean_prior", mean_prior)
        std = initial_std(init_std, action_dim).to(dtype)
        mean = (
            torch.zeros(action_dim, dtype=dtype)
            if init_mean is None
            else as_checked("init_mean", init_mean, (action_dim,), dtype).clone()
        )
        self.in_features = in_features
        self.action_dim = action_dim
        self.min_variance: Tensor
        self.register_buffer("min_variance", floor)  # (D,) float64, a float given is broadcast
        self.weight = nn.Parameter(torch.zeros(action_dim, in_features, dtype=dtype), False)
        self.bias = nn.Parameter(mean, requires_grad=False)
        self.chol = nn.Parameter(torch.diag(std), requires_grad=False)

    _stacked = ("weight", "bias", "chol")
    _shared = ("in_features", "action_dim", "covariance_prior", "mean_prior")

    # ---- distribution ---------------------------------------------------------------------
    def _features(self, features: Tensor) -> Tensor:
        shape = (*self.batch_shape, None, self.in_features)
        return as_checked("features", features, shape, self.bias.dtype, self.bias.device)

    def mean(self, features: Tensor) -> Tensor:
        """features: ([S,] N, F) -> mean ([S,] N, D)."""
        x = self._features(features)
        return matmul_each(x, self.weight.mT) + self.bias.unsqueeze(-2)

    @property
    def covariance(self) -> Tensor:
        """([S,] D, D) covariance chol @ chol.T."""
        return self.chol @ self.chol.mT

    def sample(self, features: Tensor, generator: Generators = None) -> Tensor:
        """features: ([S,] N, F) -> theta ([S,] N, D); a population may take S generators."""
        gen = check_population_generators(self.population, generator)
        mu = self.mean(features)
        noise = normal(tuple(mu.shape), gen, mu.dtype, mu.device)
        return mu + noise @ self.chol.mT

    def log_prob(self, features: Tensor, theta: Tensor) -> Tensor:
        """features: ([S,] N, F), theta: ([S,] N, D) -> log density ([S,] N)."""
        mu = self.mean(features)
        t = as_checked("theta", theta, tuple(mu.shape), mu.dtype, mu.device)
        diff = (t - mu).mT  # ([S,] D, N)
        z: Tensor = torch.linalg.solve_triangular(self.chol, diff, upper=False)
        half_logdet = torch.log(torch.diagonal(self.chol, dim1=-2, dim2=-1)).sum(-1)
        return (
            -0.5 * (z**2).sum(-2)
            - half_logdet[..., None]
            - 0.5 * self.action_dim * math.log(2 * math.pi)
        )

    def entropy(self) -> Tensor:
        """Differential entropy: ([S]) or a scalar."""
        half_logdet = torch.log(torch.diagonal(self.chol, dim1=-2, dim2=-1)).sum(-1)
        return half_logdet + 0.5 * self.action_dim * (1.0 + math.log(2 * math.pi))

    # ---- weighted maximum likelihood --------------------------------------------------------
    @torch.no_grad()
    def fit_parameters(
        self, inputs: Tensor, targets: Tensor, weights: Tensor, ridge: float = 1e-6
    ) -> dict[str, Tensor]:
        """The new ``weight``, ``bias`` and ``chol`` of :meth:`weighted_fit`, not set.

        Raises:
            ValueError: naming the argument (and member) for a wrong shape, a non-finite input,
                negative or all-zero weights, or a fit that overflows.
        """
        x = self._features(inputs).to(torch.float64)
        lead, members = tuple(x.shape[:-1]), self.population is not None
        y = as_checked("targets", targets, (*lead, self.action_dim), advice=FIX_SAMPLES)
        w = as_weights("weights", weights, lead, members)
        r = check_nonnegative_float("ridge", ridge)
        return self.fit_checked(x, y, power_of_two_scaled(w, members), r)

    def fit_checked(self, x: Tensor, y: Tensor, w: Tensor, r: float = 1e-6) -> dict[str, Tensor]:
        """:meth:`fit_parameters` on checked float64 x ([S,] N, F), y ([S,] N, D) and w ([S,] N)
        (a positive entry per member, at most 2^200: :func:`power_of_two_scaled`)."""
        try:
            if self.mean_prior > 0:
                W, b = map_linear_regression(x, y, w, self.weight, self.bias, self.mean_prior, r)
            else:
                W, b = weighted_least_squares(x, y, w, ridge=r)
        except RuntimeError:
            raise self._overflow(x, y, None) from None
        resid = (
            y - b.unsqueeze(-2)
            if x.shape[-1] == 0
            else y - (matmul_each(x, W.mT) + b.unsqueeze(-2))
        )
        total = reduce_each(w, "sum", -1)
        cov = matmul_each((w[..., None] * resid).mT, resid) / total[..., None, None]
        if self.covariance_prior > 0:
            n_eff = (total**2 / reduce_each(w**2, "sum", -1))[..., None, None]
            k = self.covariance_prior
            cov = (n_eff * cov + k * self.covariance.to(torch.float64)) / (n_eff + k)
        # a non-finite W or b makes every residual of its row, and so cov, non-finite
        chol = self._unfloored_cholesky(cov)
        if chol is None:  # not finite, or the floor binds: the checks and the floor one by one
            bad = ~(_finite_members(cov) & _finite_members(W))
            if bool(bad.any()):
                raise self._overflow(x, y, bad)
            chol = self._floored_cholesky(cov)
        new = {"weight": W, "bias": b, "chol": chol}
        if self.chol.dtype != torch.float64:  # finite in float64 (checked above); narrower?
            for name, value in new.items():
                new[name] = value = value.to(self.chol.dtype)
                if not all_finite(value):
                    raise ValueError(f"the refitted {name} does not fit in {value.dtype}")
        return new

    def _overflow(self, x: Tensor, y: Tensor, bad: Tensor | None) -> ValueError:
        """The error of an overflowing fit."""
        who = ""
        if bad is not None and self.population is not None:
            s = int(bad.nonzero()[0, 0])
            who, x, y = f"member {s}: ", x[s], y[s]
        return ValueError(
            f"{who}the weighted fit overflows (largest |target| {float(y.abs().max()):.3g}, "
            f"largest |input| {float(x.abs().max()) if x.numel() else 0.0:.3g}): rescale the "
            "parameters / features"
        )

    @torch.no_grad()
    def weighted_fit(
        self, inputs: Tensor, targets: Tensor, weights: Tensor, ridge: float = 1e-6
    ) -> None:
        """Weighted maximum-likelihood refit; a failed fit changes nothing.

        Mean: :func:`weighted_least_squares` (:func:`map_linear_regression` if ``mean_prior``);
        covariance: ``sum_i w_i r_i r_i^T / sum_i w_i`` of the residuals, then the prior and
        floor of the class docstring.

        Args:
            inputs: ([S,] N, F) features.
            targets: ([S,] N, D) parameters / actions.
            weights: ([S,] N) non-negative, finite, not all zero (for each member).
            ridge: slope penalty relative to the weight sum (0 for plain WLS).
        """
        self.set_parameters(self.fit_parameters(inputs, targets, weights, ridge))

    def _unfloored_cholesky(self, cov: Tensor) -> Tensor | None:
        """Cholesky factor of cov ([S,] D, D) if finite and cov - diag(m) is positive definite
        (the floor does not bind); None otherwise."""
        floor = torch.diag_embed(self.min_variance.to(cov))  # the factor reads one triangle
        factor = torch.linalg.cholesky_ex(torch.stack([cov, cov - floor]))
        chol: Tensor = factor.L[0]
        return chol if not bool(factor.info.any()) and all_finite(chol) else None

    def _floored_cholesky(self, cov: Tensor) -> Tensor:
        """Cholesky factor (parameter dtype) of float64 cov ([S,] D, D) symmetrised and floored."""
        cov = 0.5 * (cov + cov.mT)
        root = self.min_variance.to(cov.device).sqrt()
        scale = torch.outer(root, root)  # sqrt(m_i m_j) of the floor m
        scaled = cov / scale
        if not all_finite(scaled):
            raise ValueError(
                f"the covariance overflows (largest entry {float(cov.abs().max()):.3g}): "
                "rescale the parameters"
            )
        evals, evecs = torch.linalg.eigh(scaled)
        low = (evals < 1.0).any(-1)
        floored = (evecs * evals.clamp_min(1.0).unsqueeze(-2)) @ evecs.mT * scale
        floored = 0.5 * (floored + floored.mT)
        cov = torch.where(low[..., None, None], floored, cov)
        factor = torch.linalg.cholesky_ex(cov)
        chol: Tensor = factor.L
        if bool((factor.info != 0).any()):
            who = "" if cov.dim() == 2 else f" (member {int((factor.info != 0).nonzero()[0, 0])})"
            raise ValueError(f"the floored covariance is not positive definite{who}")
        return chol.to(self.chol.dtype)

    @torch.no_grad()
    def set_covariance(self, cov: Tensor) -> None:
        """Set the covariance ([S,] D, D), symmetrised and floored at ``min_variance``."""
        c = as_checked("cov", cov, (*self.batch_shape, self.action_dim, self.action_dim))
        self.set_parameters({"chol": self._floored_cholesky(c)})

    OPTIONAL_STATE = ("min_variance",)

    def check_state(self, state: Mapping[str, Tensor]) -> None:
        """A loaded ``chol`` lower triangular, positive diagonal; ``min_variance`` in range."""
        floor = state.get("min_variance")
        if floor is not None:
            check_floor(floor.to(torch.float64), self.action_dim, floor.tolist())
        chol = state.get("chol")
        if chol is None:
            return
        c = chol.to(torch.float64)
        diagonal = torch.diagonal(c, dim1=-2, dim2=-1)
        if bool((c.triu(1) != 0).any()) or bool((diagonal <= 0).any()):
            raise ValueError(
                "chol must be lower triangular with a positive diagonal, got "
                f"diagonal {diagonal.tolist()}"
            )


def _finite_members(t: Tensor) -> Tensor:
    """t ([S,] a, b) -> ([S]) all finite."""
    return torch.isfinite(t).flatten(-2).all(-1)
