"""Smoke runs (``--quick``) of the identification experiments, with their headline checks."""
from __future__ import annotations

import json

import pytest
from conftest import load_experiment as _load


def test_stanford_convergence_quick(tmp_path):
    out = _load("stanford_convergence").main(["--quick", "--json", str(tmp_path / "s.json")])
    d = json.loads((tmp_path / "s.json").read_text())
    assert set(d) == {"config", "trials", "summary"}
    for tr in out["trials"]:
        assert tr["initial_rmse_mm"] == pytest.approx(600.0, rel=1e-3)
        assert tr["n_free"] == 34  # GECARO Table 2, location measure
    # GECARO: about 5 iterations from 60 cm of initial end-point error
    for est in ("gauss-newton", "lm"):
        assert out["summary"][est]["success_rate"] == 1.0
        assert out["summary"][est]["max_iterations"] <= 12


def test_puma_case_study_quick(tmp_path):
    out = _load("puma_case_study").main(["--quick", "--json", str(tmp_path / "p.json")])
    assert json.loads((tmp_path / "p.json").read_text())["fit"]["converged"]
    assert out["fit"]["n_parameters"] == 30  # the textbook's 30-parameter model, full pose
    s = out["summary"]
    assert s["nominal_rms_in"] > 0.5 and s["nominal_rms_deg"] > 1.0  # Table 6.13 nominal: ~1 in, ~3.5 deg
    # calibrated at the noise floor: below one measurement's 3-D noise, far below the book's 0.02-0.04 in
    assert s["calibrated_rms_in"] < s["measurement_noise_3d"]["position_in"]
    assert s["calibrated_rms_deg"] < s["measurement_noise_3d"]["orientation_deg"]
    assert out["parameter_errors"]["max_z"] < 5


def test_textbook_5r1p_quick(tmp_path):
    out = _load("textbook_5r1p").main(["--quick", "--json", str(tmp_path / "t.json")])
    assert set(out["tables"]) == {"4.2", "4.5", "4.6", "4.7"}
    c = out["checks"]
    assert c["4.2 angle error grows as the tool distance shrinks"]
    assert c["4.5 noise-free best, largest measurement noise worst (angle)"]
    # the book's strategy ranking S4 > S3 > S2 >> S1 at m = 36 (Table 4.6), in κ and in δrms angle,
    # with S4 < S3 resolved beyond 2 standard errors (100 repetitions per cell in --quick)
    assert c["4.6 kappa at m=36: S4 < S3 < S2, S1 > 5 S2 (book S4 > S3 > S2 >> S1)"]
    assert c["4.6 angle error at m=36: S4 < S3 < S2 < S1 (book ranking)"]
    assert c["4.6 S4 < S3 angle at m=36 resolved (> 2 standard errors)"]
    assert out["separation_46"]["S4<S3"] > 2
    assert all(out["kendall_tau"][t]["angle"] > 0 for t in ("4.2", "4.5", "4.6", "4.7"))
    assert c["4.7 S4: kappa grows as the joint range shrinks (F < E)"]


def test_tiago_mocap_quick(tiago_dir, tmp_path):
    out = _load("tiago_mocap").main(["--quick", "--data", str(tiago_dir), "--json", str(tmp_path / "t.json")])
    runs = {(r["points"], r["level"], r["criterion"]): r for r in out["runs"]}
    reg = runs[(1, "registration", "structural")]
    assert reg["train_rmse_mm"] == pytest.approx(3.37, abs=0.005)
    assert reg["validation_rmse_mm"] == pytest.approx(4.87, abs=0.005)
    jo = runs[(1, "joint_offset", "structural")]
    assert jo["n_parameters"] == 14  # FIGAROH's joint_offset count
    assert jo["train_rmse_mm"] == pytest.approx(2.88, abs=0.01)
    # docs/calibration.md, "TIAGo motion capture": the procedure fixed on 11-30 only (structural QR set + ridge, τ by leave-one-pose-out)
    ridge = runs[(1, "full", "structural+ridge")]
    g = ridge["regularization"]
    assert g["loo_rmse_mm"] < g["loo_rmse_unregularised_mm"]  # the training-only evidence for it
    assert ridge["n_parameters"] == runs[(1, "full", "structural")]["n_parameters"]
    t = out["target_full_1pt"]
    assert t["met"] == (t["validation_rmse_mm"] <= 3.07)  # reported as measured, met or not
    # documented in docs/calibration.md: the AIC-pruned set scores below FIGAROH's 3.07 on 11-26
    assert runs[(1, "full", "aic")]["validation_rmse_mm"] <= 3.07
