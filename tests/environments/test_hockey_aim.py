"""The kinematic aim mapping of the hockey shot: poses and twists from pytorch-kinematics, the
slopes, a shot that hits a target off the demo's line, and the options it initialises."""

import math

import numpy as np
import pytest
import torch

pytest.importorskip("pybullet")
pytest.importorskip("pytorch_kinematics")

from hireps_torch.envs.hockey import ArmGeometry, HockeyParams, HockeySim, demo_action  # noqa: E402
from hireps_torch.envs.hockey.aim import (  # noqa: E402
    aim_angle,
    aim_slopes,
    aimed_shot,
    blade_twist,
    rotation_z,
)
from hireps_torch.envs.hockey.kinematics import arm_kinematics  # noqa: E402


@pytest.fixture(scope="module")
def demo():
    return torch.as_tensor(demo_action(HockeyParams()), dtype=torch.float64)


def test_no_turn_gives_the_demo_shot_back(demo):
    assert torch.equal(aimed_shot(demo, 0.0), demo)
    # a tiny turn moves the shot by a tiny amount (the IK starts at the demo's goal)
    assert float((aimed_shot(demo, 1e-4) - demo).abs().max()) < 1e-2


@pytest.mark.parametrize("phi", [-0.3, -0.12, 0.05, 0.2])
def test_aimed_goal_turns_the_blade_about_the_puck_spot(demo, phi):
    """pytorch-kinematics' forward kinematics of the aimed goal: the blade centre where the
    demo's is (on the turning axis), its orientation the demo's turned by phi; its Jacobian
    maps the aimed goal velocity to the demo's blade twist turned by phi."""
    kin = arm_kinematics(ArmGeometry())
    shot = aimed_shot(demo, phi)
    p0, R0 = kin.blade_pose(demo[:7])
    p, R = kin.blade_pose(shot[:7])
    assert float((p - p0).abs().max()) < 1e-5
    Rz = rotation_z(phi)
    assert float((R - Rz @ R0).abs().max()) < 1e-4
    twist0 = blade_twist(demo[:7], demo[7:])
    twist = blade_twist(shot[:7], shot[7:])
    expected = torch.cat([Rz @ twist0[:3], Rz @ twist0[3:]])
    torch.testing.assert_close(twist, expected, rtol=0, atol=1e-8)
    # the blade face normal (its x axis, -x_world in the demo) is turned by phi in the plane
    face = -R[:, 0]
    assert math.isclose(math.atan2(float(face[1]), float(face[0])), phi, abs_tol=1e-4)


def test_slopes_are_the_derivative_of_the_aimed_shot_in_the_target_position(demo):
    p0 = torch.tensor([1.1, 0.05], dtype=torch.float64)
    W = aim_slopes(demo, p0)
    assert W.shape == (14, 2)
    h = 1e-3
    for j in range(2):
        e = torch.zeros(2, dtype=torch.float64)
        e[j] = h
        fd = (aimed_shot(demo, aim_angle(p0 + e)) - aimed_shot(demo, aim_angle(p0 - e))) / (2 * h)
        torch.testing.assert_close(W[:, j], fd, rtol=2e-2, atol=2e-3)
    # straight out along the demo's line, moving the target along it needs no turn
    on_line = aim_slopes(demo, torch.tensor([1.1, 0.0], dtype=torch.float64))
    assert float(on_line[:, 0].abs().max()) == 0.0
    assert float(on_line[:, 1].abs().max()) > 1.0  # rad per m (rad/s per m for velocities)


@pytest.mark.parametrize("y", [-0.15, 0.15])
def test_the_aimed_shot_hits_a_target_the_demo_shot_misses(demo, y):
    """In the simulation: with the target 15 cm off the demo's line the demo shot leaves it
    where it was; the shot aimed by the mapping (and its linearisation at the start mean, the
    options' initial mean) sends it beyond 1.4 m (a scoring zone's inner edge)."""
    sim = HockeySim(HockeyParams())
    try:
        target = np.array([1.1, y])
        W = aim_slopes(demo, torch.tensor([1.1, 0.0], dtype=torch.float64))
        linear = demo + W @ torch.tensor([0.0, y], dtype=torch.float64)
        ends = {}
        for name, shot in (
            ("demo", demo),
            ("aimed", aimed_shot(demo, aim_angle(torch.tensor(target)))),
            ("linear", linear),
        ):
            sim.new_world()
            sim.reset(target)
            sim.shot(shot[:7], shot[7:])
            ends[name] = sim.puck_positions()[1]
    finally:
        sim.close()
    assert np.allclose(ends["demo"], target, atol=1e-3)
    for name in ("aimed", "linear"):
        assert np.linalg.norm(ends[name]) > 1.4, (name, ends[name])
        assert np.sign(ends[name][1]) == np.sign(y)  # pushed outward on the target's side


def test_bad_aim_inputs_are_named(demo):
    with pytest.raises(ValueError, match=r"demo must have shape \(14,\), got \(7,\)"):
        aimed_shot(demo[:7], 0.1)
    with pytest.raises(ValueError, match="phi must be finite, got nan"):
        aimed_shot(demo, float("nan"))
    with pytest.raises(ValueError, match=r"target \(0.5, 0.1\) is not beyond"):
        aim_angle(torch.tensor([0.5, 0.1]))
    with pytest.raises(ValueError, match=r"target must have shape \(2,\)"):
        aim_slopes(demo, torch.tensor([1.1, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"step must be in \(0, 0.5\] rad, got 0"):
        aim_slopes(demo, torch.tensor([1.1, 0.0]), step=0)
    with pytest.raises(ValueError, match=r"step must be in \(0, 0.5\] rad, got 5.0"):
        aim_slopes(demo, torch.tensor([1.1, 0.0]), step=5.0)
    with pytest.raises(TypeError, match="phi must be a number .*got the bool True"):
        aimed_shot(demo, True)
    with pytest.raises(ValueError, match=r"q must have shape \(7,\), got \(6,\)"):
        blade_twist(demo[:6], demo[7:])
    with pytest.raises(ValueError, match=r"qdot must have shape \(7,\)"):
        blade_twist(demo[:7], demo[7:13])
    with pytest.raises(RuntimeError, match="cannot be turned by phi = 3.0 rad"):
        aimed_shot(demo, 3.0)
    with pytest.raises(TypeError, match="geometry must be an ArmGeometry, got str"):
        aim_angle(torch.tensor([1.1, 0.0]), "x")
    with pytest.raises(ValueError, match="phi must be finite, got nan"):
        rotation_z(float("nan"))
    for target in (torch.tensor([1.1 + 0.5j, 0.0]), [1.1 + 0.5j, 0.0]):  # not its real part
        with pytest.raises(TypeError, match="target must hold real numbers, got dtype .*complex"):
            aim_angle(target)
    with pytest.raises(TypeError, match=r"q must hold real numbers"):
        blade_twist(demo[:7].to(torch.complex128), demo[7:])


@pytest.mark.parametrize("variant", ["sequential", "episodic"])
def test_aim_slopes_option_start_keeps_the_means_at_the_start_mean(demo, variant):
    """aim_slopes (the default) with options on (x, y): every option's slopes are the
    mapping's (stacked per shot), and at the start mean every option's mean is what it is
    without them (--no-aim-slopes)."""
    from hireps_torch.experiments import hockey

    Config = (
        hockey.HockeySequentialConfig if variant == "sequential" else hockey.HockeyEpisodicConfig
    )
    params = HockeyParams()
    p0 = torch.tensor([params.target_mean], dtype=torch.float64)
    W = aim_slopes(demo, p0[0])
    plain = hockey._make_algorithm(
        Config(seed=3, aim_slopes=False, option_features="position"), 3, demo, params
    )
    aimed = hockey._make_algorithm(Config(seed=3, option_features="position"), 3, demo, params)
    for a, b in zip(plain.policies, aimed.policies, strict=True):
        a, b = a.member(0), b.member(0)  # one member: --seed 3
        for o_plain, o_aim in zip(a.sub_policies, b.sub_policies, strict=True):
            torch.testing.assert_close(o_aim.weight, W.repeat(a.action_dim // 14, 1))
            torch.testing.assert_close(o_aim.mean(p0), o_plain.mean(p0), rtol=0, atol=1e-12)
            assert float(o_plain.weight.abs().max()) == 0.0


def test_aim_features_are_the_angle_and_distance_from_the_puck_spot():
    from hireps_torch.envs.hockey.aim import AimFeatures

    f = AimFeatures(ArmGeometry())
    p = torch.tensor([[1.1, 0.0], [1.2, 0.65], [0.55, -0.3]], dtype=torch.float64)
    expected = torch.tensor(
        [[0.0, 0.55], [math.atan2(0.65, 0.65), math.hypot(0.65, 0.65)], [-math.pi / 2, 0.3]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(f(p), expected)
    with pytest.raises(ValueError, match=r"takes states of shape \(\.\.\., 2\)"):
        f(torch.zeros(3, 3))


def test_options_on_aim_features_turn_by_the_angle_at_any_distance(demo):
    """option_features = "aim" (the default): each option's mean is the demo shot plus the
    turn's derivative times the target's aim angle, the same first-order aim near the start
    mean and twice as far out (where slopes on (x, y) fitted at the start mean over-turn)."""
    from hireps_torch.envs.hockey.aim import turn_derivative
    from hireps_torch.experiments import hockey

    params = HockeyParams()
    algo = hockey._make_algorithm(hockey.HockeySequentialConfig(seed=2), 3, demo, params)
    plain = hockey._make_algorithm(
        hockey.HockeySequentialConfig(seed=2, aim_slopes=False), 3, demo, params
    )
    d = turn_derivative(demo)
    for x in (1.1, 1.65):
        p = torch.tensor([[x, 0.1]], dtype=torch.float64)
        phi = aim_angle(p[0])
        for a, b in zip(algo.policies, plain.policies, strict=True):
            a, b = a.member(0), b.member(0)  # one member: --seed 2
            for o_aim, o_plain in zip(a.sub_policies, b.sub_policies, strict=True):
                expected = o_plain.mean(p)[0] + d * phi  # plain: the same bias, no slopes
                aimed = o_aim.mean(a.policy_features(p))[0]
                torch.testing.assert_close(aimed, expected, rtol=0, atol=1e-12)
