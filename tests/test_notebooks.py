"""The notebooks execute top to bottom (on a tiny sweep when no benchmark results exist)."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]


def executed_outputs(name: str, timeout: int) -> list[dict]:
    """Run notebooks/<name> from the repository root; return every code cell's outputs."""
    nb = nbformat.read(ROOT / "notebooks" / name, as_version=4)
    NotebookClient(
        nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    ).execute()
    return [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]


@pytest.mark.slow
@pytest.mark.parametrize(
    "name,timeout,needs",
    [("pendulum_ablations.ipynb", 300, None), ("hockey.ipynb", 1500, "pybullet")],
)
def test_notebook_executes_and_shows_figures(name, timeout, needs):
    if needs:
        pytest.importorskip(needs)
    outputs = executed_outputs(name, timeout)
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert any("image/png" in o.get("data", {}) for o in outputs)
