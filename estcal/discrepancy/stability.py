"""Causes that survive a new split: named only when most posture-grouped folds name them too.

On small real files the forward selection of :func:`estcal.discrepancy.diagnose` can name a
different cause for every subset of postures (a gear harmonic on one half, nothing on the
other, a drift on a third): a cause that does not survive a new split is not a cause. The
diagnosis therefore repeats its selection on the training part of every posture-grouped fold
(no posture on both sides) and keeps a cause (effect and joints) only if

* the selection on all the rows names it,
* the selections of more than half of the folds name it (the count is reported), and
* the model with the kept causes lowers the posture-grouped CV RMSE of the geometric model.

The fold selections are **linearised** at the all-rows geometric estimate: every candidate's
columns were computed there by the all-rows screening (the effect terms are linear in their
parameters; the geometric parameters move little between folds — one Gauss–Newton step). The
selection on a subset of rows is then linear algebra on row subsets of those columns, with the
rules of the nonlinear selection — ΔBIC < 0, the significance test at α / (candidates screened),
the share of the excess residual explained, the posture-grouped CV gate (linear refit on each
inner fold's training rows) — so k folds, and the nested prediction's outer × inner folds
(:mod:`estcal.discrepancy.prediction`), cost milliseconds instead of k nonlinear diagnoses.

Time runs from the start of each session (``session_time``), so a drift term is zero at
every session's first posture; with several sessions the drift columns are also taken
orthogonal to a per-session constant shift of the measured points (:func:`drift_free_of_offsets`),
so a drift can never explain an offset between sessions: that is the repeatability's
(between-session) part of the budget.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["LinearCandidates", "linear_selection", "fold_selections", "folds_naming", "joint_votes",
           "stable_selection", "information_criterion",
           "significance", "cause_key", "drift_free_of_offsets", "TIME_EFFECTS"]

#: effects of time (from each session's start): with several sessions they are screened orthogonally to an
#: offset between sessions (:func:`drift_free_of_offsets`)
TIME_EFFECTS = ("drift", "thermal_expansion")


def information_criterion(rss, M, p, known):
    """BIC (up to a constant) of a Gaussian model: χ² + p ln M (known σ) or M ln(RSS/M) + p ln M."""
    return (rss if known else M * math.log(max(rss, 1e-300) / M)) + p * math.log(M)


def significance(rss0, rss1, k, M, p1, known):
    """``(test name, statistic, p-value)`` of adding k parameters: likelihood ratio (known σ) or nested F.
    The tails are scipy.special's ``chdtrc`` / ``fdtrc``, what ``scipy.stats.chi2.sf`` / ``f.sf`` evaluate,
    without importing scipy.stats (~0.3 s of CPU)."""
    from scipy.special import chdtrc, fdtrc

    if known:
        stat = max(rss0 - rss1, 0.0)
        return "likelihood ratio", stat, float(chdtrc(k, stat))
    d2 = max(M - p1, 1)
    F = max(rss0 - rss1, 0.0) / k / (max(rss1, 1e-300) / d2)
    return "nested F", F, float(fdtrc(k, d2, F))


def cause_key(cause) -> str:
    """The candidate label of a named cause (``effect[orders=[k]](joint,…)``; whole arm: ``(arm)``)."""
    j = ",".join(cause.joints) if cause.joints else "arm"
    o = "".join(f"[{k}={v}]" for k, v in (cause.options or {}).items() if k in ("orders", "scope"))
    return f"{cause.effect}{o}({j})"


@dataclass
class LinearCandidates:
    """The diagnosis linearised at the all-rows geometric estimate (module docstring).

    b : (M,) weighted residual e/σ; A : (M, P) weighted columns of every geometric parameter in
    ``names``; sigma : (M,) σ of each residual row (m / rad); row : (M,) dataset row of each residual
    row; position : (M,) True for position rows (the CV gate's RMSE is over measured points, mm);
    labels, family, blocks, params : each candidate's label, whether it is one effect over several joints,
    its weighted columns (M, k) and their parameter names; ``family_joints``: the joints of each family
    column (a family is reduced to the joints not in the model yet, as the nonlinear selection does);
    the selection rules of the diagnosis.
    """

    b: np.ndarray
    A: np.ndarray
    names: list
    sigma: np.ndarray
    row: np.ndarray
    position: np.ndarray
    labels: list
    family: list
    blocks: list
    params: list  # the effect parameter name of every column of every block
    known: bool
    alpha: float
    min_explained: float
    max_effects: int
    n_refit: int
    regroup_tol: float
    candidates: dict = field(default_factory=dict)  # label -> (effect, joints, options)
    family_joints: dict = field(default_factory=dict)  # block index -> joint of each column

    def mask(self, rows) -> np.ndarray:
        return np.isin(self.row, np.asarray(rows))


def _orth(X):
    if X.shape[1] == 0:
        return np.zeros((X.shape[0], 0))
    s = np.linalg.norm(X, axis=0)
    s[s == 0] = 1.0
    U, S, _ = np.linalg.svd(X / s, full_matrices=False)
    return U[:, S > 1e-9 * max(S.max(), 1e-300)]


def _fold_predictions(X, b, tests):
    """Held-out predictions ``X[te] @ δ_te`` of the least-squares fits ``δ_te = argmin ‖X[~te] δ − b[~te]‖`` of
    every fold (``tests``: boolean masks of the held-out rows), from one QR factorisation of all rows.

    With ``X = Q R`` (R invertible) the training fit is ``y = R δ`` minimising ``‖Q[~te] y − b[~te]‖``, and the
    held-out prediction ``X[te] δ = Q[te] y`` needs no inverse of R. Removing rows downdates the normal
    equations of the orthonormal Q (Golub & Van Loan, *Matrix Computations*, 4th ed., §6.5: down-dating):
    ``(I − Q[te]ᵀQ[te]) y = Qᵀb − Q[te]ᵀ b[te]``, whose condition number is 1 / (1 − ‖Q[te]‖²) — that of
    the fold's own problem relative to all rows', not the square of X's. A rank-deficient X, or a fold whose
    training rows lose a direction (condition above 10⁶), is solved by ``numpy.linalg.lstsq`` as before
    (its minimum-norm solution)."""
    from scipy.linalg import cho_factor, cho_solve

    out = [None] * len(tests)
    Q, R = np.linalg.qr(X)
    r = np.abs(np.diag(R))
    full = X.shape[1] == 0 or (len(X) >= X.shape[1] and r.min() > 1e-10 * max(r.max(), 1e-300))
    if full and X.shape[1]:
        Qb = Q.T @ b
        eye = np.eye(X.shape[1])
        for f, te in enumerate(tests):
            Qt = Q[te]
            G = eye - Qt.T @ Qt
            w = np.linalg.eigvalsh(G)
            if w[0] <= 1e-6 * w[-1]:
                continue
            y = cho_solve(cho_factor(G, lower=True, check_finite=False), Qb - Qt.T @ b[te], check_finite=False)
            out[f] = Qt @ y
    for f, te in enumerate(tests):
        if out[f] is None:
            delta, *_ = np.linalg.lstsq(X[~te], b[~te], rcond=None)
            out[f] = X[te] @ delta
    return out


def _cv_rmse_mm(lc: LinearCandidates, X, m, folds) -> float:
    """Posture-grouped CV RMSE (mm, point-error norms) of the linear model X on the rows ``m``: refit on each
    fold's training rows, predict its held-out rows (``folds``: dataset-row arrays; the fits share one
    factorisation, :func:`_fold_predictions`)."""
    sq, npts = 0.0, 0
    rows = lc.row[m]
    tests = [np.isin(rows, test) for test in folds]
    preds = _fold_predictions(X[m], lc.b[m], tests)
    for test, pred in zip(folds, preds):
        te = m & np.isin(lc.row, test)
        e = (lc.b[te] - pred) * lc.sigma[te]
        p = lc.position[te]
        sq += float(e[p] @ e[p])
        npts += int(p.sum()) // 3
    return float(np.sqrt(sq / max(npts, 1)) * 1e3)


def _block(lc: LinearCandidates, i, have: set):
    """``(columns, label)`` of candidate i as it can still be added given the parameters ``have`` in the model:
    None when its parameters are in the model; a family reduced to its joints not in the model (≥ 2)."""
    names = lc.params[i]
    keep = [c for c, n in enumerate(names) if n not in have]
    if len(keep) == len(names):
        return lc.blocks[i], lc.labels[i]
    if not lc.family[i] or not keep:
        return None
    joints = list(dict.fromkeys(lc.family_joints[i][c] for c in keep))
    if len(joints) < 2:
        return None
    effect, _, opts = lc.candidates[lc.labels[i]]
    o = "".join(f"[{k}={v}]" for k, v in opts.items() if k in ("orders", "scope"))
    label = f"{effect}{o}({','.join(joints)})"
    lc.candidates.setdefault(label, (effect, joints, opts))
    return lc.blocks[i][:, keep], label


def _screen(lc: LinearCandidates, m, X, have):
    """``(ΔBIC, candidate index, k, RSS, columns, label)`` of every candidate that can still be added and does
    not regroup on the rows ``m``, and the current RSS, rank and number of rows.

    Every candidate's columns are projected orthogonally to the model's at once (one product with the
    model's orthonormal basis for all of them), and their SVDs — the regrouping test and the least-squares
    gain — run as one stacked call per number of columns: the same numbers as candidate by candidate
    (each stacked SVD is LAPACK's on that candidate's matrix), without ~60 rounds of small-array calls
    per screen (a linearised selection screens ~70 times per diagnosis)."""
    b = lc.b[m]
    Q = _orth(X[m])
    bp = b - Q @ (Q.T @ b)
    rss = float(np.sum(bp ** 2))
    p, M = Q.shape[1], len(b)
    blocks = [(i, blk) for i in range(len(lc.blocks)) if (blk := _block(lc, i, have)) is not None]
    if not blocks:
        return [], rss, p, M
    sizes = np.array([blk[0].shape[1] for _, blk in blocks])
    start = np.r_[0, np.cumsum(sizes)[:-1]]
    E = np.concatenate([blk[0] for _, blk in blocks], axis=1)[m]
    En = np.linalg.norm(E, axis=0)
    Ep = E - Q @ (Q.T @ E)
    rel = np.linalg.norm(Ep, axis=0) / np.where(En == 0, 1.0, En)
    rss1 = {}
    for k in np.unique(sizes):
        idx = [c for c in np.flatnonzero(sizes == k) if np.all(En[start[c]:start[c] + k] > 0)]
        if not idx:
            continue
        cols = start[idx][:, None] + np.arange(k)  # (c, k)
        U, sv, _ = np.linalg.svd((Ep[:, cols] / En[cols]).transpose(1, 0, 2), full_matrices=False)
        for c, u, s_, r in zip(idx, U, sv, rel[cols]):
            if r.min() < lc.regroup_tol or s_.min() < lc.regroup_tol * s_.max():
                continue
            # full column rank here (the singular values pass the regroup test): the least-squares residual
            # is bp minus its projection on the columns' range, U Uᵀ bp — the SVD reused, not a second solve
            u = u[:, s_ > np.finfo(float).eps * max(M, k) * s_.max()]  # lstsq's rank rule (rcond=None)
            rss1[c] = float(np.sum((bp - u @ (u.T @ bp)) ** 2))
    out = []
    for c, (i, blk) in enumerate(blocks):
        if c in rss1:
            k = int(sizes[c])
            out.append((information_criterion(rss1[c], M, p + k, lc.known) - information_criterion(rss, M, p, lc.known),
                        i, k, rss1[c], blk[0], blk[1]))
    return out, rss, p, M


def linear_selection(lc: LinearCandidates, rows, folds, free=None) -> list[str]:
    """The labels the diagnosis's forward selection names on the dataset rows ``rows`` (linearised).

    folds : the posture-grouped folds of the CV gate (dataset-row arrays within ``rows``).
    free : the geometric free set of these rows (default: every column of ``lc.A``).
    """
    m = lc.mask(rows)
    cols = list(range(len(lc.names))) if free is None else [lc.names.index(n) for n in free if n in lc.names]
    X = lc.A[:, cols]
    named, have = [], set()
    cv = _cv_rmse_mm(lc, X, m, folds)
    for _ in range(lc.max_effects):
        table, rss, p, M = _screen(lc, m, X, have)
        excess = rss - (max(M - p, 0) if lc.known else 0.0)
        n_cv, accepted = 0, None
        for group in ([t for t in table if not lc.family[t[1]]], [t for t in table if lc.family[t[1]]]):
            for dbic, i, k, rss1, E, label in sorted(group, key=lambda t: t[0])[:lc.n_refit]:
                if not dbic < 0:
                    continue
                if not significance(rss, rss1, k, M, p + k, lc.known)[2] < lc.alpha / max(len(table), 1):
                    continue
                if not (excess > 0 and (rss - rss1) / excess >= lc.min_explained):
                    continue
                if n_cv >= 2:
                    break
                n_cv += 1
                cv_i = _cv_rmse_mm(lc, np.c_[X, E], m, folds)
                if cv_i < cv:
                    accepted, cv = (i, E, label), cv_i
                    break
            if accepted is not None:
                break
        if accepted is None:
            break
        i, E, label = accepted
        named.append(label)
        have.update(n for n in lc.params[i] if n not in have)
        X = np.c_[X, E]
    return named


def fold_selections(lc: LinearCandidates, groups, folds, k_inner: int, rng=0, rows=None, free=None) -> list:
    """What the selection names on each fold's training rows: one list of ``(effect, joints)`` per fold
    (:func:`linear_selection` with the fold's own posture-grouped inner folds). ``rows``: the rows the folds
    partition (default all; ``folds`` index into them); ``groups``: posture labels of those rows."""
    from estcal.validation import grouped_folds

    rows = np.arange(len(groups)) if rows is None else np.asarray(rows)
    g = np.asarray(groups)
    out = []
    for test in folds:
        keep = ~np.isin(np.arange(len(rows)), test)
        train = rows[keep]
        inner = [train[f] for f in grouped_folds(g[keep], k_inner, rng)]
        out.append([lc.candidates[lab][:2] for lab in linear_selection(lc, train, inner, free)])
    return out


def folds_naming(effect: str, joints, selections) -> int:
    """In how many folds the selection names ``effect`` on more than half of ``joints`` (in one candidate or
    several: a compound effect named as a family in one fold and joint by joint in another counts in both);
    a whole-arm effect: named at all."""
    J = set(joints or [])
    n = 0
    for named in selections:
        covered = {j for e, jj in named if e == effect for j in (jj or [])}
        whole = any(e == effect and not jj for e, jj in named)
        n += bool(len(J & covered) > len(J) / 2) if J else whole
    return n


def joint_votes(selections) -> dict:
    """``{"effect(joint)": folds naming that effect on that joint}`` (whole-arm effects: ``effect(arm)``)."""
    votes: dict = {}
    for named in selections:
        for key in {f"{e}({j})" for e, jj in named for j in (jj or ["arm"])}:
            votes[key] = votes.get(key, 0) + 1
    # ties by name: the keys come from a set of strings, whose order changes with Python's hash seed
    return dict(sorted(votes.items(), key=lambda t: (-t[1], t[0])))


def stable_selection(lc: LinearCandidates, groups, k: int, rng=0, rows=None, free=None) -> list:
    """The effects ``(name, joints, options)`` a diagnosis of the rows ``rows`` keeps (linearised): named on
    those rows and in more than half of their posture-grouped folds — the procedure the nested CV replays
    on each outer fold (:class:`estcal.discrepancy.prediction.Procedure`)."""
    from estcal.validation import grouped_folds

    rows = np.arange(len(groups)) if rows is None else np.asarray(rows)
    g = np.asarray(groups)
    folds = grouped_folds(g, k, rng)
    named = linear_selection(lc, rows, [rows[f] for f in folds], free)
    if not named:
        return []
    sel = fold_selections(lc, g, folds, k, rng, rows, free)
    out = [lc.candidates[lab] for lab in named]
    return [c for c in out if folds_naming(c[0], c[1], sel) > len(folds) / 2]


def drift_free_of_offsets(E, row_session, kind, sigma) -> np.ndarray:
    """Weighted columns ``E`` (M, k) made orthogonal to a constant shift of the measured coordinates in each
    session (position rows; one column 1/σ per session and axis): the part of a drift (or thermal) term that
    an offset between sessions cannot explain."""
    row_session, kind = np.asarray(row_session), np.asarray(kind)
    if len(np.unique(row_session)) < 2:
        return E
    axis = np.zeros(len(kind), int)
    pos = np.flatnonzero(kind == 0)
    axis[pos] = np.arange(len(pos)) % 3
    cols = [np.where((row_session == s) & (kind == 0) & (axis == a), 1.0 / np.asarray(sigma, float), 0.0)
            for s in np.unique(row_session) for a in range(3)]
    Q = _orth(np.array([c for c in cols if c.any()]).T)
    return E - Q @ (Q.T @ E)
