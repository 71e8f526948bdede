"""Shared fixtures: the location of ../shared and a skip helper for the TIAGo data."""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
TIAGO_DIR = SHARED / "data" / "tiago"


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
