"""Packaged robot files (``estcal/robots/data/*.yaml``), one per built-in robot.

They are written in the units of their source tables (inches/degrees for the
textbook robots) and load with :func:`estcal.io.robotfile.load_robot` to the
same parameters and forward kinematics as :mod:`estcal.kinematics.robots`.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["DATA_DIR", "robot_file", "available"]

DATA_DIR = Path(__file__).resolve().parent / "data"


def available() -> list[str]:
    """Names of the packaged robot files."""
    return sorted(p.stem for p in DATA_DIR.glob("*.yaml"))


def robot_file(name: str) -> Path:
    """Path of the packaged robot file ``name`` (e.g. ``"puma560"``)."""
    p = DATA_DIR / f"{name}.yaml"
    if not p.exists():
        raise FileNotFoundError(f"no packaged robot file {name!r}; available: {available()}")
    return p
