"""Robot hockey: kinematics against pybullet, the demo, a scripted shot, the rules, bad input."""

import builtins

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

pytest.importorskip("pybullet")
pytest.importorskip("pytorch_kinematics")

from hireps_torch.envs.hockey import (  # noqa: E402
    ENV_ID,
    EPISODIC_ENV_ID,
    ArmKinematics,
    HockeyParams,
    RobotHockeyEnv,
    RobotHockeyEpisodicEnv,
    demonstration,
    zone_reward,
)
from hireps_torch.envs.hockey import kinematics as kin_module  # noqa: E402


@pytest.fixture(scope="module")
def env():
    e = RobotHockeyEnv(render_mode="rgb_array")
    yield e
    e.close()


def test_forward_kinematics_matches_pybullet_link_poses(env):
    pb, sim = env.sim.pb, env.sim
    kin = sim.kinematics
    rng = np.random.default_rng(0)
    lo, hi = kin.lower.numpy(), kin.upper.numpy()
    qs = rng.uniform(lo, hi, size=(25, 7))
    pos, rot = kin.blade_pose(torch.tensor(qs))
    for q, p_pk, r_pk in zip(qs, pos, rot, strict=True):
        for j in range(7):
            pb.resetJointState(sim.arm, j, float(q[j]), physicsClientId=sim.client)
        state = pb.getLinkState(
            sim.arm, 8, computeForwardKinematics=True, physicsClientId=sim.client
        )
        r_pb = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        assert np.abs(np.array(state[4]) - p_pk.numpy()).max() < 1e-5
        assert np.abs(r_pb - r_pk.numpy()).max() < 1e-5
    sim.reset_arm()


def test_demonstration_is_a_smooth_swing_that_meets_the_puck():
    p = HockeyParams()
    q, dt = demonstration(p.geometry)
    assert q.shape == (p.geometry.demo_points, 7)
    assert dt == pytest.approx(p.geometry.swing_duration / (p.geometry.demo_points - 1))
    assert (q[1:] - q[:-1]).abs().max() < 0.1  # one IK branch all along, no jumps
    pos, rot = ArmKinematics(p.geometry).blade_pose(q[-1])
    expected = torch.tensor([p.geometry.puck_x, 0.0, p.geometry.blade_height], dtype=torch.float64)
    assert (pos - expected).abs().max() < 1e-5
    square = torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose(rot[:, 0], square, atol=1e-6)  # blade face square to the shot


def test_dmp_reproduces_the_demonstration(env):
    q, dt = demonstration(env.params.geometry)
    dmp = env.sim.dmp
    traj = dmp.rollout(dmp.goal[None], dmp.goal_velocity[None], n_steps=q.shape[0] - 1)
    assert (traj.positions[0] - q).abs().max() < 5e-3  # rad, imitation tolerance
    assert (traj.positions[0, -1] - q[-1]).abs().max() < 1e-7  # goal reached exactly


def test_a_scripted_shot_moves_the_control_puck_into_the_target(env):
    env.reset(seed=0)
    env.sim.reset(np.array([1.1, 0.0]))  # target straight ahead
    env._target = np.array([1.1, 0.0])
    obs, reward, terminated, truncated, info = env.step(env.demo_action())
    assert info["min_gap"] == 0.0 and reward == 0.0  # contact
    assert obs[0] > 1.5  # the target puck was driven away from the robot
    assert info["control_end"][0] > 0.9  # the control puck left its spot
    assert not info["rejected"] and not info["clipped"]
    assert not terminated and not truncated


def test_zone_rewards_at_the_edges():
    zones = HockeyParams().zones
    d = torch.tensor(
        [0.0, 1.3999, 1.4, 1.7999, 1.8, 2.1999, 2.2, 2.6, 2.6001, 5.0], dtype=torch.float64
    )
    expected = torch.tensor([0, 0, 1, 1, 2, 2, 3, 3, 0, 0], dtype=torch.float64)
    assert torch.equal(zone_reward(d, zones), expected)


def test_a_shot_ending_on_a_zone_edge_scores_that_zone(env, monkeypatch):
    """The env's zone of a target puck exactly 1.4 m from the base is 1, as zone_reward's
    (before: the distance went through float32, 1.39999998, and scored 0)."""
    from hireps_torch.envs.hockey.sim import ShotResult

    env.reset(seed=0)
    edge = ShotResult(0.5, np.array([1.4, 0.0]), np.zeros(2), 1, False)
    monkeypatch.setattr(env.sim, "shot", lambda *a, **k: edge)
    for _ in range(env.params.n_shots):
        _, reward, _, _, info = env.step(env.demo_action())
    assert info["zone"] == 1 and reward == pytest.approx(1.0 - 0.5)


def test_episode_is_three_shots_with_the_zone_reward_at_the_end(env):
    start, _ = env.reset(seed=3)
    soft = env.demo_action()
    soft[7:] *= 0.05  # too slow to reach the target puck
    rewards, terms = [], []
    for _ in range(3):
        obs, r, term, _, info = env.step(soft)
        rewards.append(r)
        terms.append(term)
        assert info["min_gap"] > 0.1
        assert np.abs(obs - start).max() < 1e-3  # untouched target puck stays
    assert terms == [False, False, True]
    zone = float(
        zone_reward(torch.tensor(np.linalg.norm(obs), dtype=torch.float64), env.params.zones)
    )
    assert rewards[-1] == pytest.approx(-info["min_gap"] + zone)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(soft)


def test_same_seed_same_episode_in_fresh_envs():
    runs = []
    for _ in range(2):
        e = RobotHockeyEnv()
        obs, _ = e.reset(seed=7)
        out = [obs]
        a = e.demo_action()
        for _ in range(3):
            a[7:] *= 0.9
            o, r, *_ = e.step(a)
            out += [o, np.array([r])]
        e.close()
        runs.append(np.concatenate(out))
    assert np.array_equal(runs[0], runs[1])
    e = RobotHockeyEnv()
    other, _ = e.reset(seed=8)
    e.close()
    assert not np.array_equal(other, runs[0][:2])


def test_episodic_env_matches_three_sequential_shots(env):
    actions = [env.demo_action() * np.r_[np.ones(7), np.full(7, s)] for s in (0.7, 0.8, 0.9)]
    start, _ = env.reset(seed=11)
    total = sum(env.step(a)[1] for a in actions)
    episodic = gym.make(EPISODIC_ENV_ID).unwrapped
    start2, _ = episodic.reset(seed=11)
    _, total2, terminated, _, info = episodic.step(np.concatenate(actions))
    episodic.close()
    assert np.array_equal(start, start2)
    assert terminated and len(info["shots"]) == 3
    assert total2 == pytest.approx(total, abs=1e-9)


def test_bad_actions_are_named_clipped_or_rejected(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(14,\)"):
        env.step(np.zeros(13))
    bad = env.demo_action()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="index 3: nan"):
        env.step(bad)
    far = env.demo_action()
    far[0] = 10.0  # beyond joint 1's limit
    _, _, _, _, info = env.step(far)
    assert info["clipped"]
    low = env.demo_action()
    low[1] += 0.6  # shoulder far forward: the blade would dig into the floor
    before = env.sim.puck_positions()
    _, r, _, _, info = env.step(low)
    assert info["rejected"] and info["sim_steps"] == 0
    assert np.allclose(env.sim.puck_positions()[1], before[1])
    assert r == pytest.approx(-info["min_gap"])


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_registered_envs_pass_the_gymnasium_checker_and_render():
    for env_id in (ENV_ID, EPISODIC_ENV_ID):
        e = gym.make(env_id, render_mode="rgb_array").unwrapped
        check_env(e, skip_render_check=False)
        e.reset(seed=0)
        frame = e.render()
        assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
        assert frame.std() > 10  # a picture, not a blank
        e.close()
    with pytest.raises(ValueError, match="render_mode"):
        RobotHockeyEnv(render_mode="human")


def test_missing_pybullet_names_the_robot_extra(monkeypatch):
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "pybullet":
            raise ImportError("No module named 'pybullet'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(ImportError, match=r"hireps-torch\[robot\]"):
        kin_module.require_robot_extra()
    with pytest.raises(ImportError, match="robot extra"):
        RobotHockeyEnv()


def test_episodic_env_checks_all_three_shots_before_playing(env):
    episodic = gym.make(EPISODIC_ENV_ID).unwrapped
    episodic.reset(seed=0)
    a = np.tile(episodic.inner.demo_action(), 3)
    a[20] = np.nan  # second shot, goal velocity of joint 7
    with pytest.raises(ValueError, match="index 20: nan"):
        episodic.step(a)
    assert episodic.inner.shot_index == 0  # nothing was played
    a[20] = 0.0
    _, _, terminated, _, info = episodic.step(a)
    episodic.close()
    assert terminated and len(info["shots"]) == 3


@pytest.mark.parametrize(
    "field,value,message",
    [
        ("joint_margin", 2.0, "joint_margin must be in"),
        ("min_blade_height", float("nan"), "min_blade_height must be finite"),
        ("position_gain", 0.0, "position_gain must be in"),
        ("dmp_basis", 1, "dmp_basis must be >= 2"),
        ("dmp_basis", 7.5, "dmp_basis must be an integer"),
        ("n_shots", 0, "n_shots must be >= 1"),
        ("n_shots", 2.0, "n_shots must be an integer"),
        ("zones", (1.4, float("nan"), 2.2, 2.6), "zones must be 4 finite increasing edges"),
        ("zones", (1.4, 1.8, 2.2), "zones must be 4 finite"),
        ("target_std", -0.1, "target_std must be >= 0"),
        ("flat_pucks", 1, "flat_pucks must be a bool"),
    ],
)
def test_bad_params_are_named(field, value, message):
    with pytest.raises((ValueError, TypeError), match=message):
        HockeyParams(**{field: value})


def _tilt_degrees(sim, body) -> float:
    """Angle (deg) between a puck's axis and the vertical."""
    q = sim.pb.getBasePositionAndOrientation(body, physicsClientId=sim.client)[1]
    axis_z = np.array(sim.pb.getMatrixFromQuaternion(q)).reshape(3, 3)[2, 2]
    return float(np.degrees(np.arccos(min(1.0, abs(axis_z)))))


def test_flat_pucks_stay_flat_in_hard_shots():
    """Swings up to 2.5x the demo's goal velocity: with flat_pucks neither puck tilts by more
    than half a degree (with the real inertia such hits tipped 2 of 30 pucks, one onto its
    edge), and the pucks still slide and spin."""
    from hireps_torch.envs.hockey import HockeySim, demo_action

    p = HockeyParams(flat_pucks=True)
    sim = HockeySim(p, marks=False)
    demo = torch.as_tensor(demo_action(p), dtype=torch.float64)
    rng = np.random.default_rng(1)
    try:
        moved = 0.0
        for _ in range(6):
            a = demo.clone()
            a[7:] *= 1.0 + 1.5 * rng.random()
            sim.new_world()
            sim.reset(np.array(p.target_mean))
            res = sim.shot(a[:7], a[7:])
            moved = max(moved, float(np.linalg.norm(res.target - np.array(p.target_mean))))
            for body in (sim.target, sim.control):
                assert _tilt_degrees(sim, body) < 0.5
        assert moved > 0.5  # hard shots did move the target puck
    finally:
        sim.close()


def test_a_fixed_start_puts_the_target_at_the_same_spot_every_episode():
    e = RobotHockeyEnv(HockeyParams(target_std=0.0))
    try:
        starts = {tuple(e.reset(seed=s)[0]) for s in range(4)}
    finally:
        e.close()
    assert starts == {tuple(HockeyParams().target_mean)}


def test_the_run_options_reach_the_task_constants():
    from hireps_torch.experiments.hockey import (
        HockeyFixedStartConfig,
        HockeySequentialConfig,
        hockey_params,
    )

    cfg = HockeySequentialConfig(
        start_std=0.03, puck_restitution=0.3, floor_friction=0.025, flat_pucks=True
    )
    p = hockey_params(cfg)
    assert (p.target_std, p.puck_restitution, p.floor_friction, p.flat_pucks) == (
        0.03,
        0.3,
        0.025,
        True,
    )
    preset = HockeyFixedStartConfig()  # paper Fig 15b: fixed start, 10 per update
    assert (preset.start_std, preset.episodes_per_iteration, preset.episodes) == (0.0, 10, 300)
    assert hockey_params(HockeySequentialConfig()) == HockeyParams()  # defaults unchanged


def test_goal_velocity_exploration_scaled_to_each_joint():
    """velocity_std_fraction: each joint's goal-velocity std follows the demo's goal velocity
    of that joint (joints the demo keeps still get the minimum); 0 keeps one std for all."""
    from hireps_torch.envs.hockey import demo_action
    from hireps_torch.experiments.hockey import HockeySequentialConfig, _exploration_std

    demo = torch.as_tensor(demo_action(HockeyParams()), dtype=torch.float64)
    cfg = HockeySequentialConfig(velocity_std_fraction=0.2, min_velocity_std=0.04)
    std = _exploration_std(cfg, 2, demo)
    expected = (0.2 * demo[7:].abs()).clamp_min(0.04)
    assert torch.equal(std[7:14], expected) and torch.equal(std[21:28], expected)
    assert torch.all(std[:7] == cfg.init_std_position)
    assert std[7:14].max() > 3 * std[7:14].min()  # the wrist moves far faster than the base
    plain = _exploration_std(HockeySequentialConfig(), 1, demo)
    assert torch.all(plain[7:] == 0.3)


@pytest.mark.parametrize("episodic", [False, True])
def test_a_closed_env_names_its_closing(episodic):
    """reset, step and render after close() raise one clear error, not pybullet's."""
    e = (RobotHockeyEpisodicEnv if episodic else RobotHockeyEnv)(render_mode="rgb_array")
    e.reset(seed=0)
    action = e.action_space.sample()
    e.close()
    for call in (lambda: e.step(action), lambda: e.reset(seed=1), e.render):
        with pytest.raises(RuntimeError, match="the environment was closed: make a new one"):
            call()
    e.close()  # a second close is harmless


def test_processes_killed_without_atexit_leave_one_arm_urdf_behind(tmp_path):
    """Every process writes the arm's URDF under one name per text (before: one file per
    process, removed at exit only, so killed workers left theirs in /tmp)."""
    import os
    import subprocess
    import sys

    code = (
        "import os\n"
        "from hireps_torch.envs.hockey.kinematics import arm_urdf\n"
        "text, path = arm_urdf()\n"
        "assert open(path).read() == text\n"
        "print(path)\n"
        "os._exit(0)\n"  # like a killed worker: no atexit
    )
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    paths = [
        subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
        ).stdout.strip()
        for _ in range(2)
    ]
    assert paths[0] == paths[1]
    assert sorted(p.name for p in tmp_path.iterdir()) == [os.path.basename(paths[0])]
    text, _ = kin_module.arm_urdf()
    assert (tmp_path / os.path.basename(paths[0])).read_text() == text


def test_an_arm_urdf_name_taken_by_another_user_gives_a_file_of_our_own(tmp_path, monkeypatch):
    """Where the shared name cannot be replaced (another user's file in a sticky /tmp), the
    process keeps its own copy under its own name."""
    import os

    def refuse(src, dst):
        raise PermissionError(1, "Operation not permitted", dst)

    monkeypatch.setattr(kin_module.tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(kin_module.os, "replace", refuse)
    geometry = kin_module.ArmGeometry(stick_length=0.51)  # not in arm_urdf's cache
    text, path = kin_module.arm_urdf(geometry)
    assert os.path.dirname(path) == str(tmp_path) and path.endswith(".urdf")
    assert open(path).read() == text and len(list(tmp_path.iterdir())) == 1
