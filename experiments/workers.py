"""Whole episodes by index: in this process, in local worker processes, or on Ray::

    pool = make_pool(make_env, workers=2, backend="ray")        # or "local"
    batch = pool.play(actor, seed=0, episodes=range(30), steps=3)  # (30 * 3,) TensorDict
    pool.close()

Episode ``e`` draws from ``(seed, e)`` alone (:func:`episode_seeds`), so neither the worker nor
the backend changes the result. Every process that plays or updates runs MKL as
``MKL_CBWR=COMPATIBLE`` (:func:`reproducible_mkl`; a Python session running hockey should start
with it set, as ``hireps-train`` and the pool's workers do; why: docs/reproducibility.md).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import socket
import uuid
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Literal

import numpy as np
import torch
from tensordict import TensorDictBase

from hireps_torch.envs._common import one_thread
from hireps_torch.experiments.pool import MKL_MODE, LocalPool, mkl_environment

__all__ = [
    "Backend",
    "InProcessPool",
    "LocalProcessPool",
    "RayPool",
    "check_pool",
    "episode_seeds",
    "import_ray",
    "make_pool",
    "play_episodes",
    "reproducible_mkl",
    "split_episodes",
]

Backend = Literal["local", "ray"]
_TAG = 0x686F636B  # separates these streams from any other use of the run's seed
MAX_RETRIES = 3
"""How often a local pool broken by a dead worker is rebuilt to play the same episodes."""


def _mkl_mode() -> int | None:
    """MKL's CBWR branch (1: AUTO, the default; 2 or 3 once COMPATIBLE is in force), or None
    without an MKL in torch."""
    path = os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so")
    try:
        get = ctypes.CDLL(path).mkl_serv_cbwr_get
    except (OSError, AttributeError):
        return None
    return int(get(1))


def reproducible_mkl(warn: bool = True) -> bool:
    """Put this process's MKL in ``MKL_CBWR=COMPATIBLE`` (unless the user chose a mode; only
    before any arithmetic). Returns whether it runs in that mode; with ``warn``, warns when
    MKL had already started in another."""
    user_mode = os.environ.get("MKL_CBWR", MKL_MODE)
    with mkl_environment():
        a = torch.ones(4, 4, dtype=torch.float64)
        _ = a @ a  # MKL reads MKL_CBWR at its first call
        mode = _mkl_mode()
    if mode is None or user_mode != MKL_MODE:
        return False
    if mode == 1 and warn:
        warnings.warn(
            "MKL started before MKL_CBWR=COMPATIBLE was set (arithmetic ran before the run "
            "began, as import torchrl does): episodes played in this process can differ in the "
            "last bits, and the run then in its course, from the same seed's run by "
            "hireps-train or by worker processes; set MKL_CBWR=COMPATIBLE before starting "
            "Python",
            RuntimeWarning,
            stacklevel=2,
        )
    return mode != 1


def episode_seeds(seed: int, episode: int) -> tuple[int, int]:
    """(environment seed in [0, 2**32), policy seed in [0, 2**63)) of episode ``episode`` of
    a run with ``seed`` in [-2**62, 2**62] (``numpy.random.SeedSequence``)."""
    if episode < 0:
        raise ValueError(f"episode must be >= 0, got {episode}")
    words = np.random.SeedSequence([int(seed) + 2**62, int(episode), _TAG]).generate_state(3)
    return int(words[0]), (int(words[1]) << 31) ^ int(words[2])


def play_episodes(
    env: Any, actor: Any, seed: int, episodes: Sequence[int], steps: int
) -> TensorDictBase:
    """Play ``episodes`` (indices) of exactly ``steps`` decisions each with ``actor`` on the
    TorchRL environment ``env``, episode ``e`` from :func:`episode_seeds` ``(seed, e)``, on
    one torch thread.

    Returns:
        the episodes one after another: a ``(len(episodes) * steps,)`` TensorDict with the
        collector's keys.
    """
    net = getattr(actor, "module", actor)
    if not hasattr(net, "generator"):
        raise TypeError(
            f"the actor must be a policy_module / time_indexed_module (a module with a "
            f"'generator'), got {type(net).__name__}"
        )
    if len(episodes) == 0:
        raise ValueError("play_episodes needs at least one episode index")
    gen = torch.Generator()
    out = []
    previous = net.generator
    net.generator = gen
    # one thread, whatever the process was given: an episode's sums then do not depend on
    # the machine's cores, OMP_NUM_THREADS or the backend (with reproducible MKL, above)
    try:
        with one_thread():
            for e in episodes:
                env_seed, policy_seed = episode_seeds(seed, e)
                env.set_seed(env_seed)
                gen.manual_seed(policy_seed)
                td = env.rollout(steps, actor, auto_reset=True, break_when_any_done=True)
                done = td.get(("next", "done")).reshape(-1)
                if td.shape[-1] != steps or not bool(done[-1]) or bool(done[:-1].any()):
                    raise RuntimeError(
                        f"episode {e} did not end after exactly {steps} steps (it ran "
                        f"{td.shape[-1]}): play_episodes needs fixed-length episodes"
                    )
                out.append(td)
    finally:
        net.generator = previous
    return torch.cat(out)


# ---- what a worker process keeps between calls ------------------------------------------------
_ENV: dict[str, Any] = {}


def _play_chunk(
    make_env: Callable[[], Any],
    key: str,
    actor: Any,
    seed: int,
    episodes: Sequence[int],
    steps: int,
) -> TensorDictBase:
    """Play ``episodes`` on the environment of run ``key`` in this worker process (built once;
    another run's closed)."""
    if key not in _ENV:
        for old in _ENV.values():
            with contextlib.suppress(Exception):  # best effort
                old.close()
        _ENV.clear()
        _ENV[key] = make_env()
    return play_episodes(_ENV[key], actor, seed, episodes, steps)


def split_episodes(episodes: Sequence[int], parts: int) -> list[list[int]]:
    """Contiguous, nearly equal chunks (no empty ones) of ``episodes`` for ``parts`` workers."""
    eps = np.asarray([int(e) for e in episodes], dtype=np.int64)
    return [c.tolist() for c in np.array_split(eps, parts) if c.size]


# ---- pools ------------------------------------------------------------------------------------
class InProcessPool:
    """One worker: this process, with the environment built on the first call."""

    def __init__(self, make_env: Callable[[], Any]) -> None:
        self.make_env = make_env
        self.workers = 1
        self.env: Any = None

    def play(self, actor: Any, seed: int, episodes: Sequence[int], steps: int) -> TensorDictBase:
        if self.env is None:
            self.env = self.make_env()
        return play_episodes(self.env, actor, seed, episodes, steps)

    def close(self) -> None:
        if self.env is not None:
            self.env.close()
            self.env = None


class LocalProcessPool:
    """``workers`` processes of a :class:`~.pool.LocalPool` on this machine; each keeps its
    environment between iterations. A pool broken by a dead worker is rebuilt and the episodes
    played again."""

    def __init__(self, make_env: Callable[[], Any], workers: int) -> None:
        self.make_env = make_env
        self.workers = workers
        self.key = uuid.uuid4().hex
        self.pool = LocalPool(workers)

    def play(self, actor: Any, seed: int, episodes: Sequence[int], steps: int) -> TensorDictBase:
        chunks = split_episodes(episodes, self.workers)
        for attempt in range(MAX_RETRIES + 1):
            futures = [
                self.pool.submit(_play_chunk, self.make_env, self.key, actor, seed, c, steps)
                for c in chunks
            ]
            try:
                return torch.cat([f.result() for f in futures])
            except BrokenProcessPool:
                self.pool.restart()
                if attempt == MAX_RETRIES:
                    raise RuntimeError(
                        f"worker processes died {attempt + 1} times while playing episodes "
                        f"{chunks[0][0]}..{chunks[-1][-1]}; giving up"
                    ) from None
        raise AssertionError("unreachable")  # pragma: no cover

    def close(self) -> None:
        self.pool.close()


def import_ray() -> Any:
    """``ray``, or an ImportError that names the extra to install."""
    try:
        import ray
    except ImportError:
        raise ImportError(
            "the ray backend needs Ray: pip install -e '.[distributed]' (the 'distributed' "
            "extra of hireps-torch)"
        ) from None
    return ray


def check_ray_address(address: str, timeout: float = 5.0) -> None:
    """A ``ValueError`` naming ``address`` (HOST:PORT or ray://HOST:PORT; ``"auto"`` passes)
    unless a gRPC server (as a Ray cluster's GCS is) answers there within ``timeout`` seconds
    (``ray.init`` would retry for minutes)."""
    if address.lower() == "auto":
        return
    hostport = address.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")  # [::1]:6379
    if not sep or not host or not re.fullmatch(r"[0-9]{1,5}", port) or not 0 < int(port) < 65536:
        raise ValueError(
            f"--ray-address must be HOST:PORT (a port in 1..65535), ray://HOST:PORT or 'auto', "
            f"got {address!r}"
        )
    try:  # refused, no route and unknown hosts are named at once
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except UnicodeError:  # the host name cannot be encoded (a label over 63 characters, ...)
        raise ValueError(
            f"--ray-address {address!r}: {host[:80]!r} is not a valid host name"
        ) from None
    except OSError as exc:  # refused, no route, unknown host, or no answer within timeout
        why = f"no answer within {timeout:g} s" if isinstance(exc, TimeoutError) else exc
        raise ValueError(
            f"cannot reach the Ray cluster at --ray-address {address!r}: {why}"
        ) from None
    import grpc  # Ray's own dependency: the 'distributed' extra, checked before this

    channel = grpc.insecure_channel(hostport, options=[("grpc.enable_http_proxy", 0)])  # as Ray
    try:
        grpc.channel_ready_future(channel).result(timeout=timeout)
    except grpc.FutureTimeoutError:
        raise ValueError(
            f"--ray-address {address!r} is not a Ray cluster: something accepts connections "
            f"there, but no gRPC server answered within {timeout:g} s; is it the cluster's GCS "
            "port (ray start --head prints it; 6379 by default)?"
        ) from None
    finally:
        channel.close()


RAY_ENV = {"env_vars": {"MKL_CBWR": MKL_MODE, "OMP_NUM_THREADS": "1"}}
"""The environment of every Ray worker process (reproducible MKL, one thread per task)."""


def start_ray(workers: int, address: str | None, runtime_env: dict[str, Any]) -> tuple[Any, bool]:
    """``ray``, started (a local instance with ``workers`` CPUs, or the cluster at ``address``)
    unless it runs already in this process, and whether this call started it."""
    ray = import_ray()
    if ray.is_initialized():
        return ray, False
    local = address is None
    where = {"num_cpus": workers, "configure_logging": False} if local else {"address": address}
    try:
        ray.init(**where, include_dashboard=False, log_to_driver=False, runtime_env=runtime_env)
    except (ConnectionError, RuntimeError) as exc:
        if local:  # a local start's own error, as it is
            raise
        raise ValueError(f"cannot join the Ray cluster at {address!r}: {exc}") from None
    return ray, True


class RayPool:
    """One Ray task per worker and call, on a local Ray instance with ``workers`` CPUs or on
    the cluster at ``address``; Ray re-runs a task whose worker died (3 times). A pool that
    started Ray shuts it down in :meth:`close`."""

    def __init__(
        self, make_env: Callable[[], Any], workers: int, address: str | None = None
    ) -> None:
        self.make_env = make_env
        self.workers = workers
        self.key = uuid.uuid4().hex
        self._ray, self.owns_ray = start_ray(workers, address, RAY_ENV)
        if not self.owns_ray:
            warnings.warn(
                "Ray is already running in this process: its session is used as it is "
                f"(address {address!r} and the workers' MKL_CBWR={MKL_MODE} are not applied; "
                "episodes can then differ in the last bits between workers)",
                RuntimeWarning,
                stacklevel=2,
            )
        self._task = self._ray.remote(num_cpus=1, max_retries=3)(_play_chunk)

    def play(self, actor: Any, seed: int, episodes: Sequence[int], steps: int) -> TensorDictBase:
        actor_ref = self._ray.put(actor)
        refs = [
            self._task.remote(self.make_env, self.key, actor_ref, seed, chunk, steps)
            for chunk in split_episodes(episodes, self.workers)
        ]
        return torch.cat(self._ray.get(refs))

    def close(self) -> None:
        if self.owns_ray and self._ray.is_initialized():
            self._ray.shutdown()


def check_pool(workers: object, backend: object, address: str | None, reach: bool = False) -> None:
    """A ``ValueError`` naming a bad ``--workers``, ``--backend`` or ``--ray-address``; with
    ``reach`` also an address no Ray cluster answers at (an ``ImportError`` when Ray is asked
    for and missing)."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    if address is not None and backend != "ray":
        raise ValueError(f"--ray-address {address!r} needs --backend ray (got {backend!r})")
    if reach and backend == "ray":
        import_ray()  # the extra's name before anything runs
    if reach and address is not None:
        check_ray_address(address)


def make_pool(
    make_env: Callable[[], Any],
    workers: int = 1,
    backend: Backend = "local",
    address: str | None = None,
) -> InProcessPool | LocalProcessPool | RayPool:
    """The pool for ``backend`` (see the module docstring); ``address`` only with ``ray``."""
    check_pool(workers, backend, address, reach=True)
    if backend == "ray":
        return RayPool(make_env, workers, address)
    return InProcessPool(make_env) if workers == 1 else LocalProcessPool(make_env, workers)
