"""The helpers of the TIAGo study scripts, on synthetic data against independent computations (no shared data
needed): ``experiments/tiago_disjoint.py``'s summaries of its halvings, and ``experiments/tiago_limits.py``'s
part 2 (the rebuilt sessions) and part 4 (what the residual is not a function of)."""
import argparse
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import load_experiment
from scipy.spatial.transform import Rotation


@pytest.fixture(scope="module")
def td():
    return load_experiment("tiago_disjoint")


@pytest.fixture(scope="module")
def tl():
    return load_experiment("tiago_limits")


def test_seed_sets_by_name_all_or_list_and_a_clear_error(td):
    assert td.seed_set("development") == (0, 1, 2, 3, 4, 5)
    assert td.seed_set("confirmation10") == (200, 201, 202)
    every = td.seed_set("all")
    assert len(every) == 36 and len(set(every)) == 36  # 72 halvings: both directions of each seed
    assert every[:6] == (0, 1, 2, 3, 4, 5) and every[-3:] == (200, 201, 202)
    assert td.seed_set("7, 8") == (7, 8)
    with pytest.raises(argparse.ArgumentTypeError, match="neither a seed set"):
        td.seed_set("confirmaton2")


def test_attainable_within_against_monte_carlo(td):
    """The chance that a prediction equal to the expected RMSE lands within 30 % of a measured RMSE that scatters
    normally about it with the given standard error, summed over halvings — checked by drawing the measured RMSE."""
    rows = [{"new_mm": 2.0, "new_se_mm": 0.3}, {"new_mm": 3.0, "new_se_mm": 0.9}, {"new_mm": 1.5, "new_se_mm": None}]
    rng = np.random.default_rng(0)
    mc = 1.0  # no standard error: counted as within
    for r in rows[:2]:
        a = rng.normal(r["new_mm"], r["new_se_mm"], 400_000)
        mc += np.mean(np.abs(r["new_mm"] / a - 1) <= 0.3)
    assert td.attainable_within(rows) == pytest.approx(mc, abs=3e-3)


def test_named_counts_count_each_cause_once_per_halving_and_the_most_common_list(td):
    rows = [{"named": ["a", "b"]}, {"named": ["b", "a"]}, {"named": ["a"]}, {"named": ["a", "a"]}, {"named": []},
            {"named": ["b", "a"]}]
    out = td.named_counts(rows)
    assert out["causes"] == {"a": 5, "b": 3}
    assert list(out["causes"]) == ["a", "b"]  # most often first
    assert out["most_common_list"] == ["a", "b"]  # the order within a list does not matter
    assert out["most_common_list_count"] == 3


def test_rigid_motion_of_a_body_against_scipys_alignment(tl):
    """Each posture's small rigid motion from its points' residual equals the rotation and translation scipy's
    Kabsch alignment finds between the body before and after (to second order in the angle)."""
    rng = np.random.default_rng(0)
    pts = _bodies(rng, rng.normal(0, 0.08, (4, 3)), 5)
    w = rng.normal(0, 3e-3, (5, 3))  # rad
    t = rng.normal(0, 1e-3, (5, 3))  # m
    c = pts.mean(axis=1, keepdims=True)
    moved = np.stack([Rotation.from_rotvec(w[i]).apply(pts[i] - c[i]) for i in range(5)]) + c + t[:, None]
    got = tl._rigid(moved - pts, pts)
    for i in range(5):
        rot, _ = Rotation.align_vectors(moved[i] - moved[i].mean(0), pts[i] - c[i])
        assert got[i, :3] == pytest.approx(rot.as_rotvec() * 1e3, abs=0.02)  # mrad; second order: ~(3 mrad)²
        assert got[i, 3:] == pytest.approx((moved[i].mean(0) - c[i, 0]) * 1e3, abs=1e-9)  # mm, exact


def _sessions(rng, n=(20, 30), joints=("j1", "j2", "j3")):
    out = {}
    for k, m in enumerate(n):
        q = np.cumsum(rng.normal(0, 0.3, (m, len(joints))), axis=0)
        cols = {j: rng.normal(0, 1e-3 * (i + 1), (m, 4, 3)) for i, j in enumerate(joints)}
        out[f"s{k}"] = (SimpleNamespace(n=m, readings=q, joint_names=list(joints),
                                        columns={"marker_std_mm": rng.uniform(0.05, 0.5, m)}), cols)
    return out


def _screen(tl, rng, sessions, residual, permutations=199):
    model = {"residual": residual, "joint_columns": {k: v[1] for k, v in sessions.items()}}
    data = {k: v[0] for k, v in sessions.items()}
    grp = np.concatenate([np.full(d.n - 1, i) for i, d in enumerate(data.values())])
    perms = [np.arange(len(grp))] + [np.concatenate([rng.permutation(np.flatnonzero(grp == g)) for g in range(2)])
                                     for _ in range(permutations)]
    feats = {k: tl._path_features(d) for k, d in data.items()}
    return tl._joint_screen(data, model, feats, perms, grp), data, grp


def test_joint_screen_share_is_the_least_squares_fit_of_one_joint_error(tl):
    """The screen's share for every (joint, feature) pair is 1 − ‖r − c x‖²/‖r‖² with c by numpy's least squares on
    the regressor x_i = f_i ∂x/∂q_j (f standardised within each session), and the largest is reported."""
    rng = np.random.default_rng(1)
    sessions = _sessions(rng)
    residual = {k: rng.normal(0, 1e-3, (v[0].n, 4, 3)) for k, v in sessions.items()}
    out, data, grp = _screen(tl, rng, sessions, residual)
    r = np.concatenate([residual[k][1:].ravel() for k in data])
    best = 0.0
    for j in ("j1", "j2", "j3"):
        for name in ("move", "move size", "move before", "previous reading"):
            f = np.concatenate([tl._path_features(d)[f"{j} {name}"][1:] for d in data.values()])
            f = tl._standardise(f[:, None], grp)[:, 0]
            x = np.concatenate([(f[grp == i][:, None, None] * sessions[k][1][j][1:]).ravel()
                                for i, k in enumerate(data)])
            c = np.linalg.lstsq(x[:, None], r, rcond=None)[0]
            best = max(best, 1 - np.sum((r - x * c) ** 2) / np.sum(r ** 2))
    assert out["pairs"] == 12
    assert out["largest_share"] == pytest.approx(best, rel=1e-9)
    assert out["p_value"] > 0.05  # noise: nothing found (this seed; the figure is a permutation p-value)


def test_joint_screen_finds_a_path_error_it_is_given(tl):
    """A joint error proportional to the direction of the move before (a hysteresis with a longer memory), added
    to noise, is found: the right joint and feature, the least p-value the permutations allow; and the screen's
    power finds an error of that size on that joint."""
    rng = np.random.default_rng(2)
    sessions = _sessions(rng)
    residual = {}
    for k, (d, cols) in sessions.items():
        f = tl._path_features(d)["j2 move before"]
        residual[k] = rng.normal(0, 2e-4, (d.n, 4, 3)) + 0.3 * f[:, None, None] * cols["j2"]
    out, _, _ = _screen(tl, rng, sessions, residual)
    assert out["feature"] == "j2 move before"
    assert out["largest_share"] > 0.5
    assert out["p_value"] == pytest.approx(1 / 200)
    assert out["found_from"]["j2"] is not None


def test_permutation_p_value_counts_the_observed_statistic(tl):
    assert tl._p_value(np.array([5.0, 1.0, 2.0, 6.0])) == pytest.approx(2 / 4)
    assert tl._p_value(np.array([9.0, 1.0, 2.0, 3.0])) == pytest.approx(1 / 4)


def _bodies(rng, body, n):
    """``n`` poses (n, 4, 3) of the rigid ``body`` (4, 3): random orientations, positions within about half a metre."""
    return np.stack([Rotation.random(random_state=i).apply(body) + rng.normal(0, 0.5, 3) for i in range(n)])


def _moved(motion, pts):
    """The points' displacement (n, 4, 3) under each body's small rigid motion ``motion`` (n, 6): (ω rad, t m) about
    its centroid."""
    arm = pts - pts.mean(axis=1, keepdims=True)
    return motion[:, None, 3:] + np.cross(motion[:, None, :3], arm)


class _Data(SimpleNamespace):
    def subset(self, _):
        return _Data(**vars(self))


def test_rebuilt_sessions_move_each_body_by_a_real_rigid_residual_or_a_draw_of_psi(tl):
    """``permuted``: each posture's points move off the model's prediction by the real rigid residual of a posture
    of the same session (centred), as :func:`_rigid` reads it back, every one used once; ``rigid-sessions``: by
    Gaussian draws whose translation and rotation spreads are Ψ's (translation first in Ψ, as the relevance
    model's random effect)."""
    rng = np.random.default_rng(3)
    n = 400
    meas = _bodies(rng, rng.normal(0, 0.08, (4, 3)), n)
    real = np.c_[rng.normal(0, 5e-3, (n, 3)), rng.normal(0, 1e-3, (n, 3))]  # (ω rad, t m)
    resid = _moved(real, meas)
    data = _Data(n=n, points=meas)
    model = {"residual": {"s": resid}}
    out = tl._rebuilt(data, model, "s", "permuted", None, 0.0, seed=5)
    pred = meas - resid
    got = tl._rigid(out.points - pred, pred) * 1e-3
    want = tl._rigid(resid, meas) * 1e-3
    want -= want.mean(axis=0)
    order = np.lexsort(got.T)
    assert np.allclose(got[order], want[np.lexsort(want.T)], atol=1e-12)
    assert not np.allclose(got, want)  # permuted, not in place
    psi = np.array([1e-6, 4e-6, 9e-6, 1e-5, 4e-5, 9e-5])  # translation (m²), then rotation (rad²)
    out = tl._rebuilt(data, model, "s", "rigid-sessions", psi, 0.0, seed=6)
    drawn = tl._rigid(out.points - pred, pred) * 1e-3  # (ω, t)
    assert drawn.std(axis=0) == pytest.approx(np.sqrt(np.r_[psi[3:], psi[:3]]), rel=0.15)


def test_gaussian_rebuilt_sessions_draw_the_real_residuals_covariance_or_its_diagonal(tl):
    """``gaussian``: the drawn rigid motions have the real residuals' covariance, correlations included;
    ``gaussian-diag``: the same variances and no correlation."""
    rng = np.random.default_rng(4)
    n = 3000
    meas = _bodies(rng, rng.normal(0, 0.08, (4, 3)), n)
    mix = np.eye(6) + 0.6 * np.eye(6, k=3) + 0.6 * np.eye(6, k=-3)  # each rotation correlates with a translation
    real = rng.normal(0, 1, (n, 6)) @ mix * np.r_[[5e-3] * 3, [1e-3] * 3]  # (ω rad, t m)
    resid = _moved(real, meas)
    data = _Data(n=n, points=meas)
    model = {"residual": {"s": resid}}
    pred = meas - resid
    want = np.cov(real.T)
    for kind, target in (("gaussian", want), ("gaussian-diag", np.diag(np.diag(want)))):
        out = tl._rebuilt(data, model, "s", kind, None, 0.0, seed=7)
        got = np.cov((tl._rigid(out.points - pred, pred) * 1e-3).T)
        scale = np.sqrt(np.outer(np.diag(want), np.diag(want)))
        assert np.abs(got - target).max() / scale.max() < 0.08, kind


def test_rigid_shape_against_gaussian_and_heavy_tailed_samples(tl):
    """Mardia's kurtosis is p(p + 2) = 48 for six Gaussian components (large sample), inside its Gaussian range for a
    Gaussian sample of 60, and far above it for Student t (3 degrees of freedom) of the same size."""
    rng = np.random.default_rng(8)
    big = tl.rigid_shape(rng.normal(size=(20000, 6)), draws=10)
    assert big["mardia_kurtosis"] == pytest.approx(48.0, rel=0.03) and big["gaussian_kurtosis"] == 48.0
    g = tl.rigid_shape(rng.normal(size=(60, 6)) @ np.triu(np.ones((6, 6))))
    lo, hi = g["gaussian_range"]
    assert lo < g["mardia_kurtosis"] < hi and g["max_abs_correlation"] > 0.5
    t = tl.rigid_shape(rng.standard_t(3, size=(60, 6)))
    assert t["mardia_kurtosis"] > hi


def test_shared_permutation_keeps_a_shared_posture_s_error_the_same_in_both_sessions(tl):
    """``permuted-shared``: every row takes another row's residual, each row used once per session; a posture both
    sessions measured takes, in both, the residual of one and the same posture; a posture of one session alone
    takes that of another posture of that session alone."""
    rng = np.random.default_rng(9)
    postures = rng.uniform(-2, 2, (30, 4))
    a_rows, b_rows = rng.permutation(20), rng.permutation(30)  # postures 0–19 in both, 20–29 in b only
    a, b = _Data(n=20, readings=postures[a_rows]), _Data(n=30, readings=postures[b_rows])
    robot = SimpleNamespace(joint_types=["revolute"] * 4)
    src = tl._shared_permutation(robot, {"11-30": a, "11-26": b}, seed=1)
    for s, rows in (("11-30", a_rows), ("11-26", b_rows)):
        assert sorted(src[s]) == list(range(len(rows)))  # a permutation of the session's rows
    taken_a = dict(zip(a_rows, a_rows[src["11-30"]]))  # posture → the posture whose residual it takes
    taken_b = dict(zip(b_rows, b_rows[src["11-26"]]))
    assert all(taken_a[p] == taken_b[p] for p in range(20))
    assert all(taken_b[p] >= 20 for p in range(20, 30))
    assert sum(taken_b[p] != p for p in range(30)) > 20  # moved, not in place


def test_residual_shrink_is_the_share_of_each_component_s_variance_a_refit_keeps(tl, monkeypatch):
    """A refit that keeps 0.9 of the rotation and 0.8 of the translation of every simulated error (standing in for the
    two-session diagnosis) gives variance shares 0.81 and 0.64, whatever the draws."""
    import estcal.discrepancy.feedback as feedback

    rng = np.random.default_rng(10)
    body = rng.normal(0, 0.08, (4, 3))
    sessions, resid = {}, {}
    for k, n in (("a", 150), ("b", 200)):
        meas = _bodies(rng, body, n)
        real = np.c_[rng.normal(0, 5e-3, (n, 3)), rng.normal(0, 1e-3, (n, 3))]
        resid[k] = _moved(real, meas)
        sessions[k] = _Data(n=n, points=meas)
    model = {"residual": resid, "fit": None}
    monkeypatch.setattr(feedback, "load_fit", lambda fit: {"random_effect": {"sigma_mm": 0.0, "psi_si": [0.0] * 6}})

    def refit(robot, sims):
        out = {}
        for k, sim in sims.items():
            pred = np.asarray(sessions[k].points) - resid[k]
            e = tl._rigid(np.asarray(sim.points) - pred, np.asarray(sim.points)) * 1e-3 * np.r_[[0.9] * 3, [0.8] * 3]
            out[k] = _moved(e, np.asarray(sim.points))
        return {"residual": out, "fit": SimpleNamespace(causes=[SimpleNamespace(label="drift of j1")])}

    monkeypatch.setattr(tl, "two_session_model", refit)
    got = tl.residual_shrink(None, sessions, model, seeds=(1, 2))
    assert got["variance_kept"] == pytest.approx([0.81] * 3 + [0.64] * 3, rel=1e-6)
    assert got["named"] == [["drift of j1"], ["drift of j1"]]


def test_named_line_tells_the_truth_s_causes_its_unnamed_terms_and_false_causes(tl, monkeypatch):
    import estcal.discrepancy.feedback as feedback

    effects = [{"effect": "backlash", "joints": ["arm_6_joint"], "options": {"by": "approach"}},
               {"effect": "joint_compliance", "joints": ["arm_6_joint"]},
               {"effect": "link_tilt", "joints": ["arm_1_joint"]}]
    monkeypatch.setattr(feedback, "load_fit", lambda fit: {"model": {"effects": effects}})
    terms = tl._term_labels(None)
    assert terms == ["backlash (by approach) of arm_6_joint", "joint compliance of arm_6_joint",
                     "link tilt of arm_1_joint"]
    truth = terms[:2]
    named = [[terms[0]], [terms[0], terms[2]], ["drift of arm_3_joint", terms[1]], []]
    line = tl._named_line(named, truth, terms)
    assert line == ("of its 4 halvings named: backlash (by approach) of arm_6_joint 2, joint compliance of arm_6_joint 1; "
                    "a term it holds unnamed in 1; a cause it does not hold in 1 (drift of arm_3_joint)")


def test_drift_screen_recovers_a_joint_drift_it_is_given_and_not_one_it_is_not(tl):
    """A residual holding ``c · t`` along joint b's column in session "s" (and noise): the screen picks b there, its
    slope is the least-squares one (numpy's lstsq on the stacked points), p is small; in the other session, noise
    alone, p is not."""
    rng = np.random.default_rng(11)
    sessions, model = {}, {"residual": {}, "joint_columns": {}}
    for label, n, c in (("s", 60, 2e-5), ("u", 50, 0.0)):
        t0 = np.sort(rng.uniform(0, 900, n))
        sessions[label] = _Data(n=n, columns={"t_start_robot": t0, "t_end_robot": t0 + 4.0})
        cols = {j: rng.normal(0, 0.3, (n, 4, 3)) for j in ("a", "b", "c")}
        t = t0 + 2.0 - (t0[1:] + 2.0).mean()
        model["residual"][label] = c * t[:, None, None] * cols["b"] + rng.normal(0, 1e-3, (n, 4, 3))
        model["joint_columns"][label] = cols
    grp = np.r_[np.zeros(59, int), np.ones(49, int)]
    perms = [np.arange(108)] + [np.r_[rng.permutation(59), 59 + rng.permutation(49)] for _ in range(400)]
    out = tl._drift_screen(sessions, model, perms, grp)
    s = out["s"]
    X = (model["joint_columns"]["s"]["b"][1:] * (sessions["s"].columns["t_start_robot"][1:] + 2.0
                                                  - (sessions["s"].columns["t_start_robot"][1:] + 2.0).mean())[:, None, None])
    want = np.linalg.lstsq(X.reshape(-1, 1), model["residual"]["s"][1:].ravel(), rcond=None)[0][0]
    assert s["joint"] == "b" and s["slope_mrad_per_s"] == pytest.approx(want * 1e3, rel=1e-9)
    assert s["p_value"] < 0.01 and out["u"]["p_value"] > 0.05


def test_all_is_every_set_declared_before_the_eleventh(td):
    later = {"confirmation11": (220, 221, 222), "confirmation12": (240, 241, 242), "confirmation13": (260, 261, 262),
             "confirmation14": (280, 281, 282), "confirmation15": (300, 301, 302)}
    for name, seeds in later.items():
        assert td.seed_set(name) == seeds
        assert not set(seeds) & set(td.seed_set("all"))
    assert len(td.seed_set("all")) == 36
    assert set(td.seed_set("all")) | {s for v in later.values() for s in v} == {s for v in td.SEED_SETS.values()
                                                                               for s in v}
