"""The pure pieces of experiments/extrapolation_study.py against independent computations (no data needed)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

EXP = Path(__file__).resolve().parents[1] / "experiments"


@pytest.fixture(scope="module")
def study():
    sys.path.insert(0, str(EXP))
    spec = importlib.util.spec_from_file_location("extrapolation_study", EXP / "extrapolation_study.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_extrapolation_distance_by_hand(study):
    from estcal.validation import inside_ranges

    A = np.array([[0.0, -1.0], [2.0, 1.0], [1.0, 0.0]])  # ranges [0, 2] and [-1, 1]
    B = np.array([[1.0, 0.5], [3.0, 0.0], [-0.5, 2.0], [2.0, -1.0]])
    d = study.extrapolation(A, B)
    # by hand: 1 beyond a range of 2 = 0.5; 0.5 below = 0.25; 1 beyond a range of 2 = 0.5; the edges are inside
    np.testing.assert_allclose(d, [[0, 0], [0.5, 0], [0.25, 0.5], [0, 0]])
    np.testing.assert_array_equal((d == 0).all(1), inside_ranges(A, B))
    rng = np.random.default_rng(1)
    A, B = rng.normal(size=(20, 5)), rng.normal(size=(200, 5)) * 1.5
    np.testing.assert_array_equal((study.extrapolation(A, B) == 0).all(1), inside_ranges(A, B))


def test_spanning_half_holds_every_extreme(study):
    from estcal.validation import inside_ranges

    Q = np.random.default_rng(3).normal(size=(62, 8))
    for seed in range(5):
        m = study.spanning_half(Q, seed)
        assert m.sum() == 31
        assert inside_ranges(Q[m], Q[~m]).all()  # every other posture is an interpolation


def test_only_along_extrapolates_one_joint(study):
    Q = np.random.default_rng(4).normal(size=(62, 6))
    for j in range(6):
        ranked = np.argsort(-Q[:, j])
        held, left = study._only_along(Q, j, ranked, 5)
        assert len(held) > 0
        rest = np.setdiff1d(np.arange(62), np.r_[held, left])
        d = study.extrapolation(Q[rest], Q[held])
        assert (np.delete(d, j, 1) == 0).all()  # inside on every other joint
        assert d[0, j] > 0  # the most extreme one held out lies beyond the range of j
        assert not set(held) & set(left)


def test_counterfactual_removes_each_joints_line(study):
    rng = np.random.default_rng(5)
    D = np.abs(rng.normal(size=(40, 3))) * (rng.random((40, 3)) < 0.3)
    P = rng.integers(4, 9, 40).astype(float)
    a, b_true = 2.0, np.array([3.0, 0.0, 1.5])
    E = a + D @ b_true  # exact: the NNLS recovers it, the counterfactuals follow by hand
    a_hat, b = study._nnls_fit(E, D, P)
    np.testing.assert_allclose([a_hat, *b], [a, *b_true], atol=1e-9)
    tot, each, none = study._counterfactual(E, D, P, b)
    w = lambda e: np.sqrt(np.sum(e ** 2 * P) / P.sum())  # noqa: E731
    assert tot == pytest.approx(w(E))
    assert each[0] == pytest.approx(w(a + D[:, 2] * 1.5)) and each[1] == pytest.approx(tot)
    assert none == pytest.approx(a)


def test_hand_scaled_changes_only_the_last_link(study, tiago_dir):
    from estcal.kinematics import tiago

    rb = tiago()
    rb2 = study.hand_scaled(rb, 2.0)
    masses = [lk.mass for lk in rb.links]
    last = max(i for i, lk in enumerate(rb.links) if lk.joint is not None)
    assert masses[last] > 0  # the arm_7 link with the gripper (URDF masses)
    assert [lk.mass for lk in rb2.links] == [m * 2.0 if i == last else m for i, m in enumerate(masses)]
    # the torque on the last joint's axis comes from that link alone: it doubles; the prismatic lift's force
    # grows by the added mass times g (an independent sum)
    q = np.array([[0.2, 0.5, -0.3, -1.0, 1.2, 0.3, 0.6, 0.4]])
    t1, t2 = rb.gravity_torques(q), rb2.gravity_torques(q)
    assert abs(t1[0, -1]) > 1e-2
    np.testing.assert_allclose(t2[0, -1], 2 * t1[0, -1], rtol=1e-12)
    assert abs(t2[0, 0] - t1[0, 0]) == pytest.approx(masses[last] * np.linalg.norm(rb.gravity), rel=1e-9)


def test_stiffening_compliance_against_torques_and_finite_differences(study, tiago_dir):
    from estcal.io.dataset import Dataset
    from estcal.kinematics import tiago

    rb = tiago()
    rng = np.random.default_rng(6)
    lo, hi = np.array([0.0, 0.1, -1.0, -2.0, 0.5, -1.5, -1.0, -1.5]), np.array([0.35, 1.5, 0.5, 0.0, 2.0, 1.0, 1.0, 1.5])
    R = lo + (hi - lo) * rng.random((12, rb.n_joints))
    data = Dataset(list(rb.joint_names), R, "none", None, None, None, {}, {}, np.arange(12), None, [])
    rs = study.with_stiffening(rb, data)
    eff = rs.effects[-1]
    tau = rb.gravity_torques(R)
    idx = [rb.joint_names.index(j) for j in eff.joints]
    assert "arm_1_joint" not in eff.joints and "torso_lift_joint" not in eff.joints  # constant loads: no term
    np.testing.assert_allclose(eff.tau_ref, np.abs(tau[:, idx]).max(0))
    # the joint correction is c3 τ³ / τ_ref² on each loaded joint (τ from the rigid model: gravity_torques)
    th = rs.params.values.copy()
    c3 = rng.normal(size=len(idx)) * 1e-3
    th[eff.indices] = c3
    dq, _ = eff.joint_correction(rs, R, R, th, {})
    np.testing.assert_allclose(dq[:, idx], c3 * tau[:, idx] ** 3 / eff.tau_ref ** 2, rtol=1e-9, atol=1e-15)
    # the chain's Jacobian column of each c3 against central differences of the tool position
    kin = rs.kinematics(R, th, jacobian=True)
    for k, i in enumerate(eff.indices):
        h = 1e-6
        tp, tm = th.copy(), th.copy()
        tp[i] += h
        tm[i] -= h
        fd = (rs.kinematics(R, tp).p - rs.kinematics(R, tm).p) / (2 * h)
        np.testing.assert_allclose(kin.J[:, :3, i], fd, rtol=1e-5, atol=1e-9)
