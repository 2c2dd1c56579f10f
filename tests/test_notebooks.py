"""The notebooks run top to bottom (small sizes) without an error or a failed assert."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

NB_DIR = Path(__file__).resolve().parent.parent / "notebooks"
NAMES = [
    "01_tour_of_terms.ipynb",
    "02_fitting.ipynb",
    "03_speed_vs_error.ipynb",
    "04_transparency_and_shadows.ipynb",
    "05_mirrors_and_glass.ipynb",
    "06_photographs.ipynb",
    "07_textures.ipynb",
]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_executes(name, tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    path = NB_DIR / name
    assert path.exists(), f"{path} missing: run python notebooks/build.py"
    nb = nbformat.read(path, as_version=4)
    # The saved notebook is the one built from notebooks/build.py (sources agree).
    sys.path.insert(0, str(NB_DIR))
    try:
        import build
    finally:
        sys.path.pop(0)
    assert [c.source for c in nb.cells] == [c.source for c in build.build(name, build.NOTEBOOKS[name]).cells]
    # Saved with outputs, and none of them an error.
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert all(c.execution_count for c in code) and sum(len(c.outputs) for c in code) >= len(code) - 1, (
        "saved unexecuted or without outputs: run python notebooks/build.py"
    )
    assert any("image/png" in o.get("data", {}) for c in code for o in c.outputs), "saved without its plots"
    assert not any(o.output_type == "error" for c in code for o in c.outputs)
    monkeypatch.setenv("DIFFSHADE_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(NB_DIR.parent), os.environ.get("PYTHONPATH", "")]))
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()  # raises CellExecutionError naming the cell on any error or failed assert
