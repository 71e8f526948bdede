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
    assert {"uncertainty.ipynb", "experiment_design.ipynb", "online_calibration.ipynb"} <= names, names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_without_outputs(path):
    """Notebooks are committed clean (no outputs, no execution counts) so diffs show only the source."""
    nb = nbformat.read(path, as_version=4)
    dirty = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and (c.outputs or c.execution_count)]
    assert not dirty, f"{path.name}: cells {dirty} have outputs; clear them before committing"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    if path.stem == "real_robot" and not (Path(__file__).resolve().parents[2] / "shared" / "data" / "ur10").exists():
        pytest.skip("real_robot.ipynb reads the UR10 files of ../shared (absent)")
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


# ----------------------------------------------------------------- online_stream.py
SCRIPT = NB_DIR / "online_stream.py"


@pytest.fixture(scope="module")
def stream_csv(tmp_path_factory):
    from estcal.estimate.testproblems import drifting_problem
    from estcal.io.dataset import write_dataset

    sim = drifting_problem("puma560", n_poses=40, seed=11, drift={"theta_2": 5e-4}, sigma_p=1e-4, sigma_r=1e-4)
    path = tmp_path_factory.mktemp("stream") / "stream.csv"
    write_dataset(path, sim.problem.terms[0].data)
    return path, sim.free


def _script(args, stdin_path=None, text=None):
    import subprocess

    fh = open(stdin_path) if stdin_path else None
    try:
        return subprocess.run([sys.executable, str(SCRIPT), *args], stdin=fh, input=text, capture_output=True,
                              text=True, timeout=120)
    finally:
        if fh:
            fh.close()


def test_online_stream_matches_estcal_online(stream_csv, tmp_path):
    """Piped row by row through stdin, the script ends where `estcal online` ends on the same file."""
    import json

    from typer.testing import CliRunner

    from estcal.cli.main import app

    path, free = stream_csv
    common = ["--noise-pos-mm", "0.1", "--noise-rot-mrad", "0.1", "--free", ",".join(free), "--q-mm", "0.02",
              "--q-params", "theta_2"]
    r = _script(["puma560", "-", *common, "--show", "theta_2", "--json", str(tmp_path / "script.json")],
                stdin_path=path)
    assert r.returncode == 0, r.stderr
    rows = [ln for ln in r.stdout.splitlines() if ln.startswith("row ")]
    assert len(rows) == 40 and "theta_2 = " in rows[-1] and " ± " in rows[-1]
    # the same options as estcal online's (docs/conventions.md, "Units on the command line")
    res = CliRunner().invoke(app, ["online", str(path), "--robot", "puma560", *common, "--json",
                                   str(tmp_path / "cli.json")])
    assert res.exit_code == 0, res.output
    a = json.loads((tmp_path / "script.json").read_text())["parameters"]
    b = json.loads((tmp_path / "cli.json").read_text())["parameters"]
    assert set(a) == set(b) == set(free)
    for n in free:
        assert abs(a[n]["estimate"] - b[n]["estimate"]) <= 1e-6 * b[n]["std"], n
        assert a[n]["std"] == pytest.approx(b[n]["std"], rel=1e-9)
    # a real calibration, not the nominal echoed back
    assert max(abs(v["estimate"] - v["nominal"]) / v["std"] for v in a.values()) > 10


def _main(args, capsys, monkeypatch, text=None):
    """Run the script's main() in this process (fast); returns (exit code, stdout, stderr)."""
    import importlib.util
    import io

    spec = importlib.util.spec_from_file_location("online_stream", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    if text is not None:
        monkeypatch.setattr(sys, "stdin", io.StringIO(text))
    try:
        code = mod.main(args)
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_online_stream_malformed_rows(stream_csv, tmp_path, capsys, monkeypatch):
    path, free = stream_csv
    lines = path.read_text().splitlines()
    bad = lines[:3] + [lines[3].replace(lines[3].split(",")[7], "abc", 1), "1,2,3"] + lines[4:8]
    (tmp_path / "bad.csv").write_text("\n".join(bad) + "\n")
    args = ["puma560", str(tmp_path / "bad.csv"), "--free", "theta_*", "--noise-rot-mrad", "0.1"]
    code, out, err = _main(args, capsys, monkeypatch)
    assert code == 0, err
    assert "line 4, column 'y': value is 'abc', not a finite number" in err  # the dataset loader's messages
    assert "line 5: 3 fields but the header has 14" in err
    assert "(2 skipped)" in out and len([ln for ln in out.splitlines() if ln.startswith("row ")]) == 6
    code, out, err = _main(args + ["--strict"], capsys, monkeypatch)
    assert code == 2 and "line 4, column 'y'" in err
    code, out, err = _main(["puma560", "-"], capsys, monkeypatch, text="j1,j2,j3,x,y,z\n")
    assert code == 2 and "missing joint column(s) ['j4', 'j5', 'j6']" in err
    code, out, err = _main(["puma560", "-"], capsys, monkeypatch, text="")
    assert code == 2 and "empty input" in err
    code, out, err = _main(["puma560", "-", "--show", "nope"], capsys, monkeypatch, text="")
    assert code == 2 and "--show" in err
    # a bad robot name exits 2 with the loader's message, no traceback, in a real process too
    r = _script(["no_such_robot", "-"], text="")
    assert r.returncode == 2 and "no_such_robot" in r.stderr and "Traceback" not in r.stderr
