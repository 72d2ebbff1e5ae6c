"""Devices: the duals, policies and algorithms compute where their inputs are.

Without a GPU the device paths are checked on the CPU by making torch's default device
``meta``: a tensor the library creates without naming a device then lands on ``meta`` and
the first operation that mixes it with the CPU data fails. The CUDA tests compare a GPU
population with the same population on the CPU; they are skipped where no GPU is present.
"""

import contextlib
import csv
import warnings

import pytest
import torch

import train
from hireps_torch.algorithms import EpisodicHiREPS, InfiniteHorizonHiREPS, TimeIndexedHiREPS
from hireps_torch.dual import (
    solve_episodic_dual,
    solve_infinite_horizon_dual,
    solve_time_indexed_dual,
)
from hireps_torch.features import FourierFeatures

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")


@contextlib.contextmanager
def default_device_meta():
    """Tensors created without a device go to ``meta`` (and break when mixed with data)."""
    torch.set_default_device("meta")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        torch.set_default_device(None)


def randn(gen, *shape):
    return torch.randn(*shape, generator=gen, dtype=torch.float64)


def dual_cases(device="cpu"):
    """Each dual with options, an entropy bound and features, as a population and alone."""
    g = torch.Generator().manual_seed(0)
    S, N, O, F, K = 3, 40, 3, 4, 3

    def d(x):
        return x.to(device)

    lr = d(torch.log_softmax(randn(g, S, N, O), -1))
    lr_k = d(torch.log_softmax(randn(g, S, N, K, O), -1))
    R, C, R1, C1 = d(randn(g, S, N)), d(randn(g, S, N, 2)), d(randn(g, N)), d(randn(g, N, 2))
    r, phi, phi2, phi0 = (
        d(randn(g, S, N)),
        d(randn(g, S, N, F)),
        d(randn(g, S, N, F)),
        d(randn(g, F)),
    )
    rk, phik = d(randn(g, S, N, K)), d(randn(g, S, N, K, F))
    return {
        "episodic population": lambda: solve_episodic_dual(
            R, epsilon=0.5, log_responsibilities=lr, context_features=C, kappa=0.8, population=True
        ),
        "episodic": lambda: solve_episodic_dual(R1, epsilon=0.5, context_features=C1),
        "infinite-horizon population": lambda: solve_infinite_horizon_dual(
            r,
            phi,
            phi2,
            phi0,
            gamma=0.95,
            epsilon=0.5,
            log_responsibilities=lr,
            kappa=0.8,
            population=True,
        ),
        "time-indexed population": lambda: solve_time_indexed_dual(
            rk, phik, epsilon=0.5, log_responsibilities=lr_k, kappa=0.8, population=True
        ),
        "constant returns": lambda: solve_episodic_dual(R1 * 0 + 1, epsilon=0.5),
        "unmeetable features (ridge fallback)": lambda: solve_infinite_horizon_dual(
            r[:, :6], phi[:, :6], phi2[:, :6], phi0 + 5, gamma=0.95, epsilon=0.1, population=True
        ),
    }


@pytest.mark.parametrize("case", list(dual_cases()))
def test_duals_create_nothing_on_the_default_device(case):
    expected = dual_cases()[case]()
    solve = dual_cases()[case]
    with default_device_meta():
        sol = solve()
    # a CPU op that took a meta operand would have left garbage: the same numbers prove none
    assert sol.weights.device.type == "cpu"
    assert torch.equal(sol.weights, expected.weights)
    assert torch.equal(torch.as_tensor(sol.kl), torch.as_tensor(expected.kl))


def build_algorithms(population, device="cpu"):
    """Each variant with inputs for one round, on ``device``."""
    g = torch.Generator().manual_seed(1)
    kw = {"seed": [0, 1, 2]} if population else {"seed": 0}
    lead = (3,) if population else ()
    features = FourierFeatures(low=[-1.0, -1.0], high=[1.0, 1.0], n_bases=3)
    return {
        "episodic": (
            EpisodicHiREPS.create(context_dim=2, param_dim=3, n_options=3, **kw).to(device),
            randn(g, *lead, 30, 2).to(device),
        ),
        "infinite-horizon": (
            InfiniteHorizonHiREPS.create(
                2, 1, value_features=features, initial_states=randn(g, 50, 2), gamma=0.95, **kw
            ).to(device),
            randn(g, *lead, 60, 2).to(device),
        ),
        "time-indexed": (
            TimeIndexedHiREPS.create(3, 2, 2, n_options=3, **kw).to(device),
            randn(g, *lead, 30, 3, 2).to(device),
        ),
    }


def play_round(built):
    """Sample and update each variant once; their diagnostics and learned tensors."""
    ep, c = built["episodic"]
    theta = ep.ask(c)
    out = {"episodic": (ep.tell(c, theta, -(theta**2).sum(-1)), ep.policy.options[0].bias)}
    ih, s = built["infinite-horizon"]
    a = ih.sample(s)
    diag = ih.update(s, a, -(s**2).sum(-1) - (a**2).sum(-1), s + 0.1 * a)
    out["infinite-horizon"] = (diag, ih.value_weights)
    ti, st = built["time-indexed"]
    p = torch.stack([ti.ask(k, st[..., k, :]) for k in range(3)], -2)
    out["time-indexed"] = (ti.tell(st, p, -(p**2).sum(-1)), ti.value_weights)
    return out


@pytest.mark.parametrize("population", [False, True])
def test_algorithms_create_nothing_on_the_default_device(population):
    expected = play_round(build_algorithms(population))
    built = build_algorithms(population)
    with default_device_meta():
        got = play_round(built)
    for name, (diag, learned) in got.items():
        assert learned.device.type == "cpu", name
        assert diag["kl"] == expected[name][0]["kl"], name  # the same computation


def test_to_moves_nothing_and_names_a_bad_device():
    algo = EpisodicHiREPS.create(context_dim=1, param_dim=2, n_options=2, seed=0)
    assert algo.to("cpu") is algo and algo.device == torch.device("cpu")
    before = algo.policy.options[0].bias.clone()
    with pytest.raises(ValueError, match="'nonsense'"):
        algo.to("nonsense")
    with pytest.raises(ValueError, match="meta"):
        algo.to("meta")
    assert torch.equal(algo.policy.options[0].bias, before)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="'cuda' is not available here"):
            algo.to("cuda")
        assert algo.device == torch.device("cpu")


def test_dual_inputs_on_two_devices_are_named():
    R = torch.randn(20, dtype=torch.float64)
    elsewhere = torch.empty(20, 2, dtype=torch.float64, device="meta")
    with pytest.raises(ValueError, match="context_features is on device meta but the other"):
        solve_episodic_dual(R, epsilon=0.5, context_features=elsewhere)


def test_algorithm_refuses_samples_on_another_device():
    algo = EpisodicHiREPS.create(context_dim=2, param_dim=2, n_options=2, seed=0)
    with pytest.raises(ValueError, match="contexts is on device meta but the other inputs are on"):
        algo.ask(torch.empty(5, 2, device="meta"))
    features = FourierFeatures(low=[-1.0], high=[1.0], n_bases=3)
    ih = InfiniteHorizonHiREPS.create(
        1, 1, value_features=features, initial_states=torch.zeros(4, 1), gamma=0.9, seed=0
    )
    s, a = torch.zeros(6, 1), torch.zeros(6, 1)
    with pytest.raises(ValueError, match="terminated is on device meta but the other inputs"):
        ih.update(s, a, torch.zeros(6), s, torch.empty(6, dtype=torch.bool, device="meta"))


def test_options_added_later_are_left_out_of_config_json_at_their_default():
    """Run directories written before ``device`` and ``final_eval_episodes`` existed compare
    equal to today's defaults (resume, sweeps); set, they are saved."""
    from hireps_torch.experiments.hockey import HockeySequentialConfig
    from hireps_torch.experiments.options import config_dict

    plain = config_dict("hockey_sequential", HockeySequentialConfig())
    assert "device" not in plain and "final_eval_episodes" not in plain
    set_ = config_dict("hockey_sequential", HockeySequentialConfig(final_eval_episodes=5))
    assert set_["final_eval_episodes"] == 5


@pytest.mark.parametrize(
    "argv, match",
    [
        (["bimodal", "--device", "nonsense"], r"device \(--device\) must be a torch device"),
        (["bimodal", "--seeds", "0-1", "--device", "meta"], "holds values"),
        (["pendulum", "--device", "meta"], "holds values"),
    ],
)
def test_bad_devices_name_the_value(tmp_path, argv, match):
    with pytest.raises(ValueError, match=match):
        train.main([*argv, "--run-dir", str(tmp_path / "run"), "--no-progress"])
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message without a GPU")
def test_cuda_without_a_gpu_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"device \(--device\) must be a device present here"):
        train.main(
            ["pendulum", "--seeds", "0-1", "--device", "cuda", "--run-dir", str(tmp_path / "r")]
        )
    assert not (tmp_path / "r").exists()


@cuda
@pytest.mark.parametrize("case", list(dual_cases()))
def test_duals_on_cuda_equal_the_cpu(case):
    on_cpu, on_gpu = dual_cases()[case](), dual_cases("cuda")[case]()
    assert on_gpu.weights.device.type == "cuda"
    torch.testing.assert_close(on_gpu.weights.cpu(), on_cpu.weights, rtol=1e-6, atol=1e-9)
    kl_gpu, kl_cpu = torch.as_tensor(on_gpu.kl).cpu(), torch.as_tensor(on_cpu.kl)  # float alone
    torch.testing.assert_close(kl_gpu, kl_cpu, rtol=1e-6, atol=1e-9)


@cuda
@pytest.mark.parametrize("population", [False, True])
def test_algorithms_on_cuda_equal_the_cpu(population):
    on_cpu = play_round(build_algorithms(population))
    on_gpu = play_round(build_algorithms(population, "cuda"))
    for name, (diag, learned) in on_gpu.items():
        assert learned.device.type == "cuda", name
        torch.testing.assert_close(learned.cpu(), on_cpu[name][1], rtol=1e-6, atol=1e-8)
        kl_gpu = torch.tensor(diag["kl"], dtype=torch.float64)  # (S[, K])
        kl_cpu = torch.tensor(on_cpu[name][0]["kl"], dtype=torch.float64)
        torch.testing.assert_close(kl_gpu, kl_cpu, rtol=1e-6, atol=1e-9, msg=name)


@cuda
@pytest.mark.parametrize("members", [["--seed", "3"], ["--seeds", "0-1"]])
@pytest.mark.parametrize(
    "argv",
    [
        ["pendulum", "--episodes", "40", "--episode-seconds", "0.5", "--eval-rollouts", "4"],
        [
            "ball-on-beam",
            "--episodes",
            "4",
            "--episodes-per-iteration",
            "2",
            "--eval-episodes",
            "2",
        ],
        ["bimodal", "--episodes", "400", "--samples-per-iteration", "200"],
    ],
)
def test_runs_on_cuda_match_the_cpu(tmp_path, argv, members):
    """One seed or a population: each run's first update on the GPU as on the CPU."""
    for device in ("cpu", "cuda"):
        train.main(
            [*argv, *members, "--device", device, "--no-progress"]
            + ["--run-dir", str(tmp_path / device)]
        )
    dirs = ["."] if members[0] == "--seed" else ["seed0", "seed1"]
    for d in dirs:
        assert_first_updates_agree(tmp_path / "cpu" / d, tmp_path / "cuda" / d)


def assert_first_updates_agree(cpu_run, gpu_run):
    """The runs' metrics.csv have as many rows, and the first update (the same samples from
    the CPU generators, the same dual) agrees to round-off."""
    with open(cpu_run / "metrics.csv") as f:
        cpu_rows = list(csv.DictReader(f))
    with open(gpu_run / "metrics.csv") as f:
        gpu_rows = list(csv.DictReader(f))
    assert len(gpu_rows) == len(cpu_rows) > 0
    first_cpu, first_gpu = cpu_rows[0], gpu_rows[0]
    for key in ("kl", "eta", "mean_return", "average_return", "eval_return"):
        if key in first_cpu:
            cpu_value, gpu_value = float(first_cpu[key]), float(first_gpu[key])
            assert gpu_value == pytest.approx(cpu_value, rel=1e-5, abs=1e-9, nan_ok=True), key


@cuda
def test_time_indexed_actor_runs_on_cuda():
    from hireps_torch.rollout import time_indexed_module

    algo = TimeIndexedHiREPS.create(3, 2, 2, n_options=3, seed=0).to("cuda")
    actor = time_indexed_module(list(algo.policies))
    obs = torch.zeros(4, 2, device="cuda")
    steps = torch.tensor([[0], [1], [2], [0]], device="cuda")
    action, option = actor.module(obs, steps)
    assert action.device.type == "cuda" and option.device.type == "cuda"
