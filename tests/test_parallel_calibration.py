"""Gough calibration through the shared estimator registry: residual Jacobians, every estimator
against LM, honest convergence, covariance (Monte Carlo), identifiability, result protocol, files."""
from __future__ import annotations

import ast
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from estcal.parallel import GoughData, GoughResiduals, load_gough, load_gough_data, simulate_gough_data
from estcal.parallel._rot import make_T
from estcal.parallel.daney import calibrate_leg_daney, generate_type2, generate_type3
from estcal.parallel.gough import left_hand
from estcal.workflows.gough import (
    ESTIMATORS,
    STEP_TOL_SIGMA,
    GoughProblem,
    calibrate_gough,
    identifiable_gough,
    save_gough_data,
)

LEG3 = ["a3_*", "b3_*", "drho_3"]
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def true_robot():
    return left_hand()


@pytest.fixture(scope="module")
def nominal(true_robot):
    rng = np.random.default_rng(0)
    return true_robot.with_theta(true_robot.theta + rng.normal(0, 1e-3, 42))


# ---------------------------------------------------------------- the measurement model
@pytest.mark.parametrize("residual", ["ik", "fk"])
def test_residual_jacobian_matches_finite_differences(true_robot, nominal, residual):
    """Analytic ∂e/∂θ of the whitened rows (IK: leg Jacobians; FK: implicit function theorem and
    the SO(3) right Jacobian) against central differences, all 42 parameters."""
    data = simulate_gough_data(true_robot, 6, 3, sigma_rho=1e-5, sigma_p=1e-5, sigma_r=1e-4)
    res = GoughResiduals(nominal, data, residual)
    th = nominal.theta
    J = res.whitened(th).J
    eps = 1e-7
    Jfd = np.stack([(res.whitened(th + eps * e, False).e - res.whitened(th - eps * e, False).e) / (2 * eps)
                    for e in np.eye(42)], -1)
    assert np.abs(J - Jfd).max() < 1e-6 * np.abs(Jfd).max()


def test_problem_adapter_rows(true_robot, nominal):
    """GoughProblem.evaluate: e = whitened residual, H = −∂e/∂θ (= ∂predicted/∂θ), σ = 1, one group
    of six rows per pose; with_free / with_values keep the model."""
    data = simulate_gough_data(true_robot, 5, 4)  # noise-free
    res = GoughResiduals(nominal, data, sigma_rho=1e-5)
    prob = GoughProblem(res, nominal.parameter_vector(42))
    rows = prob.evaluate()
    w = res.whitened(nominal.theta)
    np.testing.assert_array_equal(rows.e, w.e)
    np.testing.assert_array_equal(rows.H, -w.J)
    assert np.all(rows.sigma == 1) and rows.pose.tolist() == np.repeat(np.arange(5), 6).tolist()
    sub = prob.with_free(LEG3).with_values(true_robot.theta)
    assert sub.params.free_names == ["a3_x", "a3_y", "a3_z", "b3_x", "b3_y", "b3_z", "drho_3"]
    assert np.abs(sub.evaluate(jacobian=False).e).max() < 1e-9  # the truth reproduces the data


# ---------------------------------------------------------------- estimators of the shared registry
NOISE_FREE_CASES = [(m, r, {}) for m in ("lm", "gauss-newton", "iterated-lls", "scipy-lm", "gtsam")
                    for r in ("ik", "fk")] + [
    # iterated EKF: a small known noise level makes its 0.1 m prior negligible
    ("kalman", "ik", {"passes": 4, "sigma_rho": 1e-6}),
    ("kalman", "fk", {"passes": 4, "sigma_p": 1e-6, "sigma_r": 1e-5})]


@pytest.mark.parametrize("estimator,residual,kw", NOISE_FREE_CASES)
def test_noise_free_data_give_exact_parameters(true_robot, nominal, estimator, residual, kw):
    data = simulate_gough_data(true_robot, 40, 1)
    res = calibrate_gough(nominal, data, estimator=estimator, residual=residual, **kw)
    assert res.method == estimator and res.converged
    assert len(res.parameters) == 42 and res.fk_failures == 0
    tol = 1e-9 if estimator == "kalman" else 1e-10  # 1 nm on 0.1 m values; Kalman priors are diffuse, not flat
    np.testing.assert_allclose(res.theta, true_robot.theta, atol=tol)
    assert set(res.to_dict()["parameters"]["drho_3"]) == {"estimate", "std", "nominal"}


def test_registry_estimator_is_called_and_no_private_solver_remains(true_robot, nominal, monkeypatch):
    """calibrate_gough runs the estimator the shared registry returns (a spy registered under 'lm'
    sees the Gough problem), and the Gough code holds no solver of its own."""
    import estcal.estimate.registry as registry
    from estcal.estimate.lsq import calibrate_lsq

    calls = []

    def spy(problem, **kw):
        calls.append(problem)
        return calibrate_lsq(problem, method="lm", **kw)

    monkeypatch.setitem(registry.ESTIMATORS, "lm", spy)
    res = calibrate_gough(nominal, simulate_gough_data(true_robot, 20, 2))
    assert len(calls) == 1 and isinstance(calls[0], GoughProblem) and res.method == "lm"
    assert importlib.util.find_spec("estcal.parallel.calibration") is None
    solvers = {"scipy.optimize", "gtsam", "emcee", "filterpy"}
    for path in list((ROOT / "estcal" / "parallel").glob("*.py")) + [ROOT / "estcal" / "workflows" / "gough.py"]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                assert not any(m.split(".")[0] in solvers or m in solvers for m in mods), (path, mods)


def test_parallel_imports_nothing_above_its_layer():
    """estcal.parallel (layer 2) imports only estcal.base, estcal.kinematics and itself."""
    allowed = {"base", "kinematics", "parallel"}
    for path in (ROOT / "estcal" / "parallel").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("estcal"):
                assert node.module.split(".")[1] in allowed, (path.name, node.module)
            if isinstance(node, ast.Import):
                for a in node.names:
                    assert not a.name.startswith("estcal.") or a.name.split(".")[1] in allowed, (path.name, a.name)


@pytest.fixture(scope="module")
def leg3_case(true_robot):
    """Only leg 3 is wrong (so the leg-3 model is exact); known noise on readings and poses."""
    rng = np.random.default_rng(14)
    th = true_robot.theta.copy()
    th[14:21] += rng.normal(0, 1e-3, 7)
    data = simulate_gough_data(true_robot, 30, 6, sigma_rho=2e-5, sigma_p=2e-5, sigma_r=2e-4)
    return true_robot.with_theta(th), data


#: (estimator, options, reference LM options, tolerance on |θ − θ_LM|/σ_LM, rtol on σ, converged)
#: Estimators with a prior are compared with LM under the same prior (the same MAP). The Kalman
#: filters iterate their passes until converged (the UKF by iterated posterior linearisation); the
#: MCMC posterior mean carries Monte-Carlo error (~100 effective samples: s.e. 0.1 σ, relative s.e.
#: of σ ≈ 7 %).
AGREEMENT = [
    ("lm", {}, {}, 1e-12, 1e-12, True),
    ("gauss-newton", {}, {}, 1e-5, 1e-6, True),
    ("iterated-lls", {}, {}, 1e-5, 1e-6, True),
    ("scipy-lm", {}, {}, 1e-5, 1e-6, True),
    ("gtsam", {}, {}, 1e-5, 1e-6, True),
    ("kalman", {}, {"prior_std": 0.1}, 1e-4, 1e-5, True),
    ("isam2", {"prior_std": 1e-2}, {"prior_std": 1e-2}, 1e-6, 1e-6, True),
    ("ukf", {"prior_std": 3e-3}, {"prior_std": 3e-3}, 0.01, 0.01, True),
    ("mcmc", {"target_ess": 100, "max_steps": 300, "seed": 1}, {}, 0.3, 0.3, True),
]


@pytest.mark.parametrize("residual", ["ik", "fk"])
@pytest.mark.parametrize("estimator,kw,ref_kw,tol,rtol,converged", AGREEMENT, ids=[a[0] for a in AGREEMENT])
def test_every_estimator_agrees_with_lm(leg3_case, residual, estimator, kw, ref_kw, tol, rtol, converged):
    if estimator == "mcmc" and residual == "fk":
        pytest.skip("mcmc: every sample needs a forward-kinematics solve (90 s); IK covers the sampler")
    nominal, data = leg3_case
    lm = calibrate_gough(nominal, data, free=LEG3, residual=residual, **ref_kw)
    res = calibrate_gough(nominal, data, estimator=estimator, free=LEG3, residual=residual, **kw)
    assert res.method == estimator and res.names == lm.names
    assert np.abs((res.estimate - lm.estimate) / lm.std).max() < tol
    np.testing.assert_allclose(res.std, lm.std, rtol=rtol)
    assert res.converged is converged


def test_every_supported_estimator_is_compared_with_lm():
    assert sorted(ESTIMATORS) == sorted(a[0] for a in AGREEMENT)


def test_convergence_is_honest(leg3_case):
    """A single Kalman pass stops short of the optimum: reported as not converged, by the filter itself
    (one pass has no convergence test) and by the Gauss–Newton step, with the distance in σ and the
    remedy; the default passes converge. A chain stopped before its target ESS is not converged."""
    nominal, data = leg3_case
    one = calibrate_gough(nominal, data, estimator="kalman", free=LEG3, passes=1)
    assert not one.converged and not one.extra["convergence"]["estimator"]
    assert one.extra["convergence"]["max_step_sigma"] > STEP_TOL_SIGMA and "passes unset" in str(one)
    assert "NOT converged" in str(one)
    until = calibrate_gough(nominal, data, estimator="kalman", free=LEG3)
    assert until.converged and until.extra["convergence"]["max_step_sigma"] < STEP_TOL_SIGMA
    mc = calibrate_gough(nominal, data, estimator="mcmc", free=LEG3, target_ess=1e5, max_steps=200, seed=2)
    assert not mc.converged


def test_estimators_refused_with_a_reason(true_robot):
    data = simulate_gough_data(true_robot, 10, 2)
    with pytest.raises(ValueError, match="carry no time"):
        calibrate_gough(true_robot, data, estimator="gtsam-timevarying")
    with pytest.raises(ValueError, match="not available for Gough platforms; choose one of lm"):
        calibrate_gough(true_robot, data, estimator="no-such-estimator")
    with pytest.raises(ValueError, match="q > 0"):
        calibrate_gough(true_robot, data, estimator="kalman", q=1e-6)
    with pytest.raises(ValueError, match="has no option 'pases'"):
        calibrate_gough(true_robot, data, estimator="kalman", pases=3)
    with pytest.raises(ValueError, match="Model 36 keeps the leg offsets fixed"):
        calibrate_gough(true_robot, data, model=36, free=["drho_1"])
    with pytest.warns(DeprecationWarning, match="estimator="):
        assert calibrate_gough(true_robot, data, method="gauss-newton").method == "gauss-newton"


# ---------------------------------------------------------------- statistics
def test_model36_keeps_offsets(true_robot, nominal):
    th = nominal.theta.reshape(6, 7).copy()
    th[:, 6] = true_robot.drho  # Model 36: offsets known
    start = true_robot.with_theta(th.reshape(-1))
    res = calibrate_gough(start, simulate_gough_data(true_robot, 30, 2), model=36)
    assert len(res.parameters) == 36 and "drho_1" not in res.parameters
    np.testing.assert_allclose(res.theta, true_robot.theta, atol=1e-11)


def test_covariance_matches_monte_carlo(true_robot):
    """χ² check: with known σ, (θ̂−θ)ᵀ Σ⁻¹ (θ̂−θ) summed over R runs is χ²(R·p)."""
    rng = np.random.default_rng(4)
    T = simulate_gough_data(true_robot, 25, 5).T
    sig = 2e-5
    stat, p = 0.0, 7
    R = 150
    for _ in range(R):
        data = simulate_gough_data(true_robot, 0, rng, sigma_rho=sig, T=T)
        res = calibrate_gough(true_robot, data, free=LEG3)
        assert res.names == ["a3_x", "a3_y", "a3_z", "b3_x", "b3_y", "b3_z", "drho_3"]
        e = res.theta[14:21] - true_robot.theta[14:21]
        stat += e @ np.linalg.solve(res.covariance, e)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], R * p)
    assert lo < stat < hi


@pytest.mark.parametrize("residual,R", [("ik", 120), ("fk", 30)])
def test_covariance_with_pose_noise_matches_monte_carlo(true_robot, residual, R):
    """Pose-measurement noise correlates the six residuals of a pose; with the per-pose covariance
    whitening the χ² statistic is again χ²(R·p)."""
    rng = np.random.default_rng(15)
    T = simulate_gough_data(true_robot, 25, 16).T
    kw = dict(sigma_rho=1e-5, sigma_p=2e-5, sigma_r=2e-4)
    stat, p = 0.0, 7
    for _ in range(R):
        data = simulate_gough_data(true_robot, 0, rng, T=T, **kw)
        res = calibrate_gough(true_robot, data, free=LEG3, residual=residual)
        e = res.theta[14:21] - true_robot.theta[14:21]
        stat += e @ np.linalg.solve(res.covariance, e)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], R * p)
    assert lo < stat < hi, (stat / (R * p))


def test_rms_matches_noise(true_robot):
    sig = 2e-5
    data = simulate_gough_data(true_robot, 60, 13, sigma_rho=sig)
    res = calibrate_gough(true_robot, data, estimator="gauss-newton")
    # residual RMS after fitting p of m parameters: E[rms²] = σ²(m − p)/m
    m, p = 6 * len(data), 42
    rms = res.accuracy["train"]["after"]["rmse_mm"] * 1e-3
    assert rms**2 / (sig**2 * (m - p) / m) == pytest.approx(1.0, abs=4 * np.sqrt(2 / (m - p)))
    # started at the truth: the RMS before is that of the noise itself, E = σ²
    before = res.accuracy["train"]["before"]["rmse_mm"] * 1e-3
    assert before > rms and before**2 / sig**2 == pytest.approx(1.0, abs=4 * np.sqrt(2 / m))


# ---------------------------------------------------------------- identifiability, initial values
def test_identifiability_full_rank_and_translation_only_gauge(true_robot):
    ide = identifiable_gough(true_robot, n_poses=40, seed=1)
    assert ide["n_parameters"] == 42 and ide["n_identifiable"] == 42
    assert ide["no_effect"] == [] and ide["regrouped"] == []
    # pure translations: b_k and a_k only enter as (b_k - a_k): 3 combinations lost per leg
    T = simulate_gough_data(true_robot, 40, 1).T
    T[:, :3, :3] = np.eye(3)
    T = T[true_robot.in_workspace(T)]
    data = simulate_gough_data(true_robot, 0, 0, T=T)
    ide = identifiable_gough(true_robot, data)
    assert ide["n_identifiable"] == 24
    for g in ide["regrouped"]:
        (other, coef), = g["relation"].items()
        k, c = g["parameter"][1], g["parameter"][-1]
        assert {g["parameter"][0], other[0]} == {"a", "b"} and other[1] == k and other[-1] == c
        assert coef == pytest.approx(-1.0, abs=1e-9)
    # independent check: the rank by SVD of the unit-norm columns, and each regrouping a_j = β a_k
    # reproduces the dependent column
    J = GoughResiduals(true_robot, data).whitened(true_robot.theta).J
    names = true_robot.parameter_vector(42).names
    Js = J / np.linalg.norm(J, axis=0)
    sv = np.linalg.svd(Js, compute_uv=False)
    assert int(np.sum(sv > 1e-8 * sv[0])) == 24 and ide["no_effect"] == []
    for g in ide["regrouped"]:
        (other, coef), = g["relation"].items()
        a, b = J[:, names.index(g["parameter"])], J[:, names.index(other)]
        np.testing.assert_allclose(a, coef * b, atol=1e-9 * np.abs(a).max())
    # calibration keeps the regrouped parameters at their initial values (std None)
    res = calibrate_gough(true_robot, data)
    assert len(res.names) == 24 and sum(v["std"] is None for v in res.parameters.values()) == 18
    # Model 36 drops the offsets from the count
    assert identifiable_gough(true_robot, n_poses=30, model=36)["n_parameters"] == 36


def test_daney_solution_as_initial_guess(true_robot):
    rng = np.random.default_rng(7)
    far = true_robot.with_theta(true_robot.theta + rng.normal(0, 1e-2, 42))  # 1 cm off
    legs = []
    for k in range(6):
        T2 = generate_type2(true_robot, k, 1, 5, rng)[0]
        T3 = generate_type3(true_robot, k, 1, 6, rng)[0]
        legs.append(calibrate_leg_daney(k + 1, type2=T2, type3=T3,
                                        offset_poses=(T3, true_robot.leg_lengths(T3)[:, k])))
    data = simulate_gough_data(true_robot, 30, 8)
    res = calibrate_gough(far, data, initial="daney", daney_results=legs)
    assert res.parameters["a3_x"]["nominal"] == pytest.approx(true_robot.a[2, 0], abs=1e-11)
    np.testing.assert_allclose(res.theta, true_robot.theta, atol=1e-11)
    with pytest.raises(ValueError, match="daney_results"):
        calibrate_gough(far, data, initial="daney")


# ---------------------------------------------------------------- result protocol, files
def test_result_protocol(true_robot, nominal, tmp_path):
    """to_dict / to_json (strict JSON, SI), table (mm), save_model (a Gough robot file that loads as the
    calibrated platform, with its calibration block), inputs never overwritten."""
    data = simulate_gough_data(true_robot, 30, 9, sigma_rho=1e-5)
    save_gough_data(data, tmp_path / "m.csv")
    res = calibrate_gough(nominal, tmp_path / "m.csv", residual="fk")
    d = json.loads(json.dumps(res.to_dict()))
    assert d["method"] == "lm" and d["residual"] == "fk" and d["model"] == 42 and d["converged"]
    assert len(d["parameters"]) == 42 and len(d["covariance"]) == 42 and d["names"][0] == "a1_x"
    assert d["rmse_mm"]["train"] < d["rmse_mm"]["train_before"]
    assert d["identifiability"]["n_identifiable"] == 42 and d["fk_failures"] == 0
    res.to_json(tmp_path / "r.json")
    assert json.loads((tmp_path / "r.json").read_text())["theta"]["a3_x"] == pytest.approx(res.theta[14])
    a3x = res.parameters["a3_x"]
    table = res.table()  # the shared Table (estcal.base.tables), in mm
    assert table.columns == ["parameter", "initial", "estimate", "± std", "unit"] and len(table.rows) == 42
    assert table.rows[14][2] == pytest.approx(a3x["estimate"] * 1e3) and table.rows[14][4] == "mm"
    assert f"{a3x['estimate'] * 1e3:.6g}" in str(table) and str(table) in str(res) and str(res) == repr(res)
    res.save_model(tmp_path / "cal.yaml")
    cal = load_gough(tmp_path / "cal.yaml")
    np.testing.assert_allclose(cal.theta, res.theta, rtol=1e-15)
    np.testing.assert_allclose(res.robot().theta, res.theta, rtol=0)
    import yaml

    block = yaml.safe_load((tmp_path / "cal.yaml").read_text())["calibration"]
    assert block["estimator"] == "lm" and block["free"] == res.names and block["residual"] == "fk"
    assert block["data"][0]["file"] == str(tmp_path / "m.csv") and block["data"][0]["n_poses"] == 30
    np.testing.assert_allclose(block["covariance"], res.covariance, rtol=1e-15)
    with pytest.raises(ValueError, match="inputs are never overwritten"):
        res.save_model(tmp_path / "m.csv")
    # a saved model recalibrates as any Gough robot file
    assert calibrate_gough(tmp_path / "cal.yaml", data, estimator="gauss-newton").converged


def test_data_files_roundtrip(true_robot, tmp_path):
    data = simulate_gough_data(true_robot, 7, 9, sigma_rho=1e-5)
    save_gough_data(data, tmp_path / "m.csv")
    d1 = load_gough_data(tmp_path / "m.csv")
    np.testing.assert_allclose(d1.T, data.T, atol=1e-11)
    np.testing.assert_allclose(d1.rho, data.rho, atol=1e-12)
    np.savez(tmp_path / "m.npz", T=data.T, rho=data.rho, sigma_rho=1e-5)
    assert load_gough_data(tmp_path / "m.npz").sigma_rho == 1e-5
    (tmp_path / "m.json").write_text(json.dumps(data.to_dict()))
    np.testing.assert_allclose(load_gough_data(tmp_path / "m.json").T, data.T, atol=1e-12)
    # quaternion columns
    q = np.c_[np.ones(7), np.zeros((7, 3))]
    P = data.T[:, :3, 3]
    arr = np.c_[P, q, data.rho]
    np.savetxt(tmp_path / "q.csv", arr, delimiter=",", comments="",
               header="x,y,z,qw,qx,qy,qz," + ",".join(f"rho{k}" for k in range(1, 7)))
    np.testing.assert_allclose(load_gough_data(tmp_path / "q.csv").T, make_T(P, np.eye(3)), atol=1e-12)
    (tmp_path / "bad.csv").write_text("x,y,z,rho1\n1,2,3,4\n")
    with pytest.raises(ValueError, match="bad.csv"):
        load_gough_data(tmp_path / "bad.csv")
    with pytest.raises(ValueError, match="poses"):
        GoughData(data.T, data.rho[:3])


def test_csv_reading_column_aliases(true_robot, tmp_path):
    data = simulate_gough_data(true_robot, 4, 12)
    txt = data.to_csv_text().replace("rho", "q", 6)
    (tmp_path / "q.csv").write_text(txt)
    np.testing.assert_allclose(load_gough_data(tmp_path / "q.csv").rho, data.rho, atol=1e-12)
    (tmp_path / "none.csv").write_text(txt.replace("q1", "z1", 1))
    with pytest.raises(ValueError, match="rho1..rho6"):
        load_gough_data(tmp_path / "none.csv")
