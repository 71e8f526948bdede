"""Smoke tests: every design experiment runs in --quick mode and writes its documented JSON keys."""
from __future__ import annotations

import json

import pytest
from conftest import load_experiment


def _run(name, tmp_path, *extra):
    out = tmp_path / f"{name}.json"
    load_experiment(name).main(["--quick", "--json", str(out), *extra])
    return json.loads(out.read_text())


def test_klimchik_2link_quick(tmp_path):
    d = _run("klimchik_2link", tmp_path)
    assert set(d["table1"]) == {"0", "30", "60", "90", "120", "150", "180"}
    for q20, v in d["table1"].items():  # numerical optimum = closed form (20) (limits at 0°, 180°)
        assert v == pytest.approx(d["table1_detail"][q20]["closed_form"], rel=2e-3)
    assert d["fig2"]["c"] == pytest.approx(0.8192, abs=1e-3) and d["fig2"]["b"] == pytest.approx(1.0, abs=1e-9)
    assert d["fig3"]["c"] < d["fig3"]["b"] < d["fig3"]["a"]
    assert d["fig3_optimum"]["rho0_over_sigma"] <= d["fig3"]["c"] + 1e-9
    assert len(d["fig3_optimum"]["plan_deg"]) == 3


def test_5r1p_strategies_quick(tmp_path):
    d = _run("design_5r1p_strategies", tmp_path)
    assert d["rank"] == 21
    assert d["ranking_46"] == ["S4", "S3", "S2", "S1"]  # the book's ranking by κ at m = 36 (Table 4.6)


def test_kr270_quick(tmp_path):
    d = _run("kr270_design", tmp_path)
    for k in ("3", "4", "3x4", "4x3", "12"):
        row = d["table2"][k]
        assert row["proposed_um"] < row["random_mean_um"]
    assert d["table2"]["3x4"]["proposed_um"] == pytest.approx(d["table2"]["3"]["proposed_um"] / 2, rel=1e-9)


def test_active_calibration_quick(tmp_path):
    d = _run("active_calibration", tmp_path, "--png", str(tmp_path / "a.png"))
    assert (tmp_path / "a.png").exists()
    assert set(d["curves"]) == {"active", "random", "plan"}
    assert d["curves"]["active"]["predicted_mm"][-1] < d["curves"]["active"]["predicted_mm"][0]
