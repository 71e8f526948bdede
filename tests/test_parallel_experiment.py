"""Smoke test of experiments/daney_left_hand.py --quick (JSON keys, sane factors)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def test_daney_left_hand_quick(tmp_path):
    out = tmp_path / "d.json"
    png = tmp_path / "d.png"
    r = subprocess.run([sys.executable, str(ROOT / "experiments" / "daney_left_hand.py"), "--quick",
                        "--json", str(out), "--png", str(png)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "3.2 base point" in r.stdout
    d = json.loads(out.read_text())
    m2, m3 = d["method_3_2"], d["method_3_3"]
    assert {"N", "factor_base", "factor_platform"} <= set(m2)
    assert {"N1", "N2", "factor_a", "factor_b"} <= set(m3)
    assert len(m2["N"]) == len(m2["factor_base"]) == len(m2["factor_platform"])
    assert len(m3["N1"]) == len(m3["factor_b"]) and len(m3["N2"]) == len(m3["factor_a"])
    assert d["config"]["noise"] == {"err_p_cm": 0.01, "err_a_deg": 0.01, "err_l_cm": 0.01, "distribution": "uniform"}
    # errors are of the order of the noise, decrease with N, and the base point is worse (paper §6)
    fb, fp = np.array(m2["factor_base"]), np.array(m2["factor_platform"])
    assert np.all(fb > fp) and np.all(fp > 0.1) and np.all(np.diff(fb) < 0)
    assert np.all(np.diff(m3["factor_b"]) < 0) and np.all(np.diff(m3["factor_a"]) < 0)
    assert png.stat().st_size > 1000
