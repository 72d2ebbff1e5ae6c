"""Run directories written by earlier versions of this code: what they mean now, and why
one cannot be resumed. The one place that knows their formats."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hireps_torch.checks import NO_MEMBER_DIMENSION

__all__ = [
    "ABSENT_MEANS",
    "EARLIER_POPULATION",
    "EARLIER_RUN",
    "READABLE_FORMATS",
    "current_config",
    "earlier_version_note",
    "no_config_note",
]

READABLE_FORMATS = (2, 3)
"""``checkpoint.pt`` formats this version reads: 3 holds each member's ``metrics.csv`` text,
2 its rows as dicts."""

ABSENT_MEANS = {
    "device": "cpu",
    "final_eval_episodes": None,
    "exploration_floor_end": None,
    "option_goal_offset": False,
    "epsilon_end": None,
    "restart_probability": None,
    "versatility_samples": 500,  # measuring changes no update
    "entropy_floor": 0.5,  # read by hireps-versatile only, which came with it
}
"""Options added after the first run directories, with the value that reproduces the older
runs: ``config.json`` leaves an option out at that value, so old and new directories compare
equal, and an old one is resumed with it (even where the default has changed since)."""


def current_config(saved: Mapping[str, Any]) -> dict[str, Any]:
    """A ``config.json`` (or a checkpoint's config) as this version writes it: the experiment
    by its command-line name (``ball_on_beam`` -> ``ball-on-beam``, as versions before
    2026-12-08 wrote it)."""
    out = dict(saved)
    if isinstance(out.get("experiment"), str):
        out["experiment"] = out["experiment"].replace("_", "-")
    return out


EARLIER_RUN = "it cannot be resumed; run it again with another --run-dir"
EARLIER_POPULATION = (
    "a population that an earlier version of this code ran, which wrote no checkpoint: "
    + EARLIER_RUN
)


def earlier_version_note(exc: Exception) -> str:
    """``"; an earlier version of this code wrote it: ..."`` for a state refused for having no
    member dimension (an ordinary hockey run before populations), else ``""``."""
    if NO_MEMBER_DIMENSION not in str(exc):
        return ""
    return f"; an earlier version of this code wrote it: {EARLIER_RUN}"


def no_config_note(run_dir: Path) -> str:
    """Why ``run_dir`` has no config.json, where that can be told: it does not exist, it is not
    a directory, it holds runs of their own (``seed<s>/`` with checkpoints: a sweep's?) or an
    earlier version's population (``seed<s>/`` without); else ``""``."""
    if not run_dir.exists():
        return " It does not exist."
    if not run_dir.is_dir():
        return " It is not a directory."
    if any(run_dir.glob("seed*/checkpoint.pt")):
        return " Its seed<s>/ directories are runs of their own (a sweep's?): resume each of them."
    if any(run_dir.glob("seed*/config.json")):
        return f" If its seed<s>/ directories are the members of {EARLIER_POPULATION}."
    return ""
