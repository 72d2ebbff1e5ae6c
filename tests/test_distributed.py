"""Episodes by index on worker processes and Ray (experiments/workers.py).

The Ray tests start a local Ray instance with 2 CPUs inside a subprocess, so that the test
also checks that everything exits (a hang fails on the timeout)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

pytest.importorskip("pybullet")

from hireps_torch.experiments import hockey  # noqa: E402
from hireps_torch.experiments.workers import (  # noqa: E402
    InProcessPool,
    check_ray_address,
    episode_seeds,
    import_ray,
    make_pool,
    play_episodes,
    split_episodes,
)

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 240


def _run(args: list[str], cwd: Path = ROOT, **extra_env: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), **extra_env}
    return subprocess.run(
        args, cwd=cwd, env=env, capture_output=True, text=True, timeout=TIMEOUT, check=False
    )


def _ray_processes() -> list[str]:
    """Command lines of the Ray processes (GCS server, raylet, workers) still running."""
    found = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            args = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if "/ray/core/src/ray/" in args or args.startswith("ray::"):
            found.append(args[:120])
    return found


def _assert_ray_gone() -> None:
    import time

    deadline = time.monotonic() + 20
    while _ray_processes() and time.monotonic() < deadline:
        time.sleep(0.5)
    assert _ray_processes() == []


def members(algo):
    """A one-member hockey algorithm's policies as one run's (the actor plays those)."""
    return [p.member(0) for p in algo.policies]


def _actor_and_env() -> tuple[object, object]:
    from hireps_torch.envs.hockey import ENV_ID, HockeyParams, demo_action
    from hireps_torch.rollout import time_indexed_module

    cfg = hockey.HockeySequentialConfig(n_options=2, episodes=4, episodes_per_iteration=2)
    demo = torch.as_tensor(demo_action(HockeyParams()), dtype=torch.float64)
    algo = hockey._make_algorithm(cfg, 3, demo, hockey.hockey_params(cfg))
    return time_indexed_module(members(algo)), hockey._make_env(ENV_ID, True)


def test_episode_seeds_are_per_episode_and_repeat():
    a = [episode_seeds(7, e) for e in range(50)]
    assert a == [episode_seeds(7, e) for e in range(50)]
    assert len({s for s, _ in a}) == 50 and len({p for _, p in a}) == 50
    assert episode_seeds(8, 0) != episode_seeds(7, 0)
    assert episode_seeds(-(2**62), 0) != episode_seeds(2**62, 0)
    for env_seed, policy_seed in a:
        assert 0 <= env_seed < 2**32 and 0 <= policy_seed < 2**63
    with pytest.raises(ValueError, match="episode must be >= 0, got -1"):
        episode_seeds(0, -1)


def test_split_episodes_covers_every_episode_once_in_order():
    for n, parts in [(30, 2), (30, 4), (3, 8), (1, 1)]:
        chunks = split_episodes(range(n), parts)
        assert [e for c in chunks for e in c] == list(range(n))
        assert all(c for c in chunks) and len(chunks) == min(n, parts)


HISTORY_SCRIPT = textwrap.dedent(
    """
    import os
    os.environ.setdefault("MKL_CBWR", "COMPATIBLE")
    import torch
    from hireps_torch.envs.hockey import ENV_ID, HockeyParams, demo_action
    from hireps_torch.experiments import hockey
    from hireps_torch.experiments.workers import play_episodes
    from hireps_torch.algorithms import Experience
    from hireps_torch.rollout import episodes, time_indexed_module

    cfg = hockey.HockeySequentialConfig()
    demo = torch.as_tensor(demo_action(HockeyParams()), dtype=torch.float64)
    torch.manual_seed(0)
    algo = hockey._make_algorithm(cfg, 3, demo, hockey.hockey_params(cfg))
    actor = time_indexed_module([p.member(0) for p in algo.policies])
    env = hockey._make_env(ENV_ID, True)
    s, a, r, _ = episodes(play_episodes(env, actor, 0, range(12), 3), 3)
    algo.learn(Experience(states=s[None], actions=a[None], rewards=r[None]))  # hits the pucks
    actor = time_indexed_module([p.member(0) for p in algo.policies])
    first = play_episodes(env, actor, 0, range(12, 18), 3)
    again = play_episodes(env, actor, 0, range(12, 18), 3)
    later = play_episodes(env, actor, 0, [15, 16, 17], 3)
    fresh = play_episodes(hockey._make_env(ENV_ID, True), actor, 0, [17], 3)
    for key in ("observation", "action", ("next", "reward"), ("next", "observation")):
        assert torch.equal(first.get(key), again.get(key)), key
        assert torch.equal(first[9:].get(key), later.get(key)), key
        assert torch.equal(first[15:].get(key), fresh.get(key)), key
    assert not torch.equal(first[:3].get("observation"), first[3:6].get("observation"))
    print("SAME")
    """
)


@pytest.mark.slow
def test_an_episode_is_the_same_whatever_else_the_worker_played(tmp_path):
    """Episodes 12..17 of a learned policy played twice in a row, on their own after other
    episodes, and on a fresh environment give the same steps, bit for bit: the environment
    carries nothing from one episode to the next (with reproducible MKL, see
    hireps_torch.experiments.workers; without it these replays differed by up to 4e-3 rad)."""
    script = tmp_path / "history.py"
    script.write_text(HISTORY_SCRIPT)
    out = _run([sys.executable, str(script)])
    assert out.returncode == 0, out.stderr[-3000:]
    assert "SAME" in out.stdout


@pytest.mark.slow
def test_reproducible_mkl_reports_whether_it_is_in_force():
    code = (
        "import os; os.environ.pop('MKL_CBWR', None)\n"
        "import torch, warnings\n"
        "torch.ones(3, 3, dtype=torch.float64) @ torch.ones(3, 3, dtype=torch.float64)\n"
        "from hireps_torch.experiments.workers import _mkl_mode, reproducible_mkl\n"
        "if _mkl_mode() is None: print('NO MKL'); raise SystemExit\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    print(reproducible_mkl(), any('MKL started before' in str(x.message) for x in w))\n"
    )
    late = _run([sys.executable, "-c", code])
    assert late.returncode == 0, late.stderr
    if "NO MKL" in late.stdout:
        pytest.skip("torch without MKL")
    assert late.stdout.split() == ["False", "True"]
    early = _run(
        [
            sys.executable,
            "-c",
            "import hireps_torch.experiments.workers as w; print(w.reproducible_mkl())",
        ],
        MKL_CBWR="COMPATIBLE",
    )
    assert early.stdout.split() == ["True"], early.stderr


def test_every_episode_gets_one_fresh_world():
    """set_seed and the rollout both reset the env: the world is built once per episode."""
    actor, env = _actor_and_env()
    sim = env.base_env._env.unwrapped.sim
    built = []
    real = sim.new_world
    sim.new_world = lambda: (built.append(1), real())[1]
    try:
        play_episodes(env, actor, 0, range(4), 3)
    finally:
        env.close()
    assert len(built) == 3  # worlds for episodes 1-3; episode 0 plays in the env's first world


def test_play_episodes_refuses_other_episode_lengths_and_no_episodes():
    actor, env = _actor_and_env()
    try:
        with pytest.raises(RuntimeError, match="did not end after exactly 2 steps"):
            play_episodes(env, actor, 0, [0], 2)
        with pytest.raises(ValueError, match="at least one episode"):
            play_episodes(env, actor, 0, [], 3)
        with pytest.raises(TypeError, match="generator"):
            play_episodes(env, torch.nn.Linear(2, 2), 0, [0], 3)
    finally:
        env.close()


def test_bad_backend_options_are_named():
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        make_pool(lambda: None, workers=0)
    with pytest.raises(ValueError, match="backend must be 'local' or 'ray', got 'dask'"):
        make_pool(lambda: None, backend="dask")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs --backend ray"):
        make_pool(lambda: None, address="127.0.0.1:6379")
    assert isinstance(make_pool(lambda: None), InProcessPool)
    with pytest.raises(ValueError, match="must be HOST:PORT"):
        check_ray_address("nowhere")
    check_ray_address("AUTO")  # passed on to ray.init
    with pytest.raises(
        ValueError, match="cannot reach the Ray cluster at --ray-address '\\[::1\\]:1'"
    ):
        check_ray_address("[::1]:1", timeout=2.0)
    with pytest.raises(ValueError, match="cannot reach the Ray cluster at --ray-address '127.0.0"):
        check_ray_address("127.0.0.1:1", timeout=2.0)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (dict(workers=0), "workers must be in 1..1024, got 0"),
        (dict(ray_address="127.0.0.1:1"), "needs --backend ray"),
        (dict(backend="spark"), "backend"),
    ],
)
def test_hockey_refuses_bad_worker_options(tmp_path, options, message):
    cfg = hockey.HockeySequentialConfig(run_dir=tmp_path / "run", progress=False, **options)
    with pytest.raises(ValueError, match=message):
        hockey.run(cfg)
    assert not (tmp_path / "run").exists()


def test_ray_missing_names_the_distributed_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ImportError, match=r"\.\[distributed\]"):
        import_ray()
    with pytest.raises(ImportError, match="distributed"):
        make_pool(lambda: None, workers=2, backend="ray")


@pytest.mark.slow
def test_core_library_and_local_runs_work_without_ray(tmp_path):
    """With ``ray`` unimportable, the library, the experiments and a local hockey run work
    (torchrl imports ray on its own when it is installed; nothing of ours needs it)."""
    code = (
        "import sys; sys.modules['ray'] = None\n"
        "import train\n"
        f"train.main(['hockey-sequential', '--episodes', '4', '--episodes-per-iteration', '2',"
        f" '--n-options', '2', '--no-progress', '--run-dir', {str(tmp_path / 'run')!r}])\n"
    )
    out = _run([sys.executable, "-c", code])
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "run" / "summary.json").is_file()


TINY = ["--episodes", "12", "--episodes-per-iteration", "4", "--n-options", "2", "--no-progress"]


@pytest.mark.slow
def test_two_ray_workers_write_the_same_metrics_as_one_local_worker(tmp_path):
    pytest.importorskip("ray")
    runs = {
        "local1": ["--workers", "1", "--backend", "local"],
        "ray2": ["--workers", "2", "--backend", "ray"],
    }
    for name, extra in runs.items():
        out = _run(
            [
                sys.executable,
                "train.py",
                "hockey-sequential",
                *TINY,
                *extra,
                "--run-dir",
                str(tmp_path / name),
            ]
        )
        assert out.returncode == 0, out.stderr[-3000:]
    ref = (tmp_path / "local1" / "metrics.csv").read_text()
    assert len(ref.splitlines()) == 4  # header + 3 iterations
    assert (tmp_path / "ray2" / "metrics.csv").read_text() == ref
    _assert_ray_gone()


def test_unreachable_ray_address_is_a_clear_error(tmp_path):
    out = _run(
        [
            sys.executable,
            "train.py",
            "hockey-sequential",
            *TINY,
            "--backend",
            "ray",
            "--ray-address",
            "127.0.0.1:1",
            "--run-dir",
            str(tmp_path / "run"),
        ]
    )
    assert out.returncode == 2
    assert "127.0.0.1:1" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "run").exists()


KILL_SCRIPT = textwrap.dedent(
    """
    import os, sys
    os.environ.setdefault("MKL_CBWR", "COMPATIBLE")  # as train.py does for hockey
    import torch
    from tensordict.nn import TensorDictModule
    from hireps_torch.envs.hockey import ENV_ID, HockeyParams, demo_action
    from hireps_torch.experiments import hockey
    from hireps_torch.experiments.workers import InProcessPool, make_pool
    from hireps_torch.rollout import TimeIndexedActor, time_indexed_module

    MARK = sys.argv[2]

    class DieOnce(TimeIndexedActor):
        # the first decision anywhere kills its worker process (once: it leaves a mark)
        def forward(self, observation, step_count):
            if not os.path.exists(MARK):
                open(MARK, "w").close()
                os._exit(1)
            return super().forward(observation, step_count)

    def make_env():
        return hockey._make_env(ENV_ID, True)

    if __name__ == "__main__":
        cfg = hockey.HockeySequentialConfig(n_options=2)
        demo = torch.as_tensor(demo_action(HockeyParams()), dtype=torch.float64)
        algo = hockey._make_algorithm(cfg, 3, demo, hockey.hockey_params(cfg))
        policies = [p.member(0) for p in algo.policies]
        dying = TensorDictModule(DieOnce(policies), ["observation", "step_count"],
                                 ["action", "option"])
        pool = make_pool(make_env, workers=2, backend=sys.argv[1])
        try:
            got = pool.play(dying, 5, range(4), 3)
        finally:
            pool.close()
        assert os.path.exists(MARK), "no worker was killed"
        ref_pool = InProcessPool(make_env)
        ref = ref_pool.play(time_indexed_module(policies), 5, range(4), 3)
        ref_pool.close()
        assert got.shape == ref.shape == (12,), (got.shape, ref.shape)
        for key in ("observation", "action", ("next", "reward"), ("next", "observation")):
            assert torch.equal(got.get(key), ref.get(key)), key
        print("EPISODES", got.shape[0] // 3)
    """
)


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["ray", "local"])
def test_a_worker_killed_mid_iteration_loses_and_duplicates_no_episode(tmp_path, backend):
    if backend == "ray":
        pytest.importorskip("ray")
    script = tmp_path / "kill.py"
    script.write_text(KILL_SCRIPT)
    out = _run([sys.executable, str(script), backend, str(tmp_path / "killed")])
    assert out.returncode == 0, out.stderr[-3000:]
    assert "EPISODES 4" in out.stdout
    _assert_ray_gone()


def test_reproducible_mkl_leaves_the_environment_as_it_was(monkeypatch):
    """A hockey run in a user's process must not change what its later subprocesses get."""
    from hireps_torch.experiments.workers import mkl_environment, reproducible_mkl

    monkeypatch.delenv("MKL_CBWR", raising=False)
    reproducible_mkl(warn=False)
    assert "MKL_CBWR" not in os.environ
    with mkl_environment():
        assert os.environ["MKL_CBWR"] == "COMPATIBLE"
    assert "MKL_CBWR" not in os.environ
    monkeypatch.setenv("MKL_CBWR", "AVX2")
    with mkl_environment():
        assert os.environ["MKL_CBWR"] == "AVX2"  # the user's choice stands
    assert reproducible_mkl(warn=False) is False and os.environ["MKL_CBWR"] == "AVX2"


@pytest.mark.parametrize("address", ["host:\u00b2", "localhost:99999", "localhost:0", "h:-1"])
def test_a_ray_address_with_a_bad_port_is_refused_naming_it(address):
    with pytest.raises(ValueError, match="a port in 1..65535"):
        check_ray_address(address)


@contextlib.contextmanager
def _fake_server(pieces, gap=0.0):
    """A local TCP server that accepts one connection and sends ``pieces`` (``gap`` seconds
    apart), then stays silent; yields its port."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    held = []

    def serve():
        conn, _ = server.accept()
        held.append(conn)
        for piece in pieces:
            conn.sendall(piece)
            time.sleep(gap)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        thread.join(5)
        for conn in held:
            conn.close()
        server.close()


@pytest.mark.parametrize("banner", [b"", b"SSH-2.0-OpenSSH_9.6\r\n"], ids=["silent", "ssh"])
def test_a_port_where_something_else_listens_is_not_taken_for_ray(banner):
    """A server that says nothing, or answers like sshd, is named within the timeout
    (``ray.init`` would wait minutes)."""
    what = "is not a Ray cluster: something accepts connections there, but no gRPC server"
    with _fake_server([banner] if banner else []) as port:
        start = time.monotonic()
        with pytest.raises(ValueError, match=what):
            check_ray_address(f"127.0.0.1:{port}", timeout=1.0)
        assert time.monotonic() - start < 5


THREADS_SCRIPT = textwrap.dedent(
    """
    import os
    os.environ.setdefault("MKL_CBWR", "COMPATIBLE")
    from functools import partial
    import torch
    from hireps_torch.envs.hockey import ENV_ID, HockeyParams, demo_action
    from hireps_torch.experiments import hockey
    from hireps_torch.experiments.workers import LocalProcessPool, play_episodes
    from hireps_torch.rollout import time_indexed_module

    if __name__ == "__main__":
        cfg = hockey.HockeySequentialConfig()
        demo = torch.as_tensor(demo_action(HockeyParams()), dtype=torch.float64)
        torch.manual_seed(0)
        algo = hockey._make_algorithm(cfg, 3, demo, hockey.hockey_params(cfg))
        actor = time_indexed_module([p.member(0) for p in algo.policies])
        env = hockey._make_env(ENV_ID, True)
        played = {}
        for threads in (1, 2, 4):
            torch.set_num_threads(threads)
            played[threads] = play_episodes(env, actor, 93, range(4), 3)
            assert torch.get_num_threads() == threads  # the process's setting is restored
        pool = LocalProcessPool(partial(hockey._make_env, ENV_ID, True), workers=2)
        try:
            played["worker"] = pool.play(actor, 93, range(4), 3)
        finally:
            pool.close()
        keys = ("observation", "action", ("next", "reward"), ("next", "observation"))
        for k in (2, 4, "worker"):
            for key in keys:
                assert torch.equal(played[1].get(key), played[k].get(key)), (k, key)
        print("SAME")
    """
)


@pytest.mark.slow
def test_hockey_episodes_do_not_depend_on_the_thread_count_or_the_worker(tmp_path):
    """The same episodes played with 1, 2 and 4 torch threads and on worker processes are
    equal bit for bit (before: the process's own thread count changed the sums)."""
    script = tmp_path / "threads.py"
    script.write_text(THREADS_SCRIPT)
    out = _run([sys.executable, str(script)], OMP_NUM_THREADS="4")
    assert out.returncode == 0, out.stderr[-3000:]
    assert "SAME" in out.stdout


def test_a_ray_host_name_that_cannot_be_encoded_is_named():
    with pytest.raises(ValueError, match="is not a valid host name"):
        check_ray_address("a" * 70 + ":6379")


def test_a_grpc_server_is_taken_for_a_ray_cluster_and_an_http_one_is_not():
    """The check is gRPC's own handshake: a gRPC server passes (a Ray cluster's GCS is one),
    an HTTP/1 server is named within the timeout."""
    from concurrent.futures import ThreadPoolExecutor

    import grpc

    server = grpc.server(ThreadPoolExecutor(1))
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        check_ray_address(f"127.0.0.1:{port}", timeout=5.0)
    finally:
        server.stop(0)
    with _fake_server([b"HTTP/1.1 400 Bad Request\r\n\r\n"]) as port:
        with pytest.raises(ValueError, match="is not a Ray cluster"):
            check_ray_address(f"127.0.0.1:{port}", timeout=1.0)


def _hockey_metrics(tmp_path: Path, name: str, threads: str | None, *extra: str) -> str:
    """metrics.csv of a tiny hockey-sequential run by ``hireps-train`` with ``threads`` torch
    threads (None: the machine's default, OMP_NUM_THREADS unset)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_CBWR")}
    if threads is not None:
        env["OMP_NUM_THREADS"] = threads
    code = "import sys; from hireps_torch.cli import entry; sys.argv[0] = 'hireps-train'; entry()"
    args = ["hockey-sequential", *TINY, "--seed", "93", "--run-dir", str(tmp_path / name)]
    out = subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=ROOT,
        env={**env, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return (tmp_path / name / "metrics.csv").read_text()


def test_a_hockey_run_is_the_same_with_the_default_one_and_four_threads(tmp_path):
    """Episodes and updates bit for bit whatever torch's thread count (before: the simulation's
    set-up ran on the process's threads, and its round-off changed every episode)."""
    default = _hockey_metrics(tmp_path, "default", None)
    assert len(default.splitlines()) == 4  # header + 3 iterations
    assert _hockey_metrics(tmp_path, "one", "1") == default
    assert _hockey_metrics(tmp_path, "four", "4") == default


@pytest.mark.slow
def test_a_hockey_run_with_default_threads_equals_local_and_ray_workers(tmp_path):
    pytest.importorskip("ray")
    default = _hockey_metrics(tmp_path, "default", None)
    assert _hockey_metrics(tmp_path, "local2", None, "--workers", "2") == default
    assert _hockey_metrics(tmp_path, "ray2", None, "--workers", "2", "--backend", "ray") == default
    _assert_ray_gone()
