"""Goal-velocity DMPs: end state, imitation, batching, goal changes, bad inputs."""

import math

import pytest
import torch

from hireps_torch.dmp import DMP

J = 7
DT = 0.002  # demo sample interval (500 Hz)


def quintic_blend(s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Position shape of a unit goal-position change and of a unit (tau * goal-velocity) change
    of the moving target, in normalised time s (module docstring)."""
    return 10 * s**3 - 15 * s**4 + 6 * s**5, -4 * s**3 + 7 * s**4 - 3 * s**5


def demo_trajectory(n: int = 501, dt: float = DT) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth 7-joint demo (back-swing, then accelerating), ending at non-zero velocity.

    Returns positions (n, J) and the analytic velocities (n, J).
    """
    t = torch.arange(n, dtype=torch.float64)[:, None] * dt
    a = torch.linspace(0.2, 1.0, J, dtype=torch.float64)
    w = torch.linspace(2.0, 5.0, J, dtype=torch.float64)
    ph = torch.linspace(0.0, 1.5, J, dtype=torch.float64)
    pos = 0.3 * torch.sin(w * t + ph) + a * t**3 - 0.2 * a * t**2
    vel = 0.3 * w * torch.cos(w * t + ph) + 3 * a * t**2 - 0.4 * a * t
    return pos, vel


@pytest.fixture(scope="module")
def demo() -> tuple[torch.Tensor, torch.Tensor]:
    return demo_trajectory()


@pytest.fixture(scope="module")
def dmp(demo) -> DMP:
    return DMP.from_demonstration(demo[0], DT, n_basis=20)


def test_zero_weights_track_the_quintic_moving_target():
    # hand-checked case: without forcing the DMP equals its moving target g_m exactly
    d = DMP(2, duration=0.8)
    start = torch.tensor([0.1, -0.4], dtype=torch.float64)
    goal = torch.tensor([[1.0, 0.2]], dtype=torch.float64)
    goal_vel = torch.tensor([[2.0, -1.5]], dtype=torch.float64)
    tr = d.rollout(goal, goal_vel, start=start, n_steps=40)
    s = tr.times[:, None] / 0.8
    p, v = quintic_blend(s)
    expected = start + (goal - start) * p + 0.8 * goal_vel * v  # start at rest
    # measured 2.5e-10: RK4 error on the degree-5 solution (default 520 steps)
    assert torch.allclose(tr.positions[0], expected, atol=1e-9, rtol=0)
    dp = (30 * s**2 - 60 * s**3 + 30 * s**4) / 0.8
    dv = (-12 * s**2 + 28 * s**3 - 15 * s**4) / 0.8
    expected_vel = (goal - start) * dp + 0.8 * goal_vel * dv
    assert torch.allclose(tr.velocities[0], expected_vel, atol=1e-8, rtol=0)
    assert tr.times[-1].item() == pytest.approx(0.8, abs=1e-15)


def test_reaches_goal_position_and_goal_velocity(dmp, gen):
    B = 64
    goals = dmp.goal + 0.5 * torch.randn(B, J, generator=gen, dtype=torch.float64)
    goal_vel = 2.0 * torch.randn(B, J, generator=gen, dtype=torch.float64)
    starts = dmp.start + 0.3 * torch.randn(B, J, generator=gen, dtype=torch.float64)
    assert float(goal_vel.abs().min()) < 0.1 < float(goal_vel.abs().max())
    for duration in (0.4, 1.0):  # time scaling keeps the exact end state
        tr = dmp.rollout(goals, goal_vel, start=starts, duration=duration, n_steps=100)
        assert tr.positions.shape == (B, 101, J) and tr.positions.dtype == torch.float64
        assert tr.velocities.shape == tr.accelerations.shape == (B, 101, J)
        assert torch.equal(tr.positions[:, 0], starts)
        assert torch.equal(tr.velocities[:, 0], dmp.start_velocity.expand(B, J))
        # measured: 1.1e-9 rad, 2.8e-8 rad/s (RK4, 500 steps); a fit without the end
        # constraint misses by 1.2e-4 rad, 1.1e-3 rad/s
        assert float((tr.positions[:, -1] - goals).abs().max()) < 1e-7
        assert float((tr.velocities[:, -1] - goal_vel).abs().max()) < 1e-6
        assert bool(torch.isfinite(tr.accelerations).all())


def test_imitation_reproduces_the_demonstration(dmp, demo):
    pos, vel = demo
    assert float(vel[-1].abs().min()) > 0.1  # a hitting demo: non-zero end velocity
    assert dmp.duration == pytest.approx(1.0, abs=1e-12)
    assert torch.equal(dmp.start, pos[0]) and torch.equal(dmp.goal, pos[-1])
    # goal velocity from second-order one-sided differences (measured error 4e-5 rad/s)
    assert torch.allclose(dmp.goal_velocity, vel[-1], atol=1e-3, rtol=0)
    tr = dmp.rollout(dmp.goal[None], dmp.goal_velocity[None], n_steps=len(pos) - 1)
    assert torch.allclose(tr.times, torch.arange(len(pos), dtype=torch.float64) * DT)
    # measured: max position error 2.7e-4 rad, velocity error 1.2e-2 rad/s
    assert float((tr.positions[0] - pos).abs().max()) < 1e-3
    assert float((tr.velocities[0] - vel).abs().max()) < 3e-2
    # the shape matters: a DMP without forcing (the bare quintic) is far off the demo
    bare = DMP(J).rollout(
        dmp.goal[None],
        dmp.goal_velocity[None],
        start=dmp.start,
        start_velocities=dmp.start_velocity,
        n_steps=len(pos) - 1,
    )
    assert float((bare.positions[0] - pos).abs().max()) > 30 * 1e-3


def test_batched_rollout_equals_one_by_one(dmp, gen):
    B = 5
    goals = dmp.goal + torch.randn(B, J, generator=gen, dtype=torch.float64)
    goal_vel = torch.randn(B, J, generator=gen, dtype=torch.float64)
    starts = dmp.start + 0.2 * torch.randn(B, J, generator=gen, dtype=torch.float64)
    batch = dmp.rollout(goals, goal_vel, start=starts, n_steps=50)
    for b in range(B):
        one = dmp.rollout(goals[b : b + 1], goal_vel[b : b + 1], start=starts[b], n_steps=50)
        for x, y in zip(batch[:3], one[:3], strict=True):
            assert torch.allclose(x[b], y[0], atol=1e-12, rtol=0)


def test_changing_the_goal_moves_the_end_point_smoothly(dmp, gen):
    # the goal enters only through the quintic: shifting g by delta shifts the trajectory by
    # delta * (10 s^3 - 15 s^4 + 6 s^5), monotone from 0 to delta; changing gdot by dv shifts
    # it by tau * dv * (-4 s^3 + 7 s^4 - 3 s^5), and the end velocity by exactly dv
    delta = 0.4 * torch.randn(1, J, generator=gen, dtype=torch.float64)
    dv = torch.randn(1, J, generator=gen, dtype=torch.float64)
    goals = torch.cat([dmp.goal[None], dmp.goal[None] + delta, dmp.goal[None]])
    goal_vel = torch.cat([dmp.goal_velocity[None]] * 2 + [dmp.goal_velocity[None] + dv])
    tr = dmp.rollout(goals, goal_vel)
    s = tr.times[:, None] / dmp.duration
    p, v = quintic_blend(s)
    shift = tr.positions[1] - tr.positions[0]
    assert torch.allclose(shift, delta * p, atol=1e-8, rtol=0)
    assert torch.allclose(shift[-1], delta[0], atol=1e-8, rtol=0)
    assert bool((shift.diff(dim=0) * delta.sign() >= -1e-10).all())  # monotone, no overshoot
    assert float((shift.abs() - delta.abs()).max()) < 1e-8  # bounded by the goal change
    # acceleration change bounded by |delta| max|p''| / tau^2 = |delta| 10 / sqrt(3)
    dacc = tr.accelerations[1] - tr.accelerations[0]
    assert bool((dacc.abs() <= delta.abs() * 10 / math.sqrt(3) + 1e-6).all())
    vshift = tr.positions[2] - tr.positions[0]
    assert torch.allclose(vshift, dmp.duration * dv * v, atol=1e-8, rtol=0)
    assert torch.allclose(tr.velocities[2, -1] - tr.velocities[0, -1], dv[0], atol=1e-7, rtol=0)


def test_output_grid_options(dmp):
    g, gv = dmp.goal[None], dmp.goal_velocity[None]
    tr = dmp.rollout(g, gv, dt=0.01)
    assert tr.positions.shape == (1, 101, J)
    assert torch.allclose(tr.times, torch.linspace(0.0, 1.0, 101, dtype=torch.float64))
    coarse = dmp.rollout(g, gv, n_steps=10)
    assert torch.allclose(coarse.positions[0], tr.positions[0, ::10], atol=1e-9, rtol=0)


def test_state_dict_round_trip(dmp):
    copy = DMP(J)
    copy.load_state_dict(dmp.state_dict())
    assert copy.duration == dmp.duration
    a = dmp.rollout(dmp.goal[None], dmp.goal_velocity[None], n_steps=20)
    b = copy.rollout(copy.goal[None], copy.goal_velocity[None], n_steps=20)
    assert torch.equal(a.positions, b.positions)


def test_bad_inputs_raise_clear_errors(dmp):
    g = dmp.goal.expand(4, J).clone()
    gv = torch.zeros(4, J, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"goal_positions must have shape \(B, 7\), got \(4, 6\)"):
        dmp.rollout(g[:, :6], gv)
    with pytest.raises(ValueError, match=r"goal_positions must have shape \(B, 7\), got \(7,\)"):
        dmp.rollout(g[0], gv)
    with pytest.raises(ValueError, match=r"goal_velocities must have shape \(4, 7\), got \(3, 7\)"):
        dmp.rollout(g, gv[:3])
    for name, args in [
        ("goal_positions", (g.to(torch.complex128), gv)),
        ("goal_velocities", (g, gv.to(torch.complex128))),
        ("start", (g, gv, g.to(torch.complex128))),
    ]:  # not their real parts in silence
        with pytest.raises(TypeError, match=f"{name} must hold real numbers"):
            dmp.rollout(*args)
    with pytest.raises(TypeError, match="positions must hold real numbers"):
        DMP(J).imitate(g.to(torch.complex128), 0.01)
    bad = gv.clone()
    bad[2, 5] = float("nan")
    with pytest.raises(ValueError, match=r"goal_velocities contains non-finite .*\[2, 5\]: nan"):
        dmp.rollout(g, bad)
    bad = g.clone()
    bad[0, 1] = float("inf")
    with pytest.raises(ValueError, match="goal_positions contains non-finite"):
        dmp.rollout(bad, gv)
    with pytest.raises(ValueError, match=r"start must have shape \(7,\) or \(4, 7\), got \(2, 7\)"):
        dmp.rollout(g, gv, start=g[:2])
    with pytest.raises(ValueError, match="start_velocities contains non-finite"):
        dmp.rollout(g, gv, start_velocities=torch.full((J,), float("nan")))
    with pytest.raises(ValueError, match="n_steps must be an integer >= 1, got 0"):
        dmp.rollout(g, gv, n_steps=0)
    with pytest.raises(ValueError, match="dt=0.003 must divide the duration"):
        dmp.rollout(g, gv, dt=0.003)
    with pytest.raises(ValueError, match="not both"):
        dmp.rollout(g, gv, dt=0.01, n_steps=100)
    with pytest.raises(ValueError, match="duration must be finite and > 0, got -1"):
        dmp.rollout(g, gv, duration=-1.0)

    demo = torch.zeros(50, J, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"positions must have shape \(T, 7\) with T >= 4"):
        DMP(J).imitate(demo[:, :3], DT)
    with pytest.raises(ValueError, match=r"positions must have shape \(T, J\), got \(50,\)"):
        DMP.from_demonstration(demo[:, 0], DT)
    bad = demo.clone()
    bad[10, 3] = float("nan")
    with pytest.raises(ValueError, match=r"positions contains non-finite .*\[10, 3\]"):
        DMP.from_demonstration(bad, DT)
    with pytest.raises(ValueError, match="dt must be finite and > 0, got 0"):
        DMP.from_demonstration(demo, 0.0)
    with pytest.raises(ValueError, match="n_basis must be >= 2, got 1"):
        DMP(J, n_basis=1)


def test_rollout_follows_in_place_changes_of_weights_and_gains():
    t = torch.linspace(0, 1, 50, dtype=torch.float64)[:, None]
    demo = torch.cat([torch.sin(3 * t), t**2], dim=1)
    dmp = DMP.from_demonstration(demo, 1 / 49)
    g, gd = dmp.goal[None], dmp.goal_velocity[None]
    before = dmp.rollout(g, gd).positions
    dmp.weights.data.mul_(0.0)  # .data changes bypass the version counter
    flat = dmp.rollout(g, gd).positions
    assert (flat - before).abs().max() > 1e-3
    # changed gains with the same weights: the cached shape response must be recomputed
    dmp = DMP.from_demonstration(demo, 1 / 49)
    weights = dmp.weights.clone()
    first = dmp.rollout(g, gd).positions
    dmp.alpha_z, dmp.beta_z = 10.0, 2.5
    changed = dmp.rollout(g, gd).positions
    fresh = DMP(2, alpha_z=10.0, beta_z=2.5).imitate(demo, 1 / 49)
    fresh.weights.data.copy_(weights)
    assert (changed - first).abs().max() > 1e-4
    assert torch.allclose(changed, fresh.rollout(g, gd).positions, atol=1e-12)


def test_counts_must_be_integers():
    with pytest.raises(TypeError, match="n_joints must be an integer"):
        DMP(2.5)
    with pytest.raises(TypeError, match="n_basis must be an integer"):
        DMP(2, n_basis=10.0)
    with pytest.raises(ValueError, match="n_basis must be >= 2"):
        DMP(2, n_basis=1)
