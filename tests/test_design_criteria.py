"""Design criteria against hand-computable cases (diagonal matrices, Klimchik's 2-link closed forms)."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.design import criteria as cr
from estcal.design.model import DesignModel
from estcal.design.update import (added_criterion_value, added_logdet_cov, added_test_pose_variance,
                                  added_trace, whiten, woodbury_covariance)
from estcal.kinematics.robots import planar2, puma560

DEG = np.pi / 180


def _rot(p, seed=0):
    Q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(p, p)))
    return Q


@pytest.mark.parametrize("rotate", [False, True])
def test_diagonal_hand_values(rotate):
    # M = diag(9, 4, 1): singular values of the whitened J are s = (3, 2, 1)
    lam = np.array([9.0, 4.0, 1.0])
    M = np.diag(lam)
    if rotate:  # every criterion is invariant to an orthogonal change of parameters
        V = _rot(3)
        M = V @ M @ V.T
    m = 4
    assert cr.cond_J(M) == pytest.approx(3.0)
    assert cr.cond_JtJ(M) == pytest.approx(9.0)
    assert cr.o1(M, m) == pytest.approx(6 ** (1 / 3) / 2)
    assert cr.o2(M) == pytest.approx(1 / 3)
    assert cr.o3(M) == pytest.approx(1.0)
    assert cr.o4(M) == pytest.approx(1 / 3)
    assert cr.o5(M) == pytest.approx(6 / 11)
    assert cr.d_criterion(M) == pytest.approx((1 / 36) ** (1 / 3))
    assert cr.a_criterion(M) == pytest.approx(1 / 9 + 1 / 4 + 1)
    assert cr.e_criterion(M) == pytest.approx(1.0)
    np.testing.assert_allclose(cr.singular_values(M), [3, 2, 1], rtol=1e-12)


def test_test_pose_and_g_on_diagonal():
    M = np.diag([4.0, 1.0])  # C = diag(1/4, 1)
    J0 = np.array([[[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]],   # variance 1/4
                   [[0.0, 2.0], [1.0, 0.0], [0.0, 0.0]]])  # variance 4·1 + 1/4
    v = cr.test_pose_variance(M, J0)
    np.testing.assert_allclose(v, [0.25, 4.25])
    assert cr.test_pose_criterion(M, J0, "mean") == pytest.approx(2.25)
    assert cr.test_pose_criterion(M, J0, "max") == pytest.approx(4.25)
    assert cr.g_criterion(M, J0) == pytest.approx(4.25)
    assert cr.criterion_value("test-pose", M, J_test=J0) == pytest.approx(2.25)
    assert cr.criterion_value("G", M, J_test=J0) == pytest.approx(4.25)


def test_singular_plans():
    M = np.diag([1.0, 0.0])
    assert np.isinf(cr.d_criterion(M)) and np.isinf(cr.a_criterion(M)) and np.isinf(cr.cond_J(M))
    assert cr.o1(M, 2) == 0 and cr.o3(M) == 0
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        cr.covariance(M)
    # the optimisation loss stays finite and orders "closer to full rank" first
    l1 = cr.criterion_loss("D", np.diag([1.0, 0.0]))
    l2 = cr.criterion_loss("D", np.diag([1.0, 1e-14]))
    assert np.isfinite(l1) and l1 > 1e5 and l2 < l1


def test_batch_equals_loop_and_information_matrix():
    rng = np.random.default_rng(1)
    J = rng.normal(size=(7, 5, 3, 4))  # 7 plans, 5 poses, 3 rows, 4 parameters
    sig = np.array([0.1, 0.2, 0.3])
    M = cr.information_matrix(J, sig)
    for b in range(7):
        A = J[b].reshape(-1, 4)
        W = np.diag(np.tile(1 / sig ** 2, 5))
        np.testing.assert_allclose(M[b], A.T @ W @ A, rtol=1e-12)
    J0 = rng.normal(size=(2, 3, 4))
    for name in cr.CRITERIA:
        batch = cr.criterion_value(name, M, m=5, J_test=J0)
        loop = [cr.criterion_value(name, M[b], m=5, J_test=J0) for b in range(7)]
        np.testing.assert_allclose(batch, loop, rtol=1e-10)
    # A = trace(C) and test-pose computed from an explicit inverse
    C = np.linalg.inv(M[0])
    assert cr.a_criterion(M[0]) == pytest.approx(np.trace(C))
    assert cr.test_pose_criterion(M[0], J0) == pytest.approx(np.mean([np.trace(j @ C @ j.T) for j in J0]))
    # the whole report
    rep = cr.evaluate_all(M[0], 5, J0, ["a", "b", "c", "d"])
    assert rep.param_std["c"] == pytest.approx(np.sqrt(C[2, 2]))
    assert rep.to_dict()["D"] == pytest.approx(np.linalg.det(C) ** 0.25)


def _two_link(free):
    return DesignModel(planar2(), "position", free, sigma=1e-3)


@pytest.mark.parametrize("free", [["a_1", "a_2"], ["offset_1", "offset_2"]])
def test_klimchik_closed_forms(free):
    """Eqs. (17)-(18): covariance and ρ0² of the 2-link arm depend only on Σ cos q2i."""
    model = _two_link(free)
    sigma = 1e-3
    rng = np.random.default_rng(3)
    q0 = np.array([[-45 * DEG, 20 * DEG]])
    J0 = model.position_jacobian(q0)
    for m in (2, 3, 5):
        Q = rng.uniform(-np.pi, np.pi, size=(m, 2))
        M = model.information(Q)
        S = np.sum(np.cos(Q[:, 1]))
        if free[0] == "a_1":  # eq. (17)
            C17 = sigma ** 2 / (m ** 2 - S ** 2) * np.array([[m, -S], [-S, m]])
            np.testing.assert_allclose(cr.covariance(M), C17, rtol=1e-9)
        rho2 = 2 * sigma ** 2 * (m - np.cos(q0[0, 1]) * S) / (m ** 2 - S ** 2)  # eq. (18)
        assert cr.test_pose_criterion(M, J0) == pytest.approx(rho2, rel=1e-9)


def test_klimchik_optimum_eq20():
    """Eq. (19)/(20): the plan with Σ cos q2i = m(1 − |sin q20|)/cos q20 reaches σ²/m · cos²q20/(1 − |sin q20|)."""
    model = _two_link(["a_1", "a_2"])
    sigma = 1e-3
    for q20 in (30, 60, 120, 150):
        q0 = np.array([[-45 * DEG, q20 * DEG]])
        J0 = model.position_jacobian(q0)
        m = 2
        target = m * (1 - abs(np.sin(q20 * DEG))) / np.cos(q20 * DEG)
        c = np.arccos(target / m)  # two configurations (0, ±c)
        Q = np.array([[0.0, -c], [0.0, c]])
        rho2 = cr.test_pose_criterion(model.information(Q), J0)
        closed = sigma ** 2 / m * np.cos(q20 * DEG) ** 2 / (1 - abs(np.sin(q20 * DEG)))
        assert rho2 == pytest.approx(closed, rel=1e-9)
        # and no symmetric plan does better (1-D scan of q2 = ±t)
        t = np.linspace(1e-3, np.pi - 1e-3, 2001)
        Qs = np.stack([np.stack([np.zeros_like(t), -t], -1), np.stack([np.zeros_like(t), t], -1)], 1)
        vals = cr.test_pose_criterion(model.information(Qs), J0)
        assert vals.min() >= closed * (1 - 1e-6)


def test_accuracy_map_matches_loop():
    model = DesignModel(puma560(), "position", ["a_2", "d_4", "offset_2", "offset_3"], sigma=1e-4)
    rng = np.random.default_rng(5)
    Q = model.random_readings(20, rng)
    C = model.covariance(Q)
    grid = model.random_readings(7, rng)
    amap = cr.accuracy_map(C, model.position_jacobian(grid), grid, model.positions(grid))
    for k, q in enumerate(grid):
        J = model.position_jacobian(q[None])[0]
        cov = J @ C @ J.T
        assert amap.std[k] == pytest.approx(np.sqrt(np.trace(cov)))
        np.testing.assert_allclose(amap.std_xyz[k], np.sqrt(np.diag(cov)))
    assert "accuracy map" in str(amap) and amap.to_dict()["summary"]["n"] == 7


def test_woodbury_updates_match_direct_inversion():
    rng = np.random.default_rng(7)
    p = 6
    A = rng.normal(size=(12, p))
    C = np.linalg.inv(A.T @ A + np.eye(p))
    H = rng.normal(size=(9, 3, p))
    sig = np.array([0.5, 1.0, 2.0])
    B = whiten(H, sig)
    direct = np.array([np.linalg.inv(np.linalg.inv(C) + b.T @ b) for b in B])
    np.testing.assert_allclose(woodbury_covariance(C, B), direct, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(added_logdet_cov(C, B), [np.linalg.slogdet(d)[1] for d in direct], rtol=1e-10)
    np.testing.assert_allclose(added_trace(C, B), np.trace(direct, axis1=1, axis2=2), rtol=1e-10)
    J0 = rng.normal(size=(2, 3, p))
    ref = np.array([[np.trace(j @ d @ j.T) for j in J0] for d in direct])
    np.testing.assert_allclose(added_test_pose_variance(C, B, J0), ref, rtol=1e-10)
    np.testing.assert_allclose(added_criterion_value("test-pose", C, B, J0), ref.mean(1), rtol=1e-10)
    np.testing.assert_allclose(added_criterion_value("G", C, B, J0), ref.max(1), rtol=1e-10)
    np.testing.assert_allclose(added_criterion_value("D", C, B),
                               [np.linalg.det(d) ** (1 / p) for d in direct], rtol=1e-10)
    # rank one (Sherman–Morrison)
    b = B[:1, :1]
    np.testing.assert_allclose(woodbury_covariance(C, b)[0], np.linalg.inv(np.linalg.inv(C) + b[0].T @ b[0]),
                               rtol=1e-9, atol=1e-12)
