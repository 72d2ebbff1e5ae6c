"""Numerics of :mod:`hireps_torch.dmp`: moving target, finite differences, RK4."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["finite_differences", "quintic_coefficients", "response_from_rest"]


def quintic_coefficients(y0: Tensor, z0: Tensor, g: Tensor, gz: Tensor) -> Tensor:
    """Coefficients (..., J, 6) of g_m(s) = sum_k m_k s^k from y0, z0 (start position, velocity
    times tau) and g, gz (goal), each (..., J)."""
    D = g - y0 - z0
    V = gz - z0
    zero = torch.zeros_like(y0)
    return torch.stack([y0, z0, zero, 10 * D - 4 * V, -15 * D + 7 * V, 6 * D - 3 * V], dim=-1)


def response_from_rest(
    forcing: Tensor, n_steps: int, substeps: int, stiffness: float, damping: float
) -> tuple[Tensor, Tensor, Tensor]:
    """e, e', e'' (each (n_steps + 1, W)) of ``e'' + damping e' + stiffness e = F`` from rest by
    RK4 on s in [0, 1], F from ``forcing`` (2 n_steps substeps + 1, W) on the half-step grid."""
    n_total = n_steps * substeps
    h = 1.0 / n_total
    k, d = stiffness, damping

    def acc(y: Tensor, z: Tensor, j: int) -> Tensor:
        return forcing[j].sub(y, alpha=k).sub_(z, alpha=d)

    ys = forcing.new_empty(n_steps + 1, forcing.shape[1], dtype=torch.float64)
    zs = torch.empty_like(ys)
    accs = torch.empty_like(ys)
    y, z = torch.zeros_like(ys[0]), torch.zeros_like(ys[0])
    ys[0], zs[0], accs[0] = y, z, acc(y, z, 0)
    for i in range(n_total):
        j = 2 * i
        a1 = acc(y, z, j)
        z2 = z + 0.5 * h * a1
        a2 = acc(y + 0.5 * h * z, z2, j + 1)
        z3 = z + 0.5 * h * a2
        a3 = acc(y + 0.5 * h * z2, z3, j + 1)
        z4 = z + h * a3
        a4 = acc(y + h * z3, z4, j + 2)
        y = y + (h / 6.0) * (z + 2.0 * z2 + 2.0 * z3 + z4)
        z = z + (h / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        if (i + 1) % substeps == 0:
            o = (i + 1) // substeps
            ys[o], zs[o], accs[o] = y, z, acc(y, z, j + 2)
    return ys, zs, accs


def finite_differences(pos: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """Second-order accurate velocity and acceleration: (T, J) -> ((T, J), (T, J)), T >= 4."""
    vel = torch.empty_like(pos)
    acc = torch.empty_like(pos)
    vel[1:-1] = (pos[2:] - pos[:-2]) / (2 * dt)
    vel[0] = (-3 * pos[0] + 4 * pos[1] - pos[2]) / (2 * dt)
    vel[-1] = (3 * pos[-1] - 4 * pos[-2] + pos[-3]) / (2 * dt)
    acc[1:-1] = (pos[2:] - 2 * pos[1:-1] + pos[:-2]) / dt**2
    acc[0] = (2 * pos[0] - 5 * pos[1] + 4 * pos[2] - pos[3]) / dt**2
    acc[-1] = (2 * pos[-1] - 5 * pos[-2] + 4 * pos[-3] - pos[-4]) / dt**2
    return vel, acc
