"""The notebooks of docs/notebooks/ run top to bottom (quick mode) and their asserts hold.

Each notebook is executed by nbclient in a fresh temporary directory (with
``online_stream.py`` copied next to it, as in the repository) with the
``python3`` kernel of the current interpreter; ``ESTCAL_NOTEBOOK_QUICK=1``
makes the notebooks choose small sizes. A failing ``assert`` in a cell — the
notebooks check their claims of agreement against independent computations —
fails the test with the cell's traceback.
"""
from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NB_DIR = Path(__file__).resolve().parents[1] / "docs" / "notebooks"
NOTEBOOKS = sorted(NB_DIR.glob("*.ipynb"))


def test_notebooks_found():
    names = {p.name for p in NOTEBOOKS}
    assert {"uncertainty.ipynb", "experiment_design.ipynb"} <= names, names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_without_outputs(path):
    """Notebooks are committed clean (no outputs, no execution counts) so diffs show only the source."""
    nb = nbformat.read(path, as_version=4)
    dirty = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and (c.outputs or c.execution_count)]
    assert not dirty, f"{path.name}: cells {dirty} have outputs; clear them before committing"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("ESTCAL_NOTEBOOK_QUICK", "1")
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    for f in NB_DIR.iterdir():
        if f.suffix in (".ipynb", ".py"):
            shutil.copy(f, tmp_path / f.name)
    nb = nbformat.read(tmp_path / path.name, as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell("import sys; print(sys.executable)"))  # which interpreter ran it
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    t0 = time.perf_counter()
    client.execute()
    dt = time.perf_counter() - t0
    print(f"{path.name}: {dt:.1f} s in quick mode")
    # the kernel must be this venv's interpreter (jupyter_client maps the spec's "python" to sys.executable)
    ran = nb.cells.pop().outputs[0]["text"].strip()
    assert Path(ran).resolve() == Path(sys.executable).resolve(), (ran, sys.executable)
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    images = sum(1 for c in nb.cells if c.cell_type == "code" for o in c.outputs
                 if o.output_type == "display_data" and "image/png" in o.get("data", {}))
    assert images >= 2, f"{path.name}: expected inline plots, got {images}"
