"""``python train.py <experiment> [--options]``: the command line of
:mod:`hireps_torch.cli` (installed as ``hireps-train``), for ``make train`` and runs from the
repository. ``python train.py --help`` lists the experiments."""

from hireps_torch.cli import entry, main, parse

__all__ = ["main", "parse"]

if __name__ == "__main__":
    entry()
