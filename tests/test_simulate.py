"""Simulator: exactness without noise, noise statistics (χ²), strategies, ground truth."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from estcal.io.dataset import load_dataset
from estcal.io.robotfile import robot_from_dict
from estcal.kinematics import puma560, robot_5r1p, stanford
from estcal.kinematics.transforms import so3_log
from estcal.simulate import NoiseModel, block_sizes, generate_poses, random_errors, simulate

P_TAIL = 1e-4  # two-sided tail probability of every statistical check


def chi2_ok(ssq, df):
    return stats.chi2.ppf(P_TAIL / 2, df) <= ssq <= stats.chi2.isf(P_TAIL / 2, df)


@pytest.mark.parametrize("measure", ["position", "points", "pose"])
def test_noise_free_equals_true_fk(measure, tmp_path):
    res = simulate("puma560", n_poses=40, measure=measure, errors="random",
                   effects=["encoder_gain:j2", "gear_harmonic:j1", "drift:j3"], seed=3, dt=30.0)
    ds, true = res.dataset, res.true_robot
    k = true.kinematics(ds.readings, context=ds.context, jacobian=False)
    if measure == "pose":
        np.testing.assert_array_equal(ds.p, k.p)
        np.testing.assert_array_equal(ds.R, k.R)
    elif measure == "points":
        assert ds.points.shape == (40, 3, 3)
        np.testing.assert_array_equal(ds.points, k.points)
    else:
        np.testing.assert_array_equal(ds.points[:, 0], k.p)
    # the nominal model is measurably wrong, the true one exact
    assert res.summary.nominal_rms_mm > 0.5
    # CSV + JSON round trip: the file reloads to the same data, the JSON to the same true robot
    csv, js = res.write(tmp_path / "d.csv", tmp_path / "t.json")
    back = load_dataset(csv, res.nominal_robot)
    np.testing.assert_allclose(back.readings, ds.readings, rtol=0, atol=1e-14)
    truth = json.loads(js.read_text())
    t2 = robot_from_dict(truth["true_robot"])
    k2 = t2.kinematics(back.readings, context=back.context, jacobian=False)
    got = back.p if measure == "pose" else back.points[:, 0]
    exp = k2.p if measure != "points" else k2.points[:, 0]
    np.testing.assert_allclose(got, exp, rtol=0, atol=1e-12)
    assert truth["parameters"] == dict(zip(true.params.names, true.params.values.tolist()))
    assert truth["seed"] == 3 and truth["strategy"] == "S4" and {e["effect"] for e in truth["effects"]} == \
        {"encoder_gain", "gear_harmonic", "drift"}


def test_compliance_with_payload_and_given_values():
    d = {"estcal_robot": 1, "name": "v", "convention": "dh", "gravity": [0, -9.81, 0], "joints": [
        {"name": "a", "a": 1.0, "mass": 2.0, "com": [-0.5, 0, 0]},
        {"name": "b", "a": 0.8, "mass": 1.0, "com": [-0.4, 0, 0]}]}
    robot = robot_from_dict(d)
    res = simulate(robot, n_poses=30, effects=[{"effect": "joint_compliance",
                                                 "params": {"compliance_a": 1e-3, "compliance_b": 2e-3}}],
                   payload=(0.0, 4.0, "uniform"), seed=1)
    q, m = res.dataset.readings, res.dataset.context["payload"]
    assert m.min() >= 0 and m.max() <= 4 and m.std() > 0.5
    g, c1, c12 = 9.81, np.cos(q[:, 0]), np.cos(q.sum(1))
    tau = np.c_[-g * (1.0 * c1 + 1.0 * (c1 + 0.4 * c12) + m * (c1 + 0.8 * c12)), -g * (0.4 + m * 0.8) * c12]
    qq = q + tau * [1e-3, 2e-3]
    x = np.c_[np.cos(qq[:, 0]) + 0.8 * np.cos(qq.sum(1)), np.sin(qq[:, 0]) + 0.8 * np.sin(qq.sum(1))]
    np.testing.assert_allclose(res.dataset.points[:, 0, :2], x, atol=1e-12)


def test_gaussian_noise_statistics_chi2():
    sp, sr, sj = 5e-5, 5e-4, 1e-4
    res = simulate("stanford", n_poses=400, measure="pose", errors="random",
                   noise=NoiseModel(position=sp, orientation=sr, joint=sj), seed=11)
    N = 400
    ep = res.dataset.p - res.true_p
    er = so3_log(res.dataset.R @ np.swapaxes(res.true_R, 1, 2))
    ej = res.dataset.readings - res.true_readings
    assert chi2_ok(np.sum(ep**2) / sp**2, 3 * N)
    assert chi2_ok(np.sum(er**2) / sr**2, 3 * N)
    assert chi2_ok(np.sum(ej**2) / sj**2, 6 * N)
    # components are independent: the sample correlation between x and y noise is ~ N(0, 1/N)
    assert abs(np.corrcoef(ep[:, 0], ep[:, 1])[0, 1]) < stats.norm.isf(P_TAIL / 2) / np.sqrt(N)
    # the summary's noise RMS is the RMS of what was added
    assert res.summary.noise_rms_mm == pytest.approx(np.sqrt(np.mean(ep**2)) * 1e3)


def test_uniform_noise_bounds_and_variance():
    a = 1e-4
    N = 2000
    res = simulate("5r1p", n_poses=N, measure="position", noise={"position": a, "distribution": "uniform"}, seed=2)
    e = (res.dataset.points - res.true_points).reshape(-1)
    assert np.all(np.abs(e) <= a)
    n = e.size
    # sum of squares of U(-a, a): mean n a²/3, variance n a⁴ (1/5 - 1/9)
    z = (np.sum(e**2) - n * a**2 / 3) / np.sqrt(n * a**4 * (1 / 5 - 1 / 9))
    assert abs(z) < stats.norm.isf(P_TAIL / 2)


def test_quantisation():
    res_ = np.radians(0.01)
    N = 3000
    res = simulate("puma560", n_poses=N, noise={"resolution": res_}, seed=4)
    rec, true = res.dataset.readings, res.true_readings
    k = rec / res_
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    e = (rec - true).reshape(-1)
    assert np.abs(e).max() <= res_ / 2 * (1 + 1e-9)
    # rounding error ~ U(-res/2, res/2): mean square res²/12
    n = e.size
    z = (np.sum(e**2) - n * res_**2 / 12) / np.sqrt(n * (res_ / 2) ** 4 * (1 / 5 - 1 / 9))
    assert abs(z) < stats.norm.isf(P_TAIL / 2)


@pytest.mark.parametrize("strategy", ["S1", "S2", "S3", "S4"])
def test_strategies_within_limits_and_structure(strategy):
    robot = robot_5r1p()
    N, n = 60, robot.n_joints
    margin = 0.05
    q = generate_poses(robot, N, strategy, np.random.default_rng(0), margin=margin)
    lo, hi = robot.limits.T
    span = hi - lo
    assert q.shape == (N, n)
    assert np.all(q >= lo + margin * span - 1e-12) and np.all(q <= hi - margin * span + 1e-12)
    frac = (q - lo - margin * span) / ((1 - 2 * margin) * span)
    if strategy == "S1":  # every joint at the same fraction of its range: one curve
        np.testing.assert_allclose(frac, np.repeat(frac[:, :1], n, 1), atol=1e-12)
        assert np.all(np.diff(frac[:, 0]) > 0)
    elif strategy == "S2":  # one joint at a time, the others at home (mid-range)
        mid = (lo + hi) / 2
        start = 0
        for j, m in enumerate(block_sizes(N, n)):
            blk = q[start:start + m]
            others = np.delete(np.arange(n), j)
            np.testing.assert_allclose(blk[:, others], np.tile(mid[others], (m, 1)), atol=1e-12)
            assert np.all(np.diff(blk[:, j]) > 0)
            start += m
    elif strategy == "S3":  # S2's complement: joint j held at home, the others step together
        mid = (lo + hi) / 2
        start = 0
        for j, m in enumerate(block_sizes(N, n)):
            blk, fblk = q[start:start + m], frac[start:start + m]
            np.testing.assert_allclose(blk[:, j], mid[j], atol=1e-12)
            others = np.delete(np.arange(n), j)
            # every moving joint at the same fraction of its range, fractions (i + 1/2)/m
            np.testing.assert_allclose(fblk[:, others], np.tile(fblk[:, others[:1]], (1, n - 1)), atol=1e-12)
            np.testing.assert_allclose(fblk[:, others[0]], np.linspace(0.5 / m, 1 - 0.5 / m, m), atol=1e-12)
            start += m
        # deterministic: no use of the generator
        np.testing.assert_array_equal(q, generate_poses(robot, N, strategy, np.random.default_rng(99), margin=margin))
    else:  # independent uniform: Kolmogorov–Smirnov per joint
        for j in range(n):
            assert stats.kstest(frac[:, j], "uniform").pvalue > P_TAIL


def test_seeds_and_independent_streams():
    a = simulate("puma560", n_poses=20, errors="random", noise={"position": 1e-4}, seed=5)
    b = simulate("puma560", n_poses=20, errors="random", noise={"position": 1e-4}, seed=5)
    c = simulate("puma560", n_poses=20, errors="random", noise={"position": 3e-4}, seed=5)
    np.testing.assert_array_equal(a.dataset.points, b.dataset.points)
    np.testing.assert_array_equal(a.dataset.readings, c.dataset.readings)  # same poses, other noise
    np.testing.assert_array_equal(a.true_robot.params.values, c.true_robot.params.values)
    np.testing.assert_allclose((c.dataset.points - c.true_points), 3 * (a.dataset.points - a.true_points),
                               rtol=1e-9, atol=1e-15)


def test_errors_dict_and_random_std():
    res = simulate("puma560", n_poses=5, errors={"offset_2": 1e-3, "d_3": -2e-4}, seed=0)
    assert res.truth["errors"] == {"offset_2": 1e-3, "d_3": -2e-4}
    assert res.true_robot.params["offset_2"] == 1e-3
    assert res.true_robot.params["d_3"] == pytest.approx(puma560().params["d_3"] - 2e-4, abs=1e-15)
    with pytest.raises(KeyError, match="unknown parameter 'ofset_2'"):
        simulate("puma560", n_poses=5, errors={"ofset_2": 1e-3})
    # random errors: the sample std over many robots' angles matches the requested σ (χ²)
    robot = stanford()
    err = [random_errors(robot, {"angle": 2e-3, "length": 0, "offset": 0}, s) for s in range(40)]
    vals = np.array([v for e in err for v in e.values()])
    assert len(err[0]) == len([n for n in robot.params.names if n.split("_")[0] in ("alpha", "theta", "beta")
                               or n in ("base_rx", "base_ry", "base_rz", "tool_rx", "tool_ry", "tool_rz")])
    assert chi2_ok(np.sum(vals**2) / 2e-3**2, vals.size)


def test_context_profiles_and_approach():
    res = simulate("puma560", n_poses=10, effects=["backlash:j2", "thermal_expansion"], dt=2.0,
                   temperature={"start": 20, "end": 30, "tau": 10.0}, payload=1.5, record_approach=True, seed=0)
    ctx = res.dataset.context
    np.testing.assert_allclose(ctx["t"], 2.0 * np.arange(10))
    np.testing.assert_allclose(ctx["temperature"], 30 - 10 * np.exp(-ctx["t"] / 10.0))
    np.testing.assert_allclose(ctx["payload"], 1.5)
    assert set(res.dataset.columns) == {"approach_j2"} and "approach_j2" in ctx
    assert res.nominal_robot.n_markers == 0  # thermal expansion acts on the tool origin itself
    # noise-free: the data are the true FK including the approach column and temperature
    k = res.true_robot.kinematics(res.dataset.readings, context=ctx, jacobian=False)
    np.testing.assert_array_equal(res.dataset.points[:, 0], k.p)
    with pytest.raises(ValueError, match="unknown strategy 'S5'"):
        simulate("puma560", n_poses=3, strategy="S5")
    with pytest.raises(ValueError, match="unknown parameters"):
        simulate("puma560", n_poses=3, effects=[{"effect": "drift", "params": {"drift_j9": 1.0}}])
