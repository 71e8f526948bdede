"""Daney's constrained-leg linear methods: exactness on noise-free data, constraints, generators."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.parallel.daney import (
    add_uniform_noise,
    calibrate_leg_daney,
    daney_initial_theta,
    generate_type1,
    generate_type2,
    generate_type3,
    solve_offset,
    solve_type1,
    solve_type2,
    solve_type3,
    type1_system,
)
from estcal.base.errors import InputError
from estcal.parallel.gough import left_hand


@pytest.fixture(scope="module")
def robot():
    return left_hand()


def _leg(robot, T, k):
    P, R = T[..., :3, 3], T[..., :3, :3]
    v = P + R @ robot.b[k] - robot.a[k]
    return v, np.linalg.norm(v, axis=-1)


@pytest.mark.parametrize("k", range(6))
def test_generators_satisfy_constraints_and_limits(robot, k):
    rng = np.random.default_rng(10 + k)
    for gen, fix_dir, fix_len in ((generate_type1, True, False), (generate_type2, True, True),
                                  (generate_type3, False, True)):
        T = gen(robot, k, 6, 8, rng)
        assert robot.in_workspace(T.reshape(-1, 4, 4)).all()
        v, L = _leg(robot, T, k)
        n = v / L[..., None]
        dir_spread = np.abs(n - n[:, :1]).max()
        len_spread = np.ptp(L, axis=1).max()
        assert (dir_spread < 1e-12) == fix_dir
        assert (len_spread < 1e-12) == fix_len
        if not fix_len:
            assert np.ptp(L, axis=1).min() > 1e-3


def test_printed_a_block_sign_is_wrong_and_derived_one_is_right(robot):
    rng = np.random.default_rng(0)
    T = generate_type1(robot, 2, 1, 6, rng)[0]
    _, L = _leg(robot, T, 2)
    M, y = type1_system(T[:, :3, 3], T[:, :3, :3], L)
    x = np.concatenate([robot.b[2], robot.a[2]])
    assert np.abs(M @ x - y).max() < 1e-15
    Mp = M.copy()
    Mp[:, 3:] *= -1  # the block (rho_i - rho_{i+1}) I as printed in (5)
    assert np.abs(Mp @ x - y).max() > 1e-4


@pytest.mark.parametrize("k", range(6))
def test_noise_free_data_give_exact_parameters(robot, k):
    rng = np.random.default_rng(20 + k)
    S = 20
    T1 = generate_type1(robot, k, S, 4, rng)
    _, L1 = _leg(robot, T1, k)
    b, a, cond = solve_type1(T1[..., :3, 3], T1[..., :3, :3], L1)
    np.testing.assert_allclose(a, np.broadcast_to(robot.a[k], a.shape), atol=1e-12)
    np.testing.assert_allclose(b, np.broadcast_to(robot.b[k], b.shape), atol=1e-12)
    T2 = generate_type2(robot, k, S, 3, rng)
    b2, _ = solve_type2(T2[..., :3, 3], T2[..., :3, :3])
    np.testing.assert_allclose(b2, np.broadcast_to(robot.b[k], b2.shape), atol=1e-12)
    T3 = generate_type3(robot, k, S, 4, rng)
    a3, _ = solve_type3(T3[..., :3, 3], T3[..., :3, :3], b2)
    np.testing.assert_allclose(a3, np.broadcast_to(robot.a[k], a3.shape), atol=1e-11)
    _, L3 = _leg(robot, T3, k)
    d = solve_offset(T3[..., :3, 3], T3[..., :3, :3], L3 - robot.drho[k], a3, b2)
    np.testing.assert_allclose(d, robot.drho[k], atol=1e-11)


def test_full_calibration_all_legs_then_initial_theta(robot):
    """Six decoupled legs, method 3.3 on each: the exact 42 parameters."""
    rng = np.random.default_rng(5)
    true = robot.theta.copy()
    nominal = robot.with_theta(true + rng.normal(0, 2e-3, 42))  # what we would start from
    results = []
    for k in range(6):
        T2 = generate_type2(robot, k, 1, 5, rng)[0]
        T3 = generate_type3(robot, k, 1, 6, rng)[0]
        rho3 = robot.leg_lengths(T3)[:, k]
        results.append(calibrate_leg_daney(k + 1, type2=T2, type3=T3, offset_poses=(T3, rho3)))
    th = daney_initial_theta(nominal, results)
    np.testing.assert_allclose(th, true, atol=1e-11)
    # method 3.2 with a known offset
    T1 = generate_type1(robot, 3, 1, 5, rng)[0]
    r = calibrate_leg_daney(4, type1=(T1, robot.leg_lengths(T1)[:, 3]), drho_known=robot.drho[3])
    np.testing.assert_allclose(np.r_[r.a, r.b], np.r_[robot.a[3], robot.b[3]], atol=1e-12)
    assert "type1" in r.to_dict()["condition_numbers"]
    with pytest.raises(ValueError, match="drho_known"):
        calibrate_leg_daney(1, type1=(T1, robot.leg_lengths(T1)[:, 0]))


def test_type3_with_four_poses_is_the_sphere_through_four_points(robot):
    """Independent check with noise: N = 4 determines the sphere, so (17) must equal
    the circumcentre of the four points V_i computed by a different route."""
    rng = np.random.default_rng(6)
    T3 = add_uniform_noise(generate_type3(robot, 2, 1, 4, rng), rng, 1e-4, np.radians(0.01))[0]
    b = robot.b[2] + rng.uniform(-1e-4, 1e-4, 3)
    a, _ = solve_type3(T3[:, :3, 3], T3[:, :3, :3], b)
    V = T3[:, :3, 3] + T3[:, :3, :3] @ b
    # circumcentre: solve |V_i - c|^2 = r^2 via determinants of the lifted 4x4 system
    A = np.c_[2 * V, np.ones(4)]
    sol = np.linalg.solve(A, np.sum(V**2, axis=1))
    np.testing.assert_allclose(a, sol[:3], atol=1e-12)


def test_noise_error_decreases_with_n(robot):
    rng = np.random.default_rng(7)
    T = add_uniform_noise(generate_type2(robot, 2, 200, 20, rng), rng, 1e-4, np.radians(0.01))
    e = [np.mean(np.linalg.norm(solve_type2(T[:, :n, :3, 3], T[:, :n, :3, :3])[0] - robot.b[2], axis=-1))
         for n in (4, 8, 20)]
    assert e[0] > e[1] > e[2]
    # uniform noise of amplitude 1e-4 m: the error is of that order, not 0
    assert 1e-5 < e[2] < 1e-3


def test_generator_reports_an_infeasible_workspace(robot):
    from estcal.parallel.daney import generate_random_poses
    from estcal.parallel.gough import Workspace

    bad = robot.with_theta(robot.theta)
    bad.workspace = Workspace([-1.0, -1.0, 1.0], [1.0, 1.0, 2.0], np.radians(20))  # metres away: legs too short
    with pytest.raises(InputError, match="leg-length limits"):
        generate_random_poses(bad, 10, np.random.default_rng(0))


@pytest.mark.parametrize("model", [36, 42])
def test_experiment_ik_baseline_is_the_shared_least_squares_fit(robot, model):
    """experiments/daney_left_hand.py batches its unconstrained IK baseline (Gauss–Newton on one leg,
    over 1000 pose sets at once, for speed); each set's solution is the shared estimator's
    (calibrate_gough with lm, leg 3 free) to 1e-6 of its standard deviation."""
    from conftest import load_experiment

    from estcal.parallel.daney import generate_random_poses
    from estcal.parallel.data import GoughData
    from estcal.workflows.gough import calibrate_gough

    exp = load_experiment("daney_left_hand")
    rng = np.random.default_rng(3)
    S, N, k = 3, 12, exp.K
    T = generate_random_poses(robot, S * N, rng).reshape(S, N, 4, 4)
    Tn, rho_k = exp._noisy(rng, T, exp._leg_len(robot, T) - robot.drho[k], 1e-4, np.radians(0.01), 1e-4)
    a, b, d, ok = exp.ik_leg_gn(robot, Tn, rho_k, model)
    assert ok.all()
    free = ["a3_*", "b3_*"] + (["drho_3"] if model == 42 else [])
    for s in range(S):
        rho = robot.leg_lengths(Tn[s])
        rho[:, k] = rho_k[s]  # the other legs' rows do not involve leg 3's parameters
        res = calibrate_gough(robot, GoughData(Tn[s], rho), model=model, free=free)
        exp_x = np.r_[a[s], b[s]] if model == 36 else np.r_[a[s], b[s], d[s]]
        assert np.abs((res.estimate - exp_x) / res.std).max() < 1e-6
