"""What `estcal diagnose` (error budget included) and reading a URDF import: none of the libraries whose
import alone cost a large share of a small command (docs/benchmarks.md, "Everyday commands") —
scikit-learn (with pandas), scipy.stats, yourdfpy with trimesh. The numbers they were imported for come
from scipy.special (χ² and F tails, χ² quantiles), estcal's own ARD GP fit (scikit-learn's computation,
tests/test_residual_budget.py) and estcal's URDF reader (yourdfpy as the oracle, tests/test_urdf_reader.py)."""
from __future__ import annotations

import subprocess
import sys

HEAVY = ("sklearn", "pandas", "scipy.stats", "yourdfpy", "trimesh")
URDF = ('<?xml version="1.0"?><robot name="r"><link name="base"/><link name="l1"/><link name="l2"/>'
        '<joint name="a" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.1" rpy="0 0.2 0"/>'
        '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
        '<joint name="b" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.3 0 0"/>'
        '<axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')


def test_diagnose_with_its_budget_imports_no_heavy_library(tmp_path):
    data, urdf = tmp_path / "p30.csv", tmp_path / "r.urdf"
    urdf.write_text(URDF)
    sim = subprocess.run([sys.executable, "-m", "estcal.cli.main", "simulate", "--robot", "puma560", "--n", "30",
                          "--measure", "position", "--noise-pos-mm", "0.1", "--seed", "3", "-o", str(data)],
                         capture_output=True, text=True)
    assert sim.returncode == 0, sim.stderr
    code = (f"import atexit, sys\n"
            f"atexit.register(lambda: print('HEAVY', [m for m in {HEAVY!r} if m in sys.modules]))\n"
            f"from estcal.kinematics.urdf import robot_from_urdf\n"
            f"assert robot_from_urdf({str(urdf)!r}).n_joints == 2\n"
            f"from estcal.cli.main import main\n"
            f"sys.argv = ['estcal', 'diagnose', {str(data)!r}, '--robot', 'puma560']\n"
            f"main()\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "Expected error at new postures" in p.stdout and "error budget" in p.stdout, p.stdout[-2000:]  # budget ran
    assert p.stdout.strip().splitlines()[-1] == "HEAVY []", p.stdout[-500:]
