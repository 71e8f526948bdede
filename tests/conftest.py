"""Shared fixtures: the location of ../shared, skip helpers for the TIAGo and TALOS data, and a loader of the
experiment scripts."""
from __future__ import annotations

import os
from pathlib import Path

# BLAS single-threaded in the test processes, as the CLI runs it (estcal.cli.main): `pytest -n 2` already uses
# both cores, and OpenBLAS threads spinning on the suite's small matrices made a clean checkout's run ~30 % slower
# in CPU (8m10 against 6m11 of user time). Set before numpy is imported; a value the caller set is kept.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
TIAGO_DIR = SHARED / "data" / "tiago"


def load_experiment(name: str, folder: str = "experiments"):
    """The module ``<folder>/<name>.py`` (experiments and benchmarks are not packages: loaded from the file, run
    as an import). It is registered in ``sys.modules`` under ``name`` while it runs, as an import would be: a
    dataclass of the script resolves its annotations through its module."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location(name, REPO / folder / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def tiago_dir() -> Path:
    if not (TIAGO_DIR / "tiago_48_schunk.urdf").exists():
        pytest.skip(f"TIAGo data not found at {TIAGO_DIR} (it lives in ../shared next to the repository)")
    return TIAGO_DIR


@pytest.fixture
def talos_dir() -> Path:
    folder = SHARED / "data" / "talos"
    if not (folder / "talos_reduced.urdf").exists():
        pytest.skip(f"TALOS data not found at {folder} (it lives in ../shared next to the repository)")
    return folder
