"""Repeatability across sessions (estcal.sessions): three agreeing formulations, REML against a
dense computation, new-session coverage against simulated truth, the re-measurement curve."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.estimate.levels import select_free
from estcal.kinematics.robots import puma560
from estcal.methods import NoiseModel, Problem
from estcal.sessions import (choose_poses, choose_vary, fit_sessions, predict_session, recalibration_curve,
                             reml_objective, simulate_sessions, solve_factor_graph, solve_gls, solve_kalman)
from estcal.sessions.system import blocks_from_rows

VARY = {"offset_2": 1e-3, "offset_3": 5e-4}
NOISE = NoiseModel(position=5e-5, known=True)


def _linear_case(seed=0, p=8, S=(1, 4, 6), q=(0.5, 0.1, 2.0), n_s=5, m=30):
    rng = np.random.default_rng(seed)
    S = np.array(S)
    A_list = [rng.normal(size=(m, p)) for _ in range(n_s)]
    theta = rng.normal(size=p)
    r_list = []
    for A in A_list:
        th = theta.copy()
        th[S] += rng.normal(size=len(S)) * np.sqrt(q)
        r_list.append(A @ th + rng.normal(size=m))
    return A_list, r_list, S, np.array(q, float)


@pytest.mark.parametrize("q", [(0.5, 0.1, 2.0), (0.0, 0.1, 2.0)])
def test_three_formulations_agree_on_the_linear_model(q):
    """GLS (random effects integrated out), the gtsam graph (per-session nodes + between factors,
    a hard constraint where q = 0) and the filterpy filter (Q at each session boundary) give the
    same estimate, covariance and session deviations; and GLS equals the dense normal equations
    of the stacked model with explicit V_s = I + B Q Bᵀ."""
    A_list, r_list, S, qv = _linear_case(q=q)
    ref = solve_gls(A_list, r_list, S, qv)
    Vinv = [np.linalg.inv(np.eye(len(r)) + A[:, S] @ np.diag(qv) @ A[:, S].T) for A, r in zip(A_list, r_list)]
    N = sum(A.T @ W @ A for A, W in zip(A_list, Vinv))
    g = sum(A.T @ W @ r for A, r, W in zip(A_list, r_list, Vinv))
    np.testing.assert_allclose(ref[0], np.linalg.solve(N, g), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ref[1], np.linalg.inv(N), rtol=1e-9, atol=1e-14)
    sd = np.sqrt(np.diag(ref[1]))
    for solve in (solve_factor_graph, solve_kalman):
        d, C, u = solve(A_list, r_list, S, qv)
        assert np.max(np.abs(d - ref[0]) / sd) < 1e-6
        np.testing.assert_allclose(np.sqrt(np.diag(C)), sd, rtol=1e-6)
        np.testing.assert_allclose(u, ref[2], atol=1e-6 * max(1.0, np.abs(ref[2]).max()))


def test_kalman_within_session_drift():
    """Pose-by-pose processing with zero within-session drift is the session-batch filter (and
    GLS); a within-session drift widens the last session's deviation uncertainty."""
    A_list, r_list, S, q = _linear_case(seed=5, m=30)
    ref = solve_kalman(A_list, r_list, S, q)
    same = solve_kalman(A_list, r_list, S, q, q_within=np.zeros(3), rows_per_pose=3)
    sd = np.sqrt(np.diag(ref[1]))
    assert np.max(np.abs(same[0] - ref[0]) / sd) < 1e-6  # round-off of the diffuse prior, in σ
    np.testing.assert_allclose(np.sqrt(np.diag(same[1])), sd, rtol=1e-6)
    drift = solve_kalman(A_list, r_list, S, q, q_within=np.full(3, 0.05), rows_per_pose=3)
    assert np.all(np.diag(drift[1]) >= np.diag(ref[1]) * (1 - 1e-9))
    assert not np.allclose(drift[0], ref[0])


def test_reml_objective_matches_dense_formula():
    """−2ℓ_R from the Woodbury blocks equals the textbook dense expression (Harville 1977)."""
    A_list, r_list, S, q = _linear_case(seed=3)
    blocks = [blocks_from_rows(A, r) for A, r in zip(A_list, r_list)]
    for s2 in (1.0, 2.5):
        V = [s2 * np.eye(len(r)) + A[:, S] @ np.diag(q) @ A[:, S].T for A, r in zip(A_list, r_list)]
        Vi = [np.linalg.inv(v) for v in V]
        N = sum(A.T @ W @ A for A, W in zip(A_list, Vi))
        g = sum(A.T @ W @ r for A, r, W in zip(A_list, r_list, Vi))
        dense = (sum(np.linalg.slogdet(v)[1] for v in V) + np.linalg.slogdet(N)[1]
                 + sum(r @ W @ r for r, W in zip(r_list, Vi)) - g @ np.linalg.solve(N, g))
        assert reml_objective(blocks, S, q, s2) == pytest.approx(dense, rel=1e-10)


@pytest.fixture(scope="module")
def sessions():
    robot = puma560()
    ds, truth = simulate_sessions(robot, 8, 20, VARY, seed=1)
    train = ds[:6]
    sel = select_free(Problem(robot, [(None, d, NOISE) for d in train], NOISE), "full", "bic")
    return robot, train, sel


def test_formulations_agree_after_the_nonlinear_fit(sessions):
    """With Q estimated by REML, the three formulations converge to the same θ (≤ 0.1 σ; in
    practice ~1e-6 σ) and the same variance components."""
    robot, train, sel = sessions
    fits = {f: fit_sessions(robot, train, sel.identifiable, list(VARY), noise=NOISE, formulation=f,
                            theta=sel.theta) for f in ("gls", "gtsam", "kalman")}
    ref = fits["gls"]
    assert ref.converged
    for f in ("gtsam", "kalman"):
        assert np.max(np.abs(fits[f].estimate - ref.estimate) / ref.std) < 0.1
        np.testing.assert_allclose(fits[f].q, ref.q, rtol=1e-3)
    vc = {v["parameter"]: v for v in ref.variance_components()}
    assert vc["offset_2"]["unit"] == "mrad" and vc["offset_2"]["varies"]
    d = ref.to_dict()
    assert set(d["session_deviations"]) == set(ref.sessions) and len(d["variance_components"]) == 2


def test_new_session_coverage_within_binomial_band(sessions):
    """95 % prediction ellipsoids of new sessions (θ covariance + Q) cover 95 % of the points of
    200 new simulated sessions (one independent pose each: within the binomial band); without the
    repeatability term (the usual one-θ fit of the same sessions) the intervals are too narrow:
    coverage below the band."""
    robot, train, sel = sessions
    fit = fit_sessions(robot, train, sel.identifiable, list(VARY), noise=NOISE, theta=sel.theta)
    # the same true robot (seed 1) and 200 new sessions of one pose each
    new, _ = simulate_sessions(robot, 206, 1, VARY, seed=1)
    from estcal.io.dataset import dataset_from_arrays

    pooled = new[6:]
    data = dataset_from_arrays(robot.joint_names, np.vstack([d.readings for d in pooled]),
                               points=np.vstack([d.points for d in pooled]))
    with_q = predict_session(fit, data)
    # the usual one-θ model (no repeatability term) fitted to the same sessions
    fit0 = fit_sessions(robot, train, sel.identifiable, [], noise=NOISE, theta=sel.theta)
    without = predict_session(fit0, data)
    lo, hi = with_q["band"]
    assert lo <= with_q["coverage"] <= hi, with_q["coverage"]
    assert without["coverage"] < lo, without["coverage"]


def test_true_variance_components_are_recovered():
    """With 25 sessions the REML between-session std of each varying offset is within 3 standard
    errors of the truth, and a parameter that does not vary is not selected (LR test)."""
    robot = puma560()
    ds, truth = simulate_sessions(robot, 25, 8, VARY, seed=4)
    # offset_1 would regroup with the base rotation about the first axis: not free
    free = ["base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz", "offset_2", "offset_3", "offset_4"]
    choice = choose_vary(robot, ds, free, candidates=["offset_2", "offset_3", "offset_4"], noise=NOISE,
                         theta=truth["theta"])
    assert sorted(choice["vary"]) == ["offset_2", "offset_3"]
    fit = choice["fit"]
    for v in fit.variance_components():
        true_sd = VARY[v["parameter"]] * 1e3
        assert abs(v["std"] - true_sd) < 3 * v["std_err"] + 0.05 * true_sd, v


def test_recalibration_curve_and_pose_choice(sessions):
    """A new session re-measured on k poses: k = 0 leaves the session's offset error (≫ noise);
    k = 2 brings the rest of the session near the noise floor (√3 · 0.05 mm); the greedy
    covariance rule's first pick is the brute-force best pose."""
    robot, train, sel = sessions
    fit = fit_sessions(robot, train, sel.identifiable, list(VARY), noise=NOISE, theta=sel.theta)
    new, _ = simulate_sessions(robot, 9, 30, VARY, seed=1)
    data = new[8]
    curve = recalibration_curve(fit, data, range(0, 4))
    floor = np.sqrt(3) * 0.05
    assert curve["rmse_mm"][0] > 3 * floor
    assert curve["rmse_mm"][2] < 1.5 * floor
    # brute force: predicted summed variance after adding each pose
    from estcal.sessions.predict import _pose_blocks

    _, J, sig = _pose_blocks(fit, data)
    P0 = fit.new_session_cov()
    best, best_c = np.inf, None
    for c in range(data.n):
        W = J[c] / sig[c][:, None]
        P = np.linalg.inv(np.linalg.inv(P0) + W.T @ W)
        tot = sum(np.trace(J[i] @ P @ J[i].T) for i in range(data.n))
        if tot < best:
            best, best_c = tot, c
    assert choose_poses(fit, data, 1) == [best_c]


def test_sessions_cli_and_session_column(tmp_path):
    """`estcal sessions` on one file per session and on one file with a `session` column gives the
    same fit; `--vary auto` picks the truly varying offset among three candidates; a new session is
    scored with its coverage; the JSON is strict."""
    import json

    from typer.testing import CliRunner

    from estcal.cli.main import app
    from estcal.io.dataset import write_dataset
    from estcal.sessions.data import stack_sessions

    robot = puma560()
    # no fixed geometric errors: the free offsets are the whole model (no misfit to mistake for variation)
    ds, truth = simulate_sessions(robot, 6, 12, {"offset_2": 2e-3}, noise=5e-5, seed=5, error_std=0.0)
    files = []
    for i, d in enumerate(ds):
        files.append(tmp_path / f"day{i + 1}.csv")
        write_dataset(files[-1], d)
    stacked = stack_sessions(ds[:5])
    write_dataset(tmp_path / "all.csv", stacked, extra={"session": stacked.columns["session"]})
    common = ["--robot", "puma560", "--free", "offset_2,offset_3,offset_4", "--noise-pos-mm", "0.05",
              "--known-noise"]
    r = CliRunner().invoke(app, ["sessions", *map(str, files[:5]), *common, "--vary", "auto", "--validate",
                                 str(files[5]), "--json", str(tmp_path / "a.json")])
    assert r.exit_code == 0, r.output
    a = json.loads((tmp_path / "a.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    assert a["vary"] == ["offset_2"]
    assert "offset_2" in r.output and "mrad" in r.output and "coverage" in r.output
    r = CliRunner().invoke(app, ["sessions", str(tmp_path / "all.csv"), *common, "--vary", "offset_2", "--json",
                                 str(tmp_path / "b.json")])
    assert r.exit_code == 0, r.output
    b = json.loads((tmp_path / "b.json").read_text())
    for n, v in a["parameters"].items():
        assert abs(v["estimate"] - b["parameters"][n]["estimate"]) < 1e-6 * v["std"] + 1e-12
    r = CliRunner().invoke(app, ["sessions", str(files[0]), *common, "--vary", "offset_9"])
    assert r.exit_code == 2 and "offset_9" in r.output
    # a pattern selects among the free parameters (offset_1, offset_5, offset_6 are fixed here)
    r = CliRunner().invoke(app, ["sessions", *map(str, files[:5]), *common, "--vary", "offset_*", "--json",
                                 str(tmp_path / "c.json")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "c.json").read_text())["vary"] == ["offset_2", "offset_3", "offset_4"]
    r = CliRunner().invoke(app, ["sessions", *map(str, files[:2]), *common, "--vary", "gain_*"])
    assert r.exit_code == 2 and "['gain_*'] match no free parameter" in r.output


def test_diagnose_takes_several_sessions(tmp_path):
    """`estcal diagnose A.csv B.csv`: the sessions are fitted together with approach directions
    derived per session (the first pose of each session has none), and the saved model lists
    both files with their sha256."""
    import hashlib

    import yaml
    from typer.testing import CliRunner

    from estcal.cli.main import app
    from estcal.discrepancy import diagnose
    from estcal.io.dataset import write_dataset

    robot = puma560()
    ds, _ = simulate_sessions(robot, 2, 15, {}, noise=5e-5, seed=6, error_std=2e-4)
    res = diagnose(robot, ds, noise=5e-5, approach_from_order=True, k_folds=3, budget=False)
    assert isinstance(res.train_data, list) and len(res.train_data) == 2
    files = []
    for i, d in enumerate(ds):
        files.append(tmp_path / f"s{i}.csv")
        write_dataset(files[-1], d)
    r = CliRunner().invoke(app, ["diagnose", *map(str, files), "--robot", "puma560", "--noise-pos-mm", "0.05",
                                 "--folds", "3", "--approach-from-order", "--save-model", str(tmp_path / "m.yaml")])
    assert r.exit_code == 0, r.output
    block = yaml.safe_load((tmp_path / "m.yaml").read_text())["calibration"]
    shas = [e["sha256"] for e in block["data"] if e["role"] == "train"]
    assert shas == [hashlib.sha256(f.read_bytes()).hexdigest() for f in files]
    # approach per session: stacking first and deriving after would give the second session's
    # first pose an approach from the first session's last pose
    from estcal.io.prepare import derive_approach
    from estcal.sessions.data import stack_sessions

    per = stack_sessions([derive_approach(d) for d in ds])
    first2 = ds[0].n
    assert all(per.columns[c][first2] == 0 for c in per.columns if c.startswith("approach_"))
    # a file stacked by the caller (its session column) gets each session's own sequence too
    after = derive_approach(stack_sessions(ds))
    for c in (c for c in per.columns if c.startswith("approach_")):
        np.testing.assert_array_equal(after.columns[c], per.columns[c])


def test_calibrate_takes_several_sessions(tmp_path):
    """`estcal calibrate A.csv B.csv` fits one parameter set to both sessions: the same estimate as
    the concatenated file, and the saved model lists both files with their sha256."""
    import hashlib
    import json

    import yaml
    from typer.testing import CliRunner

    from estcal.cli.main import app
    from estcal.io.dataset import write_dataset
    from estcal.sessions.data import stack_sessions

    robot = puma560()
    ds, _ = simulate_sessions(robot, 2, 15, {}, noise=5e-5, seed=7, error_std=2e-4)
    files = [tmp_path / "a.csv", tmp_path / "b.csv"]
    for f, d in zip(files, ds):
        write_dataset(f, d)
    write_dataset(tmp_path / "ab.csv", stack_sessions(ds))
    common = ["--robot", "puma560", "--free", "base_*,offset_2,offset_3,a_2,a_3", "--noise-pos-mm", "0.05",
              "--known-noise"]
    r = CliRunner().invoke(app, ["calibrate", *map(str, files), *common, "--json", str(tmp_path / "s.json"),
                                 "--save-model", str(tmp_path / "m.yaml")])
    assert r.exit_code == 0, r.output
    r2 = CliRunner().invoke(app, ["calibrate", str(tmp_path / "ab.csv"), *common, "--json", str(tmp_path / "c.json")])
    assert r2.exit_code == 0, r2.output
    a, b = (json.loads((tmp_path / n).read_text())["parameters"] for n in ("s.json", "c.json"))
    for n in a:
        assert abs(a[n]["estimate"] - b[n]["estimate"]) <= 1e-9 * a[n]["std"] + 1e-15
    block = yaml.safe_load((tmp_path / "m.yaml").read_text())["calibration"]
    assert [e["sha256"] for e in block["data"] if e["role"] == "train"] == \
        [hashlib.sha256(f.read_bytes()).hexdigest() for f in files]
