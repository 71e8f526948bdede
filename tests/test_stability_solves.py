"""The stability screen's shared factorisations (:func:`estcal.discrepancy.stability._fold_predictions`, the
SVD reused in ``_screen``) against one ``numpy.linalg.lstsq`` per fold / candidate, to 1e-10: well and badly
scaled columns, a fold that removes a direction (the lstsq fallback) and a rank-deficient model."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.discrepancy import stability as st


def _ref_predictions(X, b, tests):
    out = []
    for te in tests:
        delta, *_ = np.linalg.lstsq(X[~te], b[~te], rcond=None)
        out.append(X[te] @ delta)
    return out


def _problem(seed, M=240, p=30, k=5, scales=1.0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(M, p)) * scales
    b = X @ rng.normal(size=p) + rng.normal(scale=0.3, size=M)
    fold = rng.permutation(M) % k
    return X, b, [fold == f for f in range(k)], rng


def _close(got, ref):
    for g, r in zip(got, ref):
        np.testing.assert_allclose(g, r, rtol=0, atol=1e-10 * max(np.abs(r).max(), 1.0))


@pytest.mark.parametrize("seed", range(4))
def test_fold_predictions_are_the_per_fold_lstsq(seed):
    X, b, tests, _ = _problem(seed)
    _close(st._fold_predictions(X, b, tests), _ref_predictions(X, b, tests))


def test_badly_scaled_columns():
    X, b, tests, _ = _problem(7, scales=np.logspace(-4, 3, 30))
    _close(st._fold_predictions(X, b, tests), _ref_predictions(X, b, tests))


def test_a_fold_that_removes_a_direction_and_a_rank_deficient_model_fall_back_to_lstsq():
    X, b, tests, _ = _problem(11)
    X[:, 3] = np.where(tests[0], X[:, 3], 0.0)  # column 3 lives on fold 0's rows only
    _close(st._fold_predictions(X, b, tests), _ref_predictions(X, b, tests))
    X, b, tests, _ = _problem(12)
    X[:, 5] = X[:, 2] - 2 * X[:, 9]  # rank p − 1
    _close(st._fold_predictions(X, b, tests), _ref_predictions(X, b, tests))


def _candidates(seed, M=180, p=12, known=False):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(M, p))
    row = np.repeat(np.arange(M // 3), 3)
    blocks, params, labels = [], [], []
    for i, k in enumerate([1, 1, 2, 3, 2]):
        E = rng.normal(size=(M, k))
        if i == 4:
            E[:, 1] = A[:, 0] + 1e-6 * rng.normal(size=M)  # regroups into the model: skipped by both
        blocks.append(E)
        params.append([f"c{i}_{c}" for c in range(k)])
        labels.append(f"c{i}")
    b = A @ rng.normal(size=p) + blocks[2] @ [0.4, -0.2] + rng.normal(scale=0.5, size=M)
    return st.LinearCandidates(b=b, A=A, names=[f"g{j}" for j in range(p)], sigma=np.full(M, 1e-4), row=row,
                               position=np.ones(M, bool), labels=labels, family=[False] * 5, blocks=blocks,
                               params=params, known=known, alpha=0.05, min_explained=0.3, max_effects=3, n_refit=3,
                               regroup_tol=1e-3)


@pytest.mark.parametrize("known", [False, True])
def test_screen_rss_is_the_per_candidate_lstsq(known):
    lc = _candidates(3, known=known)
    m = lc.row < 50  # a subset of rows, as a fold's training part
    X = lc.A
    table, rss, p, M = st._screen(lc, m, X, set())
    assert [t[1] for t in table] == [0, 1, 2, 3]  # the regrouping candidate is skipped
    Q = st._orth(X[m])
    bp = lc.b[m] - Q @ (Q.T @ lc.b[m])
    for dbic, i, k, rss1, E, _ in table:
        Ep = E[m] - Q @ (Q.T @ E[m])
        x, *_ = np.linalg.lstsq(Ep, bp, rcond=None)
        ref = float(np.sum((bp - Ep @ x) ** 2))
        assert rss1 == pytest.approx(ref, rel=1e-10)
        ref_dbic = (st.information_criterion(ref, M, p + k, known) - st.information_criterion(rss, M, p, known))
        assert dbic == pytest.approx(ref_dbic, rel=1e-10, abs=1e-10)


def test_cv_rmse_is_the_per_fold_lstsq():
    lc = _candidates(5)
    m = lc.row < 55
    folds = [np.arange(f, 55, 5) for f in range(5)]
    X = np.c_[lc.A, lc.blocks[2]]
    sq, npts = 0.0, 0
    for test in folds:
        te = m & np.isin(lc.row, test)
        tr = m & ~te
        delta, *_ = np.linalg.lstsq(X[tr], lc.b[tr], rcond=None)
        e = (lc.b[te] - X[te] @ delta) * lc.sigma[te]
        sq += float(e @ e)
        npts += int(te.sum()) // 3
    assert st._cv_rmse_mm(lc, X, m, folds) == pytest.approx(np.sqrt(sq / npts) * 1e3, rel=1e-10)
