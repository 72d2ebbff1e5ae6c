r"""Batched discrete DMPs that end at a goal position AND a goal velocity.

The hitting DMP of Kober et al. (2010) with the quintic moving target g_m of Mülling et al.
(2013), per joint, in normalised time s = t / tau (``'`` = d/ds, tau the duration):

    canonical system      x = exp(-alpha_x s)
    transformation        z' = alpha_z (beta_z (g_m - y) + g_m' - z) + g_m'' + f(x),   y' = z
    forcing term          f(x) = sum_i w_i psi_i(x) / sum_i psi_i(x),
                          psi_i(x) = exp(-(x - c_i)^2 / (2 sigma_i^2))
    moving target         g_m(s) = y_0 + tau ydot_0 s + (10 D - 4 V) s^3 + (-15 D + 7 V) s^4
                                   + (6 D - 3 V) s^5,
                          D = g - y_0 - tau ydot_0,   V = tau (gdot - ydot_0).

So y = g_m + e with ``e'' + alpha_z e' + alpha_z beta_z e = f``, e(0) = e'(0) = 0 (linear in
the weights, the same for every goal); the weight fit imposes e(1) = e'(1) = 0, hence
y(tau) = g and ydot(tau) = gdot for any goal, start and duration (up to the integrator).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from hireps_torch._dmp_math import finite_differences, quintic_coefficients, response_from_rest
from hireps_torch.checks import (
    as_finite_f64,
    check_count,
    check_nonnegative_float,
    check_positive_float,
)

__all__ = ["DMP", "DMPTrajectory"]

_DEFAULT_OUTPUT_DT = 0.01  # s, output sample interval when neither n_steps nor dt is given
_MIN_RK4_STEPS = 500  # default: at least this many RK4 steps per movement
_CONSTRAINT_RK4_STEPS = 2000  # RK4 steps for the basis responses E_i(1), E_i'(1)


class DMPTrajectory(NamedTuple):
    """A batch of DMP rollouts.

    Attributes:
        positions: (B, T, J) joint positions.
        velocities: (B, T, J) joint velocities.
        accelerations: (B, T, J) joint accelerations.
        times: (T,) sample times in seconds, from 0 to the duration.
    """

    positions: Tensor
    velocities: Tensor
    accelerations: Tensor
    times: Tensor


class DMP(nn.Module):
    """Discrete DMP for J joints with goal position and goal velocity (module docstring).

    Buffers (float64): ``tau ()``, ``weights (J, n_basis)``, ``start``, ``start_velocity``,
    ``goal``, ``goal_velocity`` (J,) from the demonstration, ``centers``, ``sigmas``
    (n_basis,) in phase.

    Args:
        n_joints: J, number of joints.
        n_basis: number of Gaussian basis functions, >= 2.
        duration: tau, movement duration in seconds.
        alpha_z: spring-damper gain of the transformation system, > 0.
        beta_z: stiffness ratio; ``alpha_z / 4`` (critical damping) by default.
        alpha_x: decay of the canonical system, > 0 (x(tau) = exp(-alpha_x)).
        width: Gaussian std in units of the spacing of neighbouring centres, > 0.
    """

    tau: Tensor
    weights: Tensor
    start: Tensor
    start_velocity: Tensor
    goal: Tensor
    goal_velocity: Tensor
    centers: Tensor
    sigmas: Tensor

    def __init__(
        self,
        n_joints: int,
        n_basis: int = 20,
        duration: float = 1.0,
        alpha_z: float = 25.0,
        beta_z: float | None = None,
        alpha_x: float = 25.0 / 3.0,
        width: float = 0.7,
    ) -> None:
        super().__init__()
        self.n_joints = n_joints = check_count("n_joints", n_joints, 1)
        self.n_basis = n_basis = check_count("n_basis", n_basis, 2)
        self.alpha_z = check_positive_float("alpha_z", alpha_z)
        self.beta_z = check_positive_float("beta_z", alpha_z / 4.0 if beta_z is None else beta_z)
        self.alpha_x = check_positive_float("alpha_x", alpha_x)
        self.width = check_positive_float("width", width)
        f64 = torch.float64
        centers = torch.exp(-self.alpha_x * torch.linspace(0.0, 1.0, n_basis, dtype=f64))
        spacing = centers[:-1] - centers[1:]
        spacing = torch.cat([spacing, spacing[-1:]])
        self.register_buffer(
            "tau", torch.tensor(check_positive_float("duration", duration), dtype=f64)
        )
        self.register_buffer("centers", centers)
        self.register_buffer("sigmas", self.width * spacing)
        self.register_buffer("weights", torch.zeros(n_joints, n_basis, dtype=f64))
        for name in ("start", "start_velocity", "goal", "goal_velocity"):
            self.register_buffer(name, torch.zeros(n_joints, dtype=f64))

    @property
    def duration(self) -> float:
        """Movement duration tau in seconds."""
        return float(self.tau)

    # ---- basis --------------------------------------------------------------------------------
    def basis(self, s: Tensor) -> Tensor:
        """Normalised basis at ``s = t / tau``: (T,) -> (T, n_basis), rows summing to one."""
        x = torch.exp(-self.alpha_x * s.to(torch.float64))
        psi = torch.exp(-0.5 * ((x[:, None] - self.centers) / self.sigmas) ** 2)
        return psi / psi.sum(-1, keepdim=True)

    def _drive_matrix(self) -> Tensor:
        """(6, 6): coefficients of g_m -> those of alpha_z beta_z g_m + alpha_z g_m' + g_m''."""
        deriv = torch.diag(torch.arange(1, 6, dtype=torch.float64), diagonal=-1)  # m @ deriv = m'
        eye = torch.eye(6, dtype=torch.float64)
        return self.alpha_z * self.beta_z * eye + self.alpha_z * deriv + deriv @ deriv

    def _end_constraint(self) -> Tensor:
        """(2, n_basis): e(1), e'(1) of each normalised basis function as the forcing."""
        n = _CONSTRAINT_RK4_STEPS
        s_half = torch.arange(2 * n + 1, dtype=torch.float64) / (2 * n)
        k, d = self.alpha_z * self.beta_z, self.alpha_z
        y, z, _ = response_from_rest(self.basis(s_half), 1, n, k, d)
        return torch.stack([y[-1], z[-1]])

    # ---- imitation ----------------------------------------------------------------------------
    @torch.no_grad()
    def imitate(self, positions: Tensor, dt: float, ridge: float = 1e-8) -> DMP:
        """Fit the weights to one demonstration (ridge least squares of the target forcing,
        under e(1) = e'(1) = 0) and set duration, start and goals from its ends.

        Args:
            positions: (T, J) demo joint positions at times k dt, T >= 4.
            dt: sample interval in seconds.
            ridge: penalty on the weights, relative to the basis Gram matrix's mean diagonal.

        Returns:
            self, with ``duration = (T - 1) dt``.
        """
        dt = check_positive_float("dt", dt)
        ridge = check_nonnegative_float("ridge", ridge)
        pos = as_finite_f64("positions", positions)
        if pos.dim() != 2 or pos.shape[1] != self.n_joints or pos.shape[0] < 4:
            raise ValueError(
                f"positions must have shape (T, {self.n_joints}) with T >= 4, "
                f"got {tuple(pos.shape)}"
            )
        T = pos.shape[0]
        tau = (T - 1) * dt
        vel, acc = finite_differences(pos, dt)
        z, zdot = tau * vel, tau**2 * acc  # derivatives in normalised time s
        s = torch.arange(T, dtype=torch.float64, device=pos.device) / (T - 1)
        m = quintic_coefficients(pos[0], z[0], pos[-1], z[-1])  # (J, 6)
        powers = s[:, None] ** torch.arange(6, dtype=torch.float64, device=pos.device)  # (T, 6)
        drive = powers @ (m @ self._drive_matrix()).T  # (T, J)
        k, d = self.alpha_z * self.beta_z, self.alpha_z
        f_target = zdot - drive + k * pos + d * z  # (T, J)

        phi = self.basis(s)  # (T, n)
        gram = phi.T @ phi
        eye = torch.eye(self.n_basis, dtype=torch.float64)
        gram = gram + ridge * float(gram.diagonal().mean()) * eye
        C = self._end_constraint()
        C = C / C.norm(dim=1, keepdim=True)  # row scaling only improves the KKT conditioning
        corner = torch.zeros(2, 2, dtype=torch.float64)
        kkt = torch.cat([torch.cat([gram, C.T], 1), torch.cat([C, corner], 1)])
        rhs = torch.cat([phi.T @ f_target, torch.zeros(2, self.n_joints, dtype=torch.float64)])
        sol = torch.linalg.solve(kkt, rhs)

        self.tau.fill_(tau)
        self.weights.copy_(sol[: self.n_basis].T)
        self.start.copy_(pos[0])
        self.start_velocity.copy_(vel[0])
        self.goal.copy_(pos[-1])
        self.goal_velocity.copy_(vel[-1])
        return self

    @classmethod
    def from_demonstration(
        cls, positions: Tensor, dt: float, n_basis: int = 20, ridge: float = 1e-8, **kwargs: float
    ) -> DMP:
        """A DMP imitating ``positions (T, J)`` (:meth:`imitate`); ``kwargs`` to the constructor."""
        pos = torch.as_tensor(positions)
        if pos.dim() != 2:
            raise ValueError(f"positions must have shape (T, J), got {tuple(pos.shape)}")
        return cls(pos.shape[1], n_basis=n_basis, **kwargs).imitate(pos, dt, ridge=ridge)

    # ---- rollout ------------------------------------------------------------------------------
    def _state(self, name: str, value: Tensor | None, default: Tensor, B: int) -> Tensor:
        """(J,) or (B, J) -> (B, J), defaulting to ``default (J,)``."""
        J = self.n_joints
        if value is None:
            return default.expand(B, J).clone()
        v = as_finite_f64(name, value)
        if v.shape == (J,):
            v = v.expand(B, J)
        if tuple(v.shape) != (B, J):
            raise ValueError(f"{name} must have shape ({J},) or ({B}, {J}), got {tuple(v.shape)}")
        return v.clone()

    def _grid(
        self, tau: float, n_steps: int | None, dt: float | None, substeps: int | None
    ) -> tuple[int, int]:
        if n_steps is not None and dt is not None:
            raise ValueError(f"give n_steps or dt, not both (got n_steps={n_steps}, dt={dt})")
        if dt is not None:
            dt = check_positive_float("dt", dt)
            n_steps = round(tau / dt)
            if n_steps < 1 or abs(n_steps * dt - tau) > 1e-9 * tau:
                raise ValueError(f"dt={dt} must divide the duration {tau} into whole steps")
        elif n_steps is None:
            n_steps = max(1, round(tau / _DEFAULT_OUTPUT_DT))
        if int(n_steps) != n_steps or n_steps < 1:
            raise ValueError(f"n_steps must be an integer >= 1, got {n_steps}")
        if substeps is None:
            substeps = max(1, math.ceil(_MIN_RK4_STEPS / n_steps))
        if int(substeps) != substeps or substeps < 1:
            raise ValueError(f"substeps must be an integer >= 1, got {substeps}")
        return int(n_steps), int(substeps)

    @torch.no_grad()
    def rollout(
        self,
        goal_positions: Tensor,
        goal_velocities: Tensor,
        start: Tensor | None = None,
        start_velocities: Tensor | None = None,
        *,
        duration: float | None = None,
        n_steps: int | None = None,
        dt: float | None = None,
        substeps: int | None = None,
    ) -> DMPTrajectory:
        """Integrate B goal vectors at once with the learned shape.

        Args:
            goal_positions: (B, J) g, reached at t = duration.
            goal_velocities: (B, J) gdot, the velocity at t = duration.
            start: (J,) or (B, J) start positions; ``self.start`` by default.
            start_velocities: (J,) or (B, J); ``self.start_velocity`` by default.
            duration: tau in seconds (the shape is kept); ``self.duration`` by default.
            n_steps: output intervals (T = n_steps + 1 samples); default round(tau / 0.01).
            dt: output interval in seconds instead of n_steps; must divide tau.
            substeps: RK4 steps per output interval; default ceil(500 / n_steps).

        Returns:
            :class:`DMPTrajectory` (float64).
        """
        J = self.n_joints
        g = as_finite_f64("goal_positions", goal_positions)
        if g.dim() != 2 or g.shape[1] != J:
            raise ValueError(f"goal_positions must have shape (B, {J}), got {tuple(g.shape)}")
        B = g.shape[0]
        gd = as_finite_f64("goal_velocities", goal_velocities, (B, J))
        y0 = self._state("start", start, self.start, B)
        yd0 = self._state("start_velocities", start_velocities, self.start_velocity, B)
        tau = self.duration if duration is None else check_positive_float("duration", duration)
        n_steps, substeps = self._grid(tau, n_steps, dt, substeps)

        # y = g_m + e: the polynomial exactly, e by RK4 (cached)
        m = quintic_coefficients(y0, tau * yd0, g, tau * gd)  # (B, J, 6)
        s = torch.arange(n_steps + 1, dtype=torch.float64) / n_steps
        powers = s[:, None] ** torch.arange(6, dtype=torch.float64)  # (T, 6)
        deriv = torch.diag(torch.arange(1, 6, dtype=torch.float64), diagonal=-1)
        e, ez, ezdot = self._shape_response(n_steps, substeps)  # (T, J) each
        y = torch.einsum("tk,bjk->btj", powers, m) + e
        z = torch.einsum("tk,bjk->btj", powers, m @ deriv) + ez
        zdot = torch.einsum("tk,bjk->btj", powers, m @ deriv @ deriv) + ezdot
        times = s * tau
        return DMPTrajectory(y, z / tau, zdot / tau**2, times)

    def _shape_response(self, n_steps: int, substeps: int) -> tuple[Tensor, Tensor, Tensor]:
        """e, e', e'' (each (n_steps + 1, J)) from rest, cached per grid, gains and weights."""
        key = (n_steps, substeps, float(self.alpha_z), float(self.beta_z), float(self.alpha_x))
        shape = (self.weights, self.centers, self.sigmas)
        # e, e', e'' and the (weights, centers, sigmas) they were computed with
        cache: dict[tuple[float, ...], tuple[Tensor, Tensor, Tensor, tuple[Tensor, ...]]]
        cache = self.__dict__.setdefault("_response_cache", {})
        stale = key not in cache or not all(
            torch.equal(a, b) for a, b in zip(cache[key][3], shape, strict=True)
        )
        if stale:
            cache.clear()
            n_half = 2 * n_steps * substeps + 1
            s_half = torch.arange(n_half, dtype=torch.float64) / (n_half - 1)
            forcing = self.basis(s_half) @ self.weights.T  # (n_half, J)
            k, d = self.alpha_z * self.beta_z, self.alpha_z
            e, ez, ezdot = response_from_rest(forcing, n_steps, substeps, k, d)
            cache[key] = (e, ez, ezdot, tuple(b.detach().clone() for b in shape))
        return cache[key][:3]
