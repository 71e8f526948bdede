"""Bounded memory (docs/reliability.md, "Memory"): the chunked paths give the unchunked results —
the R-factor identifiability analysis, the chunked tool poses, the numeric fast path of the loader."""
from pathlib import Path

import numpy as np
import pytest

from estcal.identify.select import identifiable, observation_matrix, reduced_observation_matrix
from estcal.io import dataset as D
from estcal.kinematics.chunked import tool_poses
from estcal.kinematics.robots import get_builtin
from estcal.methods import NoiseModel, Problem
from estcal.simulate import simulate


def _problem(n=700, seed=3):
    sim = simulate("puma560", n_poses=n, measure="pose", errors="random",
                   noise={"position": 5e-5, "orientation": 5e-4}, seed=seed)
    noise = NoiseModel(position=5e-5, orientation=5e-4)
    return Problem(sim.nominal_robot, [(None, sim.dataset, noise)], noise), sim


def test_reduced_identifiability_equals_full():
    prob, _ = _problem()
    names = list(prob.params.names)
    W, _ = observation_matrix(prob, names)
    R, _, m = reduced_observation_matrix(prob, names, chunk=128)  # 6 chunks
    assert m == W.shape[0] and R.shape == (len(names), len(names))
    # same Gram matrix: RᵀR = WᵀW (the chunked QR is exact up to round-off)
    G = W.T @ W
    assert np.allclose(R.T @ R, G, rtol=1e-10, atol=1e-10 * np.abs(G).max())
    a = identifiable(W, names)
    b = identifiable(R, names, n_rows=m)
    assert a.identifiable == b.identifiable and a.no_effect == b.no_effect
    assert [r["parameter"] for r in a.regrouped] == [r["parameter"] for r in b.regrouped]
    assert np.allclose(a.beta, b.beta, rtol=1e-8, atol=1e-10)
    assert abs(a.condition_number - b.condition_number) <= 1e-10 * a.condition_number
    assert a.n_rows == b.n_rows


def test_chunked_tool_poses_are_identical():
    rb = get_builtin("puma560")
    q = rb.random_readings(1000, np.random.default_rng(1))
    k = rb.kinematics(q, jacobian=False)
    c = tool_poses(rb, q, fields=("R", "p"), chunk=97)
    assert np.array_equal(c["R"], k.R) and np.array_equal(c["p"], k.p)


def test_numeric_fast_path_gives_the_text_path_dataset(tmp_path):
    from estcal.base.textinput import read_csv

    _, sim = _problem(n=6000, seed=4)  # > 1 MiB: the fast path is taken
    path = tmp_path / "big.csv"
    sim.write(path)
    assert path.stat().st_size > (1 << 20)
    rb = sim.nominal_robot
    fast = D._read_numeric(Path(path))
    assert fast is not None and fast.numeric.shape[0] == 6000
    a = D.dataset_from_table(fast, rb)
    b = D.dataset_from_table(read_csv(path, "dataset", D.DatasetError), rb)
    for f in ("readings", "R", "p", "lines"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    # anything unusual goes to the text path (which names the problem)
    lines = path.read_text().splitlines(keepends=True)
    lines[100] = lines[100].replace(",", ",x", 1)
    path.write_text("".join(lines))
    assert D._read_numeric(Path(path)) is None


def test_chunked_least_squares_equals_unchunked():
    """The bounded-memory path (R factor built 100 poses at a time) gives the unchunked estimate and
    covariance to 1e-10 relative (lm, gauss-newton, iterated-lls) and the same free set."""
    from estcal.estimate.levels import select_free
    from estcal.estimate.lsq import calibrate_lsq

    prob, _ = _problem(n=300, seed=5)
    sel = select_free(prob, "full")
    sel_c = None
    import estcal.methods.reduced as red

    old = red.CHUNK_POSES
    red.CHUNK_POSES = 100  # force the chunked path of select_free on 300 poses
    try:
        sel_c = select_free(prob, "full")
    finally:
        red.CHUNK_POSES = old
    assert sel_c.identifiable == sel.identifiable and sel_c.regrouped.keys() == sel.regrouped.keys()
    assert abs(sel_c.condition_number - sel.condition_number) < 1e-8 * sel.condition_number
    start = prob.with_values(sel.theta)
    for method in ("lm", "gauss-newton", "iterated-lls"):
        a = calibrate_lsq(start, method, free=sel.identifiable)
        b = calibrate_lsq(start, method, free=sel.identifiable, chunk=100)
        assert "chunk_poses" in b.extra and "chunk_poses" not in a.extra
        assert a.n_iterations == b.n_iterations
        assert np.allclose(b.estimate, a.estimate, rtol=1e-10, atol=1e-10 * np.abs(a.estimate).max()), method
        assert np.allclose(b.covariance, a.covariance, rtol=1e-8, atol=1e-10 * np.abs(a.covariance).max())
        assert b.dof == a.dof and np.isclose(b.chi2, a.chi2, rtol=1e-10)
        assert b.problem is not None and np.array_equal(b.robot().params.values, b.theta)
    # with a Gaussian prior (MAP): the prior rows are appended to R as they are to the full system
    tau = {n: 1e-4 for n in sel.identifiable if not n.startswith("base_")}
    a = calibrate_lsq(start, "lm", free=sel.identifiable, prior_std=tau)
    b = calibrate_lsq(start, "lm", free=sel.identifiable, prior_std=tau, chunk=100)
    assert "chunk_poses" in b.extra and a.n_iterations == b.n_iterations
    assert np.allclose(b.estimate, a.estimate, rtol=1e-10, atol=1e-10 * np.abs(a.estimate).max())
    assert np.allclose(b.covariance, a.covariance, rtol=1e-8, atol=1e-10 * np.abs(a.covariance).max())
    pa, pb = a.extra["prior"], b.extra["prior"]
    assert np.isclose(pa["effective_parameters"], pb["effective_parameters"], rtol=1e-9)
    assert pa["effective_parameters"] < len(sel.identifiable) - 1  # the prior is felt


def test_online_default_free_set_unchanged_by_chunking(monkeypatch):
    """`estcal online FILE` without --free picks an identifiable set from the whole file: on large
    files from the chunked R factor — the same set (forced here with a 100-pose chunk)."""
    import estcal.methods.reduced as red
    from estcal.identify import select_identifiable

    prob, _ = _problem(n=300, seed=6)
    a = select_identifiable(prob).identifiable
    monkeypatch.setattr(red, "CHUNK_POSES", 100)
    assert select_identifiable(prob).identifiable == a and len(a) > 20


def test_chunked_robust_fit_and_outlier_report_equal_unchunked(monkeypatch):
    """Iteratively reweighted (robust) least squares on the chunked R factor — row weights sliced
    chunk by chunk — gives the unchunked estimate, weights and named outlier rows."""
    import estcal.methods.reduced as red
    from estcal.estimate.levels import select_free
    from estcal.estimate.levels import robust_report
    from estcal.estimate.lsq import calibrate_lsq
    from estcal.estimate.robust import group_norms

    prob, sim = _problem(n=300, seed=7)
    ds = sim.dataset
    bad = [11, 150, 299]
    ds.p[bad] += np.array([4e-3, -3e-3, 5e-3])[:, None]  # gross errors of 3–5 mm (≥ 60 σ)
    sel = select_free(prob, "full")
    start = prob.with_values(sel.theta)
    a = calibrate_lsq(start, "lm", free=sel.identifiable, robust="cauchy")
    ra = robust_report(start, a, "cauchy")
    na = group_norms(start, a.theta)
    monkeypatch.setattr(red, "CHUNK_POSES", 70)  # 5 chunks, the last one partial
    assert red.use_chunks(start) == 70
    b = calibrate_lsq(start, "lm", free=sel.identifiable, robust="cauchy")
    assert b.extra.get("chunk_poses") == 70
    # IRLS stops when the weights or the estimate move by < 1e-6 (σ): round-off between the two
    # paths can end it an iteration or two apart, so they agree to that tolerance, not to 1e-10
    assert np.max(np.abs(b.estimate - a.estimate) / a.std) < 1e-5
    assert np.allclose(b.covariance, a.covariance, rtol=1e-4, atol=1e-6 * np.abs(a.covariance).max())
    assert np.isclose(b.chi2, a.chi2, rtol=1e-8)
    nb = group_norms(start, a.theta)
    for x, y in zip(na, nb):
        assert np.allclose(x, y, rtol=1e-12, atol=0)
    rb = robust_report(start, b, "cauchy")
    lines_a = sorted(r["line"] for r in ra["rows"])
    assert lines_a == sorted(r["line"] for r in rb["rows"]) and set(ds.lines[bad]) <= set(lines_a)


@pytest.mark.parametrize("method", ["distance", "point-link"])
def test_measurement_groups_equal_the_per_unit_scan(method):
    """GroupedProblem finds every unit's rows with one stable sort (linear in the rows; the
    per-unit scan it replaced was quadratic: hours on 10⁶ poses). Same groups, same order and the
    same row → group map as the scan, on rows shuffled so that units are interleaved."""
    from estcal.estimate._common import GroupedProblem, _units
    from estcal.kinematics.robots import puma560
    from estcal.methods import NoiseModel, Problem
    from estcal.methods.generate import generate

    rob = puma560()
    ds = generate(rob, method, 40, rng=3)
    ds = ds.subset(np.random.default_rng(0).permutation(ds.n))
    prob = Problem(rob, [(method, ds, NoiseModel(1e-4, 1e-3, 1e-4, known=True))])
    gp = GroupedProblem(prob)
    u = _units(prob.terms[0], ds.n)
    _, first = np.unique(u, return_index=True)
    ref = [np.flatnonzero(u == uu) for uu in np.argsort(first)]
    assert len(gp.groups) == len(ref) and all(np.array_equal(g.poses, r) for g, r in zip(gp.groups, ref))
    assert any(g.poses.size > 1 for g in gp.groups)
    rows = prob.evaluate(jacobian=False)
    unit_to_group = {int(u[r[0]]): k for k, r in enumerate(ref)}
    assert np.array_equal(gp.row_group, [unit_to_group[int(u[p])] for p in rows.pose])


def test_gtsam_and_kalman_on_large_data_equal_the_unchunked_fits(monkeypatch):
    """The gtsam Gaussian-graph LM on the chunked factor [R c] (RᵀR = AᵀA, Rᵀc = Aᵀb, the true bᵀb)
    and the Kalman filter with its groups, χ² and sub-problems built chunk-wise / as used give the
    fits of the unchunked paths."""
    import estcal.methods.reduced as red
    from estcal.estimate.factorgraph import calibrate_gtsam
    from estcal.estimate.kalman import calibrate_kalman
    from estcal.estimate.levels import select_free

    prob, _ = _problem(n=300, seed=11)
    sel = select_free(prob, "full")
    start = prob.with_values(sel.theta)
    a = calibrate_gtsam(start, free=sel.identifiable)
    ka = calibrate_kalman(start, free=sel.identifiable)
    monkeypatch.setattr(red, "CHUNK_POSES", 70)
    assert red.use_chunks(start) == 70
    b = calibrate_gtsam(start, free=sel.identifiable)
    kb = calibrate_kalman(start, free=sel.identifiable)
    assert np.max(np.abs(b.estimate - a.estimate) / a.std) < 1e-8
    assert np.allclose(b.covariance, a.covariance, rtol=1e-8, atol=1e-12 * np.abs(a.covariance).max())
    assert np.isclose(b.chi2, a.chi2, rtol=1e-10) and b.dof == a.dof
    assert np.array_equal(kb.estimate, ka.estimate)  # the filter steps themselves are unchanged
    assert np.allclose(kb.covariance, ka.covariance, rtol=1e-12, atol=0)  # × σ0², χ² summed by chunk
    assert np.isclose(kb.chi2, ka.chi2, rtol=1e-12) and kb.dof == ka.dof
