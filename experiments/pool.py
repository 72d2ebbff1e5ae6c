"""The one pool of worker processes on this machine, for a sweep's runs and hockey's episodes::

    with LocalPool(workers=2, pin=True, runs=True) as pool:  # each worker on its own cores
        future = pool.submit(fn, *args)                      # a concurrent.futures.Future

A ``concurrent.futures.ProcessPoolExecutor`` (spawned processes, each started once and taking
calls one after the other) whose workers start with SIGINT blocked (a Ctrl-C reaches the
process that owns the pool, which stops them) and in MKL's reproducible mode
(``MKL_CBWR=COMPATIBLE``, :func:`mkl_environment`, as ``hireps-train`` runs; why: :mod:`.workers`).

With ``runs`` the calls are runs (a sweep's): a worker then takes SIGINT / SIGTERM as a run
does (stop at the next iteration boundary with a checkpoint), and :meth:`LocalPool.stop` or the
end of the process that owns the pool (even by kill -9) asks the run in hand for the same stop;
a worker that stopped a run ends once idle, and one still busy :data:`STOP_SECONDS` after a stop
ends then. Without ``runs`` (episodes) a worker whose owner died ends at once.

A worker that dies breaks the pool (``BrokenProcessPool`` for every call in flight): its owner
calls :meth:`LocalPool.restart` and submits those calls again.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, TypeVar

from hireps_torch.experiments.checkpoint import record_early_stops, request_stop, stop_requested
from hireps_torch.rollout import workers_ignore_sigint

__all__ = ["MKL_MODE", "STOP_SECONDS", "LocalPool", "core_sets", "mkl_environment"]

R = TypeVar("R")
MKL_MODE = "COMPATIBLE"


@contextlib.contextmanager
def mkl_environment() -> Iterator[None]:
    """``MKL_CBWR=COMPATIBLE`` in ``os.environ`` inside the block (unless the user chose a
    mode), for processes started there; restored afterwards."""
    chosen = "MKL_CBWR" in os.environ
    if not chosen:
        os.environ["MKL_CBWR"] = MKL_MODE
    try:
        yield
    finally:
        if not chosen:
            os.environ.pop("MKL_CBWR", None)


STOP_SECONDS = 60.0
"""A run asked to stop ends within this (it finishes its iteration), or its worker ends."""


def core_sets(workers: int) -> list[set[int]]:
    """Disjoint sets of this process's cores, one per worker (an even share each), or none for
    one worker or fewer cores than workers (each then sees every core)."""
    if workers < 2 or not hasattr(os, "sched_getaffinity"):
        return []
    cores = sorted(os.sched_getaffinity(0))
    share = len(cores) // workers
    return [set(cores[w * share : (w + 1) * share]) for w in range(workers)] if share else []


_BUSY = threading.Event()  # in a worker: a call is running
_HALTED = threading.Event()  # in a worker: a call ended by a stop (a signal, the pool's)
_STOP: Any = None  # in a worker: the pool's stop byte


def _start_worker(parent: int, stop: Any, cores: Any, runs: bool) -> None:
    """A worker's start: its cores (one set from the ``cores`` queue), for ``runs`` the signal
    handlers, and the thread that watches the pool's ``stop`` byte and the owner ``parent``."""
    global _STOP
    _STOP = stop
    mine = None if cores is None else cores.get()
    if mine:
        os.sched_setaffinity(0, mine)
    if runs:
        record_early_stops()
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # one held since start lands

    def watch() -> None:
        deadline = None
        while True:
            orphaned = os.getppid() != parent
            if orphaned and not runs:
                os._exit(1)
            if (stop.value or orphaned) and deadline is None:
                request_stop(
                    "the pool's stop" if stop.value else "the end of the process that owns it"
                )
                deadline = time.monotonic() + STOP_SECONDS
            # an orphan ends once its run stopped (nobody takes results); a worker still busy
            # past the deadline ends then; an idle one waits for the executor's shutdown
            if orphaned and not _BUSY.is_set() or deadline and time.monotonic() > deadline:
                os._exit(0 if not _BUSY.is_set() else 1)
            time.sleep(0.1)

    threading.Thread(target=watch, daemon=True).start()


def _call(fn: Callable[..., R], *args: Any) -> R:
    """``fn(*args)``, unless a stop came before (the calls queued behind a stopped one)."""
    _BUSY.set()
    try:
        if _HALTED.is_set() or stop_requested() or (_STOP is not None and _STOP.value):
            raise KeyboardInterrupt("the pool stopped before this call started")
        return fn(*args)
    except KeyboardInterrupt as stopped:  # RunInterrupted: the owner gets its message
        _HALTED.set()
        raise KeyboardInterrupt(str(stopped)) from None
    finally:
        _BUSY.clear()


class LocalPool:
    """``workers`` spawned processes on this machine (see the module docstring); with ``pin``,
    each held to cores of its own (:func:`core_sets`) where there are enough."""

    def __init__(self, workers: int, *, pin: bool = False, runs: bool = False) -> None:
        self.workers, self.pin, self.runs = workers, pin, runs
        self._ctx = multiprocessing.get_context("spawn")
        self._stop: Any = None
        self._executor: ProcessPoolExecutor | None = None

    def __enter__(self) -> LocalPool:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()

    def submit(self, fn: Callable[..., R], *args: Any) -> Future[R]:
        """``fn(*args)`` in a worker (``fn`` and ``args`` picklable)."""
        if self._executor is None:
            self._stop = self._ctx.RawValue("b", 0)  # a plain shared byte: nothing waits on it
            sets = core_sets(self.workers) if self.pin else []
            cores = None
            if sets:
                cores = self._ctx.SimpleQueue()
                for s in sets:
                    cores.put(s)
            self._executor = ProcessPoolExecutor(
                self.workers,
                mp_context=self._ctx,
                initializer=_start_worker,
                initargs=(os.getpid(), self._stop, cores, self.runs),
            )
        # workers spawn during submit; one starts MKL while it imports torch, before any
        # initializer could run: it gets the reproducible mode from its environment
        with mkl_environment(), workers_ignore_sigint():
            return self._executor.submit(_call, fn, *args)

    def stop(self) -> None:
        """Ask every worker's run in hand to stop at its next iteration boundary."""
        if self._stop is not None:
            self._stop.value = 1

    def close(self) -> None:
        """Wait for the calls in hand, drop those not started, end the workers."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    restart = close
    """After a worker died (``BrokenProcessPool``): the next :meth:`submit` starts new ones."""
