"""Posture grouping, grouped folds, seen/new splits and the repeatability floor (estcal.validation)."""
import numpy as np
import pytest

from estcal.validation import (grouped_folds, n_postures, posture_groups, repeatability_floor, seen_new_scores,
                               seen_postures)


def _repeated(n_post=12, n_rep=3, jitter=2e-4, n=4, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.uniform(-2, 2, (n_post, n))
    Q = np.repeat(base, n_rep, axis=0) + rng.uniform(-jitter, jitter, (n_post * n_rep, n))
    return Q, np.repeat(np.arange(n_post), n_rep)


def test_posture_groups_recover_the_repeats_in_order_of_first_appearance():
    Q, truth = _repeated()
    perm = np.random.default_rng(1).permutation(len(Q))
    lab = posture_groups(Q[perm])
    assert n_postures(lab) == 12
    # same partition as the truth, labels numbered by first appearance
    for a in range(len(Q)):
        assert np.array_equal(lab == lab[a], truth[perm] == truth[perm][a])
    assert lab[0] == 0 and set(np.unique(lab)) == set(range(12))
    assert np.all(np.diff([np.argmax(lab == k) for k in range(12)]) > 0)


def test_tolerance_per_joint_type_and_transitivity():
    # prismatic joint 0: 0.8 mm apart agrees within 1 mm but not within 0.5 mm
    Q = np.array([[0.1000, 0.5], [0.1008, 0.5], [0.3, 0.5]])
    assert n_postures(posture_groups(Q, ["prismatic", "revolute"])) == 2
    assert n_postures(posture_groups(Q, ["prismatic", "revolute"], tol_m=5e-4)) == 3
    # a chain of rows each 0.9e-3 rad from the next is one posture (transitive agreement)
    chain = np.c_[np.arange(5) * 0.9e-3, np.zeros(5)]
    assert n_postures(posture_groups(chain)) == 1
    assert n_postures(posture_groups(chain, tol_rad=5e-4)) == 5
    with pytest.raises(ValueError, match="positive"):
        posture_groups(chain, tol_rad=0)
    with pytest.raises(ValueError, match="NaN"):
        posture_groups(np.array([[np.nan, 0.0]]))


def test_grouped_folds_never_split_a_posture_and_stay_balanced():
    Q, truth = _repeated(n_post=20, n_rep=3)
    lab = posture_groups(Q)
    folds = grouped_folds(lab, 5, rng=3)
    assert sorted(np.concatenate(folds).tolist()) == list(range(len(Q)))
    for f in folds:
        rest = np.setdiff1d(np.arange(len(Q)), f)
        assert not set(lab[f]) & set(lab[rest])
    assert max(map(len, folds)) - min(map(len, folds)) <= 3
    assert len(grouped_folds(lab, 100)) == 20  # capped: leave one posture out
    with pytest.raises(ValueError, match="2 distinct postures"):
        grouped_folds(np.zeros(4, int), 3)


def test_seen_postures_and_the_seen_new_scores():
    Q, truth = _repeated(n_post=10, n_rep=2)
    tr, te = Q[::2][:6], Q[1::2]  # training: postures 0..5 once; test: every posture once
    seen = seen_postures(tr, te)
    assert seen.tolist() == [True] * 6 + [False] * 4
    err = np.c_[np.where(seen, 1e-3, 3e-3), np.where(seen, 1e-3, 3e-3)]
    s = seen_new_scores(err, seen)
    assert s["seen"]["rmse_mm"] == pytest.approx(1.0) and s["new"]["rmse_mm"] == pytest.approx(3.0)
    assert s["seen"]["n_rows"] == 6 and not s["only_seen"]
    s2 = seen_new_scores(err[:6], seen[:6])
    assert s2["only_seen"] and s2["new"]["rmse_mm"] is None


def _sessions(sigma, rot, shift, n_post=40, n_sess=3, k=2, seed=0):
    rng = np.random.default_rng(seed)
    true = rng.uniform(-0.5, 0.5, (n_post, k, 3))
    pts, grp, ses = [], [], []
    for s in range(n_sess):
        w = rng.standard_normal(3)
        w *= rot / np.linalg.norm(w) if s else 0.0
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        from scipy.linalg import expm
        R = expm(K)
        t = rng.standard_normal(3) * shift if s else np.zeros(3)
        pts.append(true @ R.T + t + sigma * rng.standard_normal(true.shape))
        grp.append(np.arange(n_post))
        ses.append(np.full(n_post, s))
    return np.concatenate(pts), np.concatenate(grp), np.concatenate(ses)


def test_repeatability_floor_raw_and_after_rigid_registration():
    sigma = 2e-4  # per coordinate: the floor is √3 σ = 0.346 mm
    P, g, s = _sessions(sigma, rot=3e-3, shift=2e-3)
    r = repeatability_floor(P, g, s)
    assert r["registered_mm"] == pytest.approx(np.sqrt(3) * sigma * 1e3, rel=0.1)
    assert r["raw_mm"] > 3 * r["registered_mm"]
    assert r["difference_rms_mm"]["registered"] == pytest.approx(np.sqrt(2) * r["registered_mm"])
    assert r["n_repeated_postures"] == 40 and r["n_sessions"] == 3
    # sessions that did not move: raw and registered agree (registration fits only noise)
    P0, g0, s0 = _sessions(sigma, rot=0.0, shift=0.0)
    r0 = repeatability_floor(P0, g0, s0)
    assert r0["raw_mm"] == pytest.approx(np.sqrt(3) * sigma * 1e3, rel=0.1)
    assert r0["registered_mm"] == pytest.approx(r0["raw_mm"], rel=0.05)
    # nothing repeats: no floor
    assert repeatability_floor(P0[:40], g0[:40], s0[:40]) is None


def _marker_sessions(sigma, markers, n_post=25, seed=0):
    """Points of one tool point per session: p_g + R_g (m + d_s), each session rigidly moved, noise σ per
    coordinate; returns points, posture and session labels and the tool rotations."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    Rg = Rotation.random(n_post, random_state=seed).as_matrix()
    pg = rng.uniform(-0.5, 0.5, (n_post, 3))
    m = np.array([0.04, -0.02, 0.12])
    P, g, s, R = [], [], [], []
    for sv, d in enumerate(markers):
        Rs = Rotation.from_rotvec(rng.standard_normal(3) * 3e-3).as_matrix() if sv else np.eye(3)
        ts = rng.standard_normal(3) * 2e-3 if sv else np.zeros(3)
        pts = (pg + np.einsum("nij,j->ni", Rg, m + np.asarray(d)))[:, None, :]
        P.append(pts @ Rs.T + ts + sigma * rng.standard_normal(pts.shape))
        g.append(np.arange(n_post))
        s.append(np.full(n_post, sv))
        R.append(Rg)
    return np.concatenate(P), np.concatenate(g), np.concatenate(s), np.concatenate(R)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_repeatability_with_a_different_tool_point_per_session(seed):
    # three sessions, each measuring its own point of the tool (3–5 cm apart, like a marker glued anew):
    # after a rigid registration the spread is the distance between the points, not repeatability; removing
    # each session's point too recovers the floor √3 σ
    sigma = 2e-4
    P, g, s, R = _marker_sessions(sigma, [(0, 0, 0), (0.03, 0.02, -0.01), (-0.02, 0.04, 0.02)], seed=seed)
    r = repeatability_floor(P, g, s, tool_rotations=R)
    assert r["registered_mm"] > 10 * np.sqrt(3) * sigma * 1e3
    assert r["registered_points_mm"] == pytest.approx(np.sqrt(3) * sigma * 1e3, rel=0.2)
    assert r["registered_points_reason"] is None
    assert r["registered_mm"] == repeatability_floor(P, g, s)["registered_mm"]  # the rigid figure is unchanged
    # the same point in every session: both figures are the floor
    P1, g1, s1, R1 = _marker_sessions(sigma, [(0, 0, 0)] * 3, seed=seed)
    r1 = repeatability_floor(P1, g1, s1, tool_rotations=R1)
    assert r1["registered_mm"] == pytest.approx(np.sqrt(3) * sigma * 1e3, rel=0.2)
    assert r1["registered_points_mm"] == pytest.approx(r1["registered_mm"], rel=0.1)


@pytest.mark.parametrize("seed", [3, 4])
def test_repeatability_with_joint_zeros_moved_per_session(seed):
    # three sessions of 30 postures (three points each), each session rigidly moved and its two joint zeros moved
    # by a few mrad through the points' derivatives J_g (0.1–0.6 m/rad, different at every posture): after a
    # rigid registration the spread is the zeros' move, not repeatability; removing each session's zeros too
    # recovers the floor √3 σ. With no zero moved both figures are the floor.
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    sigma, n_post, k = 1e-4, 30, 3
    c = rng.uniform(-0.5, 0.5, (n_post, k, 3))
    J = rng.uniform(0.1, 0.6, (n_post, k, 3, 2)) * rng.choice([-1, 1], (n_post, k, 3, 2))

    def sessions(move):
        P, g, s, JJ = [], [], [], []
        for sv in range(3):
            z = rng.uniform(2e-3, 4e-3, 2) * rng.choice([-1, 1], 2) if (sv and move) else np.zeros(2)
            Rs = Rotation.from_rotvec(rng.standard_normal(3) * 3e-3).as_matrix() if sv else np.eye(3)
            ts = rng.standard_normal(3) * 2e-3 if sv else np.zeros(3)
            P.append((c + J @ z) @ Rs.T + ts + sigma * rng.standard_normal(c.shape))
            g.append(np.arange(n_post))
            s.append(np.full(n_post, sv))
            JJ.append(J)
        return np.concatenate(P), np.concatenate(g), np.concatenate(s), np.concatenate(JJ)

    P, g, s, JJ = sessions(True)
    r = repeatability_floor(P, g, s, zero_jacobians=JJ)
    assert r["registered_mm"] > 5 * np.sqrt(3) * sigma * 1e3
    assert r["registered_zeros_mm"] == pytest.approx(np.sqrt(3) * sigma * 1e3, rel=0.2)
    assert r["registered_zeros_reason"] is None
    P0, g0, s0, J0 = sessions(False)
    r0 = repeatability_floor(P0, g0, s0, zero_jacobians=J0)
    assert r0["registered_mm"] == pytest.approx(np.sqrt(3) * sigma * 1e3, rel=0.2)
    assert r0["registered_zeros_mm"] == pytest.approx(r0["registered_mm"], rel=0.1)


def test_repeatability_per_session_point_refused_when_the_tool_never_turns():
    # the tool keeps one orientation at every repeated posture: its point cannot be told from the frame
    P, g, s, R = _marker_sessions(2e-4, [(0, 0, 0), (0.03, 0.02, -0.01)])
    R[:] = np.eye(3)
    r = repeatability_floor(P, g, s, tool_rotations=R)
    assert r["registered_points_mm"] is None and "orientation" in r["registered_points_reason"]
    one = repeatability_floor(P[:25], g[:25], s[:25] * 0, tool_rotations=R[:25])
    assert one is None  # one session, nothing repeats
    few = repeatability_floor(P[[0, 1, 25, 26]], g[[0, 1, 25, 26]], s[[0, 1, 25, 26]], tool_rotations=R[[0, 1, 25, 26]])
    assert few["registered_points_mm"] is None and few["registered_points_reason"]


def test_validation_split_flags_a_validation_of_seen_postures_only():
    from estcal.validation import validation_split

    Q, _ = _repeated(n_post=8, n_rep=2)
    tr, te = Q[::2], Q[1::2]  # the same 8 postures measured again
    out = validation_split(tr, te, np.full((8, 2), 1e-3))
    assert out["only_seen"] and "memory" in out["warning"]
    new = np.random.default_rng(5).uniform(-1, 1, (3, 4))
    out2 = validation_split(tr, np.vstack([te, new]), np.full((11, 2), 1e-3))
    assert out2["warning"] is None and out2["new"]["n_rows"] == 3 and out2["seen"]["n_rows"] == 8


def test_calibrate_splits_its_validation_into_seen_and_new_postures():
    import warnings

    from estcal.base.errors import EstcalWarning
    from estcal.simulate import simulate
    from estcal.workflows.calibrate import calibrate

    sim = simulate("puma560", n_poses=30, measure="position", errors="random", seed=3,
                   noise={"position": 1e-4})
    again = simulate("puma560", readings=sim.dataset.readings[:10], measure="position", errors="random", seed=3,
                     noise={"position": 1e-4})  # ten of the training postures, measured again
    again.dataset.points = again.dataset.points + 1e-4 * np.random.default_rng(9).standard_normal((10, 1, 3))
    fresh = simulate("puma560", readings=sim.nominal_robot.random_readings(8, np.random.default_rng(7)),
                     measure="position", errors="random", seed=3, noise={"position": 1e-4})
    mixed = again.dataset.subset(slice(None))
    for k in ("readings", "points"):
        setattr(mixed, k, np.concatenate([getattr(again.dataset, k), getattr(fresh.dataset, k)]))
    mixed.lines = np.arange(2, 20)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        cal = calibrate("puma560", sim.dataset, level="full", validate=[again.dataset, mixed])
    v_seen, v_mixed = cal.result.accuracy["validation"]
    assert v_seen["only_seen"] and v_seen["seen"]["n_rows"] == 10 and v_seen["new"]["rmse_mm"] is None
    assert any(issubclass(x.category, EstcalWarning) and "memory" in str(x.message) for x in w)
    assert not v_mixed["only_seen"] and (v_mixed["seen"]["n_rows"], v_mixed["new"]["n_rows"]) == (10, 8)
    assert "seen" in cal.result.to_dict()["accuracy"]["validation"][1]


def test_inside_ranges_marks_rows_beyond_any_training_joint_range():
    """A row is inside when every joint reading lies in the training span of that joint (bounds included)."""
    from estcal.validation import inside_ranges

    train = np.array([[0.0, -1.0], [1.0, 1.0], [0.5, 0.0]])
    rows = np.array([[0.5, 0.5], [0.0, -1.0], [1.0001, 0.0], [0.5, -1.2], [-0.1, 2.0]])
    assert inside_ranges(train, rows).tolist() == [True, True, False, False, False]


def test_rmse_standard_error_over_postures_matches_a_bootstrap_of_postures():
    """rmse_se_mm (ratio estimator over postures, δ-method) against an independent computation: the spread of the
    RMSE over bootstrap resamples of the postures, on errors with a shared part per posture (rows of one posture
    are not independent: a row-level formula would be too small), and the row-level case within it."""
    from estcal.validation import rmse_mm, rmse_se_mm

    rng = np.random.default_rng(7)
    G = 40
    reps = rng.integers(1, 4, G)  # 1–3 rows per posture
    groups = np.repeat(np.arange(G), reps)
    shared = rng.normal(0, 2e-3, (G, 1))[groups]  # a posture's own error, m
    errors = np.abs(shared + rng.normal(0, 0.3e-3, (len(groups), 2)))  # (M, k=2) point-error norms
    se = rmse_se_mm(errors, groups)
    boot = []
    for _ in range(4000):
        pick = rng.integers(0, G, G)
        rows = np.concatenate([np.flatnonzero(groups == g) for g in pick])
        boot.append(rmse_mm(errors[rows]))
    assert se == pytest.approx(np.std(boot), rel=0.12)
    # treating the rows as independent would understate it: the postures are the units
    assert rmse_se_mm(errors, np.arange(len(groups))) < 0.9 * se
    assert rmse_se_mm(errors[:1], [0]) is None  # one posture: no spread to judge by
