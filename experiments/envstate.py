"""The running state of a run's batched environments, for checkpoints that continue exactly
(TorchRL's collectors do not save it). Hockey needs none (episodes draw from (seed, episode),
see :mod:`hireps_torch.experiments.workers`); with worker processes the state is not saved
and a resumed run warns that it is not bit-identical.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import torch

__all__ = ["BatchedTaskState"]


def _tensors(obj: Any) -> dict[str, torch.Tensor]:
    return {k: v for k, v in vars(obj).items() if isinstance(v, torch.Tensor)}


def _check_fits(saved: Mapping[str, Any], now: Mapping[str, torch.Tensor]) -> None:
    if set(saved) != set(now) or any(saved[k].shape != now[k].shape for k in now):
        shapes = {k: tuple(v.shape) for k, v in saved.items()}
        raise ValueError(
            f"the checkpoint's environment state {shapes} does not fit this run's "
            f"{ {k: tuple(v.shape) for k, v in now.items()} }"
        )


class BatchedTaskState:
    """The tensors and start-state generators of a collector's ``MemberTasks``; with ``carry``
    (environments run on across iterations) also its carried observation."""

    def __init__(self, collector: Any, carry: bool) -> None:
        self.collector = collector
        self.carry = carry

    def _task(self) -> Any | None:
        env = getattr(self.collector, "env", None)  # None: it lives in worker processes
        return None if env is None else env.task

    def state_dict(self) -> dict[str, Any] | None:
        task = self._task()
        if task is None:
            return None
        return {
            "tensors": {k: v.clone() for k, v in _tensors(task).items()},
            "members": [
                {
                    "tensors": {k: v.clone() for k, v in _tensors(m).items()},
                    "gen": m.gen.get_state(),
                }
                for m in task.tasks
            ],
        }

    def load_state_dict(self, state: Mapping[str, Any] | None) -> None:
        task = self._task()
        if task is None or state is None:
            warnings.warn(
                "resuming with worker processes: the environment states are not restored, so the "
                "resumed run is not bit-identical to an uninterrupted one (resume with --workers 1 "
                "for that)",
                RuntimeWarning,
                stacklevel=2,
            )
            return
        _check_fits(state["tensors"], _tensors(task))
        if len(state["members"]) != len(task.tasks):
            raise ValueError(
                f"the checkpoint's environment holds {len(state['members'])} member(s), this "
                f"run's {len(task.tasks)}"
            )
        for saved, member in zip(state["members"], task.tasks, strict=True):
            _check_fits(saved["tensors"], _tensors(member))
            torch.Generator().set_state(saved["gen"])  # checked before anything is set
        for name, value in state["tensors"].items():
            setattr(task, name, value.clone())
        for saved, member in zip(state["members"], task.tasks, strict=True):
            for name, value in saved["tensors"].items():
                setattr(member, name, value.clone())
            member.gen.set_state(saved["gen"])
        if self.carry:  # the collector's next observations: the restored systems, as they are
            task.hold = True
            self.collector.reset()
