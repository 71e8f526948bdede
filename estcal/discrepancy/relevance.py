"""The relevance model: one sparse Bayesian fit that predicts, and the tests that name its causes.

The model
---------
Every candidate of :func:`estcal.discrepancy.terms.build_terms` — the identifiable geometric parameters and
the effect terms — under its own zero-mean (nominal-centred) Gaussian prior, the registration unpenalised,
the precisions and the noise by type-II maximum likelihood (:func:`estcal.estimate.sparse.sparse_bayes`,
Tipping & Faul 2003), relinearised by Gauss–Newton: at the current estimate θ the weighted residual
``b = e/σ`` and Jacobian ``A = H/σ`` give the linear model ``b + P(θ_pen − μ) ≈ F c + P w`` in the deviations
``w = θ_pen − μ`` from the nominal values μ and the registration increments ``c``; the evidence fit of ``w``
moves θ and the system is evaluated again until the step is below a thousandth of a standard deviation.

Rows within a posture. Where the data measure one rigid body at a posture (points of a marker body, a
pose, one point), the model's error there is mostly one small rigid motion of that body — the joints and
links that the model gets wrong move every point together — not independent noise on every coordinate. So
the rows of a posture are given the covariance ``σ² I + Z_p Ψ Z_pᵀ`` (``Z_p`` the rows' response to a
rigid motion of the body: ``[I, −[x_i − c]×]`` for point ``x_i`` about the body's centroid ``c``; ``Ψ`` a
diagonal 6×6 of translation and rotation variances in the measuring frame), with ``σ²`` and ``Ψ`` by maximum
likelihood (EM) on the residual of the fit, and the system is whitened by it (a posture counts for the
rigid motion it measures, not for its 12 coordinates — on TIAGo the error at new postures of another
session drops from 3.45 to 3.15 mm, docs/discrepancy.md).

Several sessions. Each session after the first has its own measuring frame: six unpenalised columns — the
base frame's, restricted to its rows — so a session's rigid offset is registered, never named as an effect;
and its own joint zeros (the ``offset`` columns its rows identify beside the frame,
:func:`estcal.discrepancy.terms.session_zero_names`): an encoder homed at start-up reads a new session's
postures with its zero moved, a change of the session that no parameter of the robot can carry.

Naming
------
A term (an effect on a joint) is **named** when (1) it survives (one of its columns keeps a finite
precision); (2) its Bayes factor against the model without it is decisive: ``ln B ≥ 5`` (``2 ln B ≥ 10``,
"very strong" on Kass & Raftery's scale, 1995, *JASA* 90:773), ``ln B`` the difference of the two
maximised log evidences; (3) it survives in more than half of the cross-validation folds (each fold's fit
on its training rows); (4) the cross-validated error at new postures is lower with it than without it.
Relevance alone over-names: a column with no signal keeps a finite precision one time in three (its
``q²/s`` exceeds 1 when the column's score is a χ²₁ above 1; Wipf & Nagarajan 2008 explain the
ℓ1-like pruning), and a column that absorbs structured model error is as relevant as a real cause.

Load terms (:data:`estcal.discrepancy.terms.LOAD_EFFECTS`) stay in the model when relevant, named or not;
a special term enters only when named — tested one at a time in the order of its Bayes factor against the
model with the load terms and the special terms named before it. Once the search ends, every named special
term is tested again against the model it enters — the geometry, the load terms the evidence keeps and the
other named causes — and withdrawn if it fails (:func:`_against_load`): on data simulated from TIAGo's
two-session model a drift or a gear harmonic named beside the named causes stood in for load terms kept
unnamed (a cause the truth does not hold named in 4 of 24 simulations, 1 with the test;
``experiments/tiago_limits.py --parts 5``). The nested cross-validation of the error budget replays the naming
without this last test (it costs a refit and a cross-validation per named special term in every outer fold).

Cross-validation is linear: every fold refits the evidence model on its training rows of the all-rows
linearised (and whitened) system, warm-started from the all-rows precisions; the Jacobian and the
random-effect covariance are the all-rows ones (second order: ``tests/test_relevance.py`` compares with
nonlinear refits). A held-out session's frame is registered on its rows at postures of the fold's training
rows (:class:`estcal.validation.groups.Fold`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.estimate.sparse import Prepared, SparseFit, sparse_bayes
from estcal.methods import Problem

__all__ = ["LN_BF_NAMED", "System", "RelevanceFit", "linearise", "fit_relevance", "refit", "held_out_errors",
           "fold_mse", "cross_validate", "select_terms", "Selection"]

#: the decisive Bayes factor of a named cause: ln B ≥ 5 (2 ln B ≥ 10, Kass & Raftery's "very strong")
LN_BF_NAMED = 5.0
#: Gauss–Newton stops when no parameter moves by this fraction of its standard deviation (the Jacobian of the load
#: terms neglects their loads' own dependence on the geometry — second order, but it slows the last steps)
GN_TOL = 0.02
_REFITS_KEPT = 256  # System.refits: the repeats of a diagnosis are within ~200 searches of each other
#: the evidence fits stop when no single change gains more than this (nats): far below every decision's scale
TOL = 1e-2
#: each step of the naming search cross-validates at most this many candidates (in the order of their evidence)
TRIED = 2
#: each step of the naming search scores exactly the SHORTLIST candidates the cheap screen ranks first, none
#: it gives less than SCREEN_MIN nats (a lower bound of the Bayes factor, far below LN_BF_NAMED)
SHORTLIST = 5
SCREEN_MIN = 1.0
_BASE = ("base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz")


# ------------------------------------------------------------------------------------------ the system
@dataclass
class System:
    """The linearised system at ``theta`` over the rows of the data (weighted units: residual / σ).

    names : the columns, ``free`` first (registration, then the session frames ``"<session>:base_*"``), then
        ``penalised``; X (n, len(names)); t (n,) the target ``b + P(θ_pen − μ)``; Xw, tw the whitened ones
    sigma, pose, kind, session : per row — the noise σ (m, rad), the dataset row, the kind (0 position), the
        session label
    n_free : the number of unpenalised columns; frame_of : {session: column indices of its frame}
    psi : the rigid-motion variances (6,) (m², rad²) of the random-effect covariance, and ``s2`` its σ² scale
        (None: independent rows)
    zeros : the joint zero parameters the further sessions register with their frames (their union)
    alpha_min : (len(penalised),) the least prior precision of every penalised column (SI; 0: unbounded —
        :meth:`estcal.discrepancy.terms.Terms.alpha_min`)
    """

    theta: np.ndarray
    frames: dict
    names: list
    n_free: int
    X: np.ndarray
    t: np.ndarray
    Xw: np.ndarray
    tw: np.ndarray
    sigma: np.ndarray
    pose: np.ndarray
    kind: np.ndarray
    session: np.ndarray
    frame_of: dict
    blocks: list
    psi: np.ndarray | None = None
    s2: float | None = None
    zeros: tuple = ()
    alpha_min: np.ndarray | None = None
    #: sparse_bayes's row-only work (:class:`estcal.estimate.sparse.Prepared`) by training rows, shared by refits
    prepared: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    #: the last searches (:func:`refit` without ``hyper``) by training rows, columns and start: the naming's steps
    #: and the budget cross-validate the same model on the same folds again (a tenth of a diagnosis's searches).
    #: Both caches belong to this system's rows and priors: never passed on (``init=False``: a
    #: ``dataclasses.replace`` with other priors starts empty)
    refits: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def F(self):
        return self.X[:, : self.n_free]

    @property
    def P(self):
        return self.X[:, self.n_free:]

    def rows_of(self, data_rows) -> np.ndarray:
        """The system rows of the dataset rows ``data_rows``."""
        return np.flatnonzero(np.isin(self.pose, np.asarray(data_rows)))


def _session_labels(data) -> np.ndarray:
    lab = data.columns.get("session")
    return np.zeros(data.n, int) if lab is None else np.asarray(lab)


def _rigid_blocks(data, pose, kind, sigma) -> list:
    """Per dataset row: ``(system rows, Z)`` — the rows' response to a rigid motion (δt, δφ) of the measured body
    (module docstring), in weighted units. Position rows of point ``i`` respond by ``δt + δφ × (x_i − c)`` when
    the row measures two points or more (one point: its translation only), orientation rows by ``δφ``. Rows
    are grouped by dataset row in a stable order (position rows first, point by point, then orientation)."""
    from .stages import measured_points

    try:
        pts = measured_points(data)
    except ValueError:
        return []
    order = np.argsort(pose, kind="stable")
    p_sorted, k_sorted = pose[order], kind[order]
    starts = np.searchsorted(p_sorted, np.arange(data.n + 1))
    # the rank of each row among its pose's position rows (point, axis) and among its orientation rows
    rank = np.arange(len(order)) - starts[p_sorted]
    n_pos = np.bincount(p_sorted[k_sorted == 0], minlength=data.n)
    Z = np.zeros((len(order), 6))
    pos = k_sorted == 0
    pt, ax = np.divmod(rank, 3)
    Z[pos, ax[pos]] = 1.0
    rot = pos & (n_pos[p_sorted] >= 6)  # two measured points or more: the body's rotation is seen
    if rot.any():
        c = pts.mean(axis=1)
        d = pts[p_sorted[rot], np.minimum(pt[rot], pts.shape[1] - 1)] - c[p_sorted[rot]]
        # ∂(δφ × d)_ax / ∂δφ = d × e_ax
        e = np.zeros((rot.sum(), 3))
        e[np.arange(rot.sum()), ax[rot]] = 1.0
        Z[rot, 3:] = np.cross(d, e)
    ori = k_sorted == 1
    Z[ori, 3 + (rank[ori] - n_pos[p_sorted[ori]]) % 3] = 1.0
    Z /= sigma[order, None]
    return [(order[starts[i]: starts[i + 1]], Z[starts[i]: starts[i + 1]]) for i in range(data.n)
            if starts[i + 1] > starts[i]]


def _whiten(blocks, psi, s2, *arrays):
    """The arrays with every block's rows multiplied by ``L⁻¹``, ``L Lᵀ = I + Z Ψ Zᵀ / σ²`` (blocks of one size
    factored together)."""
    out = [np.array(a, float, copy=True) for a in arrays]
    if psi is None or not blocks:
        return out
    d = psi / s2
    by_size = {}
    for rows, Z in blocks:
        by_size.setdefault(len(rows), []).append((rows, Z))
    for m, group in by_size.items():
        R = np.stack([rows for rows, _ in group])  # (B, m)
        Zs = np.stack([Z for _, Z in group])  # (B, m, 6)
        C = np.eye(m) + np.einsum("bik,k,bjk->bij", Zs, d, Zs)
        L = np.linalg.cholesky(C)
        for o, a in zip(out, arrays):
            A = np.asarray(a, float)[R]  # (B, m) or (B, m, c)
            o[R] = np.linalg.solve(L, A if A.ndim == 3 else A[..., None]).reshape(A.shape)
    return out


def random_effect(r, blocks, iters: int = 100, tol: float = 1e-6, s2_min: float = 1.0):
    """``(Ψ (6,), σ²)`` of ``r_p = Z_p δ_p + ε``, ``δ_p ~ N(0, diag Ψ)``, ``ε ~ N(0, σ² I)`` by EM (the linear
    mixed model's maximum likelihood; Laird & Ware 1982) over the blocks; a variance the rows cannot see
    (a column of Z that is zero everywhere) stays 0. ``σ² ≥ s2_min`` (weighted units: 1 is the noise model's
    σ): the rows within a posture are never trusted beyond the noise the user states (or its default) — the
    points of a tracked body are rigid to a micrometre by construction, and a fit that believed it would weigh
    the body's shape, which no robot error changes, above its pose."""
    seen = np.zeros(6, bool)
    for _, Z in blocks:
        seen |= np.any(Z != 0, axis=0)
    n = sum(len(rows) for rows, _ in blocks)
    s2 = float(np.mean(r ** 2)) if n else 1.0
    psi = np.where(seen, s2 * 1e-2, 0.0)
    # blocks of one size stacked: each EM step is a few batched products, not a loop over the postures
    by_size = {}
    for rows, Z in blocks:
        by_size.setdefault(len(rows), []).append((rows, Z))
    stacks = [(np.stack([Z[:, seen] for _, Z in g]), np.stack([r[rows] for rows, _ in g])) for g in by_size.values()]
    for _ in range(iters):
        E2 = np.zeros(int(seen.sum()))
        res2 = 0.0
        for Zs, rb in stacks:  # (B, m, k), (B, m)
            Sp = np.linalg.inv(np.einsum("bik,bil->bkl", Zs, Zs) / s2 + np.diag(1.0 / psi[seen]))
            m = np.einsum("bkl,bil,bi->bk", Sp, Zs, rb) / s2
            E2 += np.sum(m ** 2, axis=0) + np.einsum("bkk->k", Sp)
            e = rb - np.einsum("bik,bk->bi", Zs, m)
            res2 += float(np.sum(e ** 2)) + float(np.einsum("bij,bjk,bik->", Zs, Sp, Zs))
        new_psi = np.zeros(6)
        new_psi[seen] = np.maximum(E2 / len(blocks), 1e-30)
        new_s2 = max(res2 / n, s2_min, 1e-30)
        done = np.allclose(new_psi, psi, rtol=tol, atol=0) and abs(new_s2 - s2) <= tol * s2
        psi, s2 = new_psi, new_s2
        if done:
            break
    return psi, s2


def session_theta(robot, theta, frame, zeros=()):
    """The parameters of one session: ``theta`` (the first session's) with the session's ``frame`` increment
    ``(6 + k,)`` added to the base parameters and to its ``k`` joint zeros ``zeros`` (names)."""
    th = np.array(theta, float, copy=True)
    th[robot.params.indices([n for n in _BASE if n in robot.params.names])] += frame[:6]
    if len(zeros):
        th[robot.params.indices(list(zeros))] += frame[6:]
    return th


def _evaluate(robot, data, noise, theta, frames, jacobian: bool, zeros=None):
    """``(e, σ, H or None, pose, kind)`` of every row, each session's rows at its own frame (``frames``: ``{session:
    (6 + k,) increment of the base parameters and of its k joint zeros ``zeros[session]``}``), in session order."""
    lab = _session_labels(data)
    parts = []
    for s in dict.fromkeys(lab.tolist()):
        m = np.flatnonzero(lab == s)
        th = session_theta(robot, theta, frames[s], (zeros or {}).get(s) or ()) if s in frames else theta
        parts.append((m, Problem(robot, [(None, data.subset(m), noise)]).evaluate(th, jacobian=jacobian)))
    H = np.concatenate([r.H for _, r in parts]) if jacobian else None
    return (np.concatenate([r.e for _, r in parts]), np.concatenate([r.sigma for _, r in parts]), H,
            np.concatenate([m[r.pose] for m, r in parts]), np.concatenate([r.kind for _, r in parts]))


def _map_objective(terms, data, noise, theta, frames, sysm, hyper, evaluated=None) -> float:
    """The MAP objective the Gauss–Newton steps lower: the whitened residual over the noise variance plus the
    relevance priors, ``‖L⁻¹ b(θ)‖²/σ² + Σ α_j (θ_j − μ_j)²`` — evaluated without a Jacobian (the line search)
    unless ``evaluated`` (:func:`_evaluate` at ``theta``, ``frames``) is given."""
    e, sig, _, _, _ = evaluated or _evaluate(terms.robot, data, noise, theta, frames, False, terms.session_zeros)
    (bw,) = _whiten(sysm.blocks, sysm.psi, sysm.s2, e / sig) if sysm.psi is not None else (e / sig,)
    alpha = hyper[0]
    ipen = terms.robot.params.indices(terms.penalised)
    d = theta[ipen] - terms.nominal[ipen]
    fin = np.isfinite(alpha)
    return float(bw @ bw / hyper[1] + np.sum(alpha[fin] * d[fin] ** 2))


def _linear_objective(sysm, d, hyper) -> float:
    """The MAP objective at the point ``sysm`` was linearised at (``d``: its penalised deviations from nominal),
    from the system's own residual — what :func:`_map_objective` evaluates there, without a new evaluation."""
    bw = sysm.tw - sysm.Xw[:, sysm.n_free:] @ d
    fin = np.isfinite(hyper[0])
    return float(bw @ bw / hyper[1] + np.sum(hyper[0][fin] * d[fin] ** 2))


def _evaluate_or_none(terms, data, noise, theta, frames):
    """:func:`_evaluate` with the Jacobian at a trial step, or None where the model cannot be evaluated there."""
    try:
        return _evaluate(terms.robot, data, noise, theta, frames, True, terms.session_zeros)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError):
        return None


def linearise(terms, data, noise, theta, frames, psi=None, s2=None, evaluated=None) -> System:
    """The :class:`System` of ``terms`` (:class:`~estcal.discrepancy.terms.Terms`) on ``data`` at ``theta``, each
    session's rows at its own frame (``frames``: ``{session: (6 + k,) increment of the base and of its joint
    zeros}``, :func:`_evaluate`; ``evaluated``: that evaluation with its Jacobian, when already made)."""
    robot = terms.robot
    free, pen = list(terms.free), terms.penalised
    names = free + pen
    idx = robot.params.indices(names)
    ibase = robot.params.indices([n for n in _BASE if n in robot.params.names])
    lab = _session_labels(data)
    svals = list(dict.fromkeys(lab.tolist()))
    zeros = terms.session_zeros
    e, sig, H, pose, kind = evaluated or _evaluate(robot, data, noise, theta, frames, True, zeros)
    session = lab[pose]
    b = e / sig
    A = H[:, idx] / sig[:, None]
    frame_of, extra, fnames = {}, [], []
    if ibase.size == 6:
        Hb = H[:, ibase] / sig[:, None]
        for s in svals[1:]:
            z = list(zeros.get(s) or [])
            Hs = np.hstack([Hb, H[:, robot.params.indices(z)] / sig[:, None]]) if z else Hb
            cols = np.where((session == s)[:, None], Hs, 0.0)
            frame_of[s] = np.arange(len(free) + len(fnames), len(free) + len(fnames) + 6 + len(z))
            fnames += [f"{s}:{n}" for n in (*_BASE, *z)]
            extra.append(cols)
    n_free = len(free) + len(fnames)
    X = np.hstack([A[:, : len(free)], *extra, A[:, len(free):]])
    ipen = robot.params.indices(pen)
    t = b + A[:, len(free):] @ (theta[ipen] - terms.nominal[ipen])
    blocks = _rigid_blocks(data, pose, kind, sig)
    Xw, tw = _whiten(blocks, psi, s2, X, t) if psi is not None else (X, t)
    return System(np.array(theta, float, copy=True), dict(frames), free + fnames + pen, n_free, X, t, Xw, tw, sig,
                  pose, kind, session, frame_of, blocks, psi, s2,
                  tuple(sorted({n for z in zeros.values() for n in z})), terms.alpha_min())


# ------------------------------------------------------------------------------------------ fitting
@dataclass
class RelevanceFit:
    """The all-rows fit: ``theta`` (P,) the robot's parameters (the first session's frame), ``frames``
    ``{session: (6,) base increment}``, ``sparse`` the evidence fit on the final ``system``, ``include`` (M,)
    the penalised columns allowed in the model, ``iterations`` of Gauss–Newton."""

    theta: np.ndarray
    frames: dict
    sparse: SparseFit
    system: System
    include: np.ndarray
    iterations: int
    converged: bool
    extra: dict = field(default_factory=dict)


def refit(system: System, train=None, include=None, start=None, hyper=None) -> SparseFit:
    """The evidence fit of the linear ``system`` on its rows ``train`` (system row indices; None: all) with the
    penalised columns ``include`` (bool (M,); None: all), warm-started at ``start`` (precisions); with ``hyper``
    = ``(precisions, noise variance)`` no search: the posterior at those hyperparameters (the MAP of a
    Gauss–Newton step). Free columns with no training row (a held-out session's frame) are dropped: their
    coefficients are 0."""
    rows = np.arange(len(system.tw)) if train is None else np.asarray(train)
    M = system.X.shape[1] - system.n_free
    exclude = None if include is None else ~np.asarray(include, bool)
    key = None if train is None else rows.tobytes()
    if key not in system.prepared:
        Fw = system.Xw[rows, : system.n_free]
        keep = np.any(Fw != 0, axis=0)
        system.prepared[key] = (Prepared(system.Xw[rows, system.n_free:], system.tw[rows], Fw[:, keep]), keep)
    pre, keep = system.prepared[key]
    if hyper is not None:
        fit = sparse_bayes(None, None, start=hyper[0], exclude=exclude, noise_var=hyper[1], max_iter=0,
                           alpha_min=system.alpha_min, prepared=pre)
    else:
        memo = (key, None if exclude is None else exclude.tobytes(),
                None if start is None else np.asarray(start, float).tobytes())
        if memo in system.refits:
            system.refits[memo] = fit = system.refits.pop(memo)  # the most recent last; never written to
            return fit
        fit = sparse_bayes(None, None, start=start, exclude=exclude, tol=TOL, alpha_min=system.alpha_min,
                           prepared=pre)
    free = np.zeros(system.n_free)
    free[keep] = fit.free
    free_cov = np.zeros((system.n_free, system.n_free))
    free_cov[np.ix_(keep, keep)] = fit.free_cov
    fit.free, fit.free_cov = free, free_cov
    fit.extra["free_kept"] = keep
    assert fit.mean.shape == (M,)
    if hyper is None:
        system.refits[memo] = fit
        if len(system.refits) > _REFITS_KEPT:
            del system.refits[next(iter(system.refits))]
    return fit


def _residual(system: System, fit: SparseFit, rows) -> np.ndarray:
    """Unwhitened weighted residual of the linear model at ``rows``."""
    return system.t[rows] - system.X[rows, : system.n_free] @ fit.free - system.X[rows, system.n_free:] @ fit.mean


def held_out_errors(system: System, fit: SparseFit, test, register=()) -> np.ndarray:
    """The residual (m, rad: weighted residual × σ) of the linear model ``fit`` at every system row of the
    dataset rows ``test``, their session's frame first registered on the dataset rows ``register`` when given
    (least squares of the frame's six columns on their residual; module docstring)."""
    rt = system.rows_of(test)
    r = _residual(system, fit, rt)
    reg = system.rows_of(register) if len(register) else np.zeros(0, int)
    if len(reg):
        s = system.session[rt[0]]
        cols = _frame_columns(system, s)
        rr = _residual(system, fit, reg)
        delta, *_ = np.linalg.lstsq(system.X[np.ix_(reg, cols)], rr, rcond=None)
        r = r - system.X[np.ix_(rt, cols)] @ delta
    return r * system.sigma[rt]


def _frame_columns(system: System, s) -> np.ndarray:
    """The columns of session ``s``'s frame: its own (a further session: the base and its joint zeros) or, for
    the first session, the registration's base columns and the model's own columns of the joint zeros the
    further sessions register (restricted to its rows, they are that session's frame and zeros: a fold trained
    on the further sessions alone has put their zeros in their own columns)."""
    if s in system.frame_of:
        return system.frame_of[s]
    return np.array([system.names.index(n) for n in (*_BASE, *system.zeros) if n in system.names], int)


def fit_relevance(terms, data, noise, include=None, start=None, max_gn: int = 20, max_rounds: int = 6,
                  system0=None, rigid: bool = True, ridge_start: bool = True) -> RelevanceFit:
    """The relevance model of ``terms`` on ``data`` (module docstring) by MacKay's alternation (1992): at fixed
    hyperparameters (the precisions and the noise) Gauss–Newton on the MAP estimate until no parameter moves by
    ``GN_TOL`` of its standard deviation; then the hyperparameters by the evidence at that estimate (a warm
    sequential search, started from the geometric least-squares fit: :func:`_geometric_start`); until the search
    keeps the same terms with precisions within 1 %. The residual of that converged fit gives each posture's
    rigid-motion covariance (the whitening, module docstring), and the alternation runs again on the whitened
    system. A search after
    every Gauss–Newton step instead oscillates between near-equal optima of the evidence: the whitened
    problem's posterior is sharp and a relinearisation moves the estimate by several of its standard
    deviations. ``include``: the penalised columns allowed (None: all); ``system0``: a fit of the same rows
    to start from (its whitening kept); ``rigid=False``: independent rows (no rigid error per posture);
    ``ridge_start=False``: the search grows from the single best column (every column out)."""
    theta = terms.theta0.copy() if system0 is None else system0.theta.copy()
    frames = {} if system0 is None else dict(system0.frames)
    psi, s2 = (None, None) if system0 is None else (system0.psi, system0.s2)
    robot = terms.robot
    ifree = robot.params.indices(terms.free)
    ipen = robot.params.indices(terms.penalised)
    nf = len(terms.free)
    hyper, converged, n_gn = None, False, 0

    def step(sysm, fit, search: bool = False, last: bool = False):
        """Move θ (and the session frames) by the fit's step; with ``search``, halve the step until the MAP
        objective decreases (a joint whose load changes sign with the parameters — backlash by the load's side —
        makes the residual step at that posture, and a full Gauss–Newton step can jump back and forth across it).
        ``last``: no linearisation follows (no Jacobian at the new point). Returns whether the step was below
        ``GN_TOL`` of every standard deviation."""
        nonlocal theta
        pending.clear()
        d_free, d_pen = fit.free[:nf], terms.nominal[ipen] + fit.mean - theta[ipen]
        d_frames = {s: fit.free[cols] for s, cols in sysm.frame_of.items()}
        sd = np.sqrt(np.maximum(np.r_[np.diag(fit.free_cov)[:nf], np.diag(fit.cov)], 0.0))
        scale = 1.0

        def at(scale):
            new = theta.copy()
            new[ifree] += scale * d_free
            new[ipen] += scale * d_pen
            return new, {s: frames.get(s, 0.0) + scale * d_frames.get(s, 0.0) for s in set(frames) | set(d_frames)}

        full = []

        def objective(new, new_frames):
            ev = None
            with np.errstate(all="ignore"):
                if not full and not last:  # the full step with its Jacobian: the next linearisation when taken
                    full.append(ev := _evaluate_or_none(terms, data, noise, new, new_frames))
                return _map_objective(terms, data, noise, new, new_frames, sysm, hyper, ev)

        new, new_frames = at(scale)
        obj = None
        if not search:
            obj = objective(new, new_frames)
            search = not np.isfinite(obj)  # a step into overflow (geometric="full", near-collinear): searched
        if search:
            base = _linear_objective(sysm, theta[ipen] - terms.nominal[ipen], hyper)
            obj = objective(new, new_frames) if obj is None else obj
            for k in range(6):  # the step, then 1/2 … 1/32 of it
                if obj <= base:
                    break
                scale *= 0.5
                if k < 5:
                    new, new_frames = at(scale)
                    obj = objective(new, new_frames)
            if not np.isfinite(obj):
                return True  # still overflowing at 1/64 of the step: stay where the objective is finite
        moved = scale * np.abs(np.r_[d_free, d_pen])
        theta = new
        frames.clear()
        frames.update(new_frames)
        pending[:] = [full[0]] if scale == 1.0 and full and full[0] is not None else []
        return bool(np.all(moved[sd > 0] <= GN_TOL * sd[sd > 0]))

    whiten = psi is None and system0 is None and rigid
    first = None
    pending = []  # the evaluation at θ (with its Jacobian) when the last step made it: lin() reuses it

    def lin():
        sysm = linearise(terms, data, noise, theta, frames, psi, s2, pending.pop() if pending else None)
        if _overflowed(sysm):
            raise _diverged(terms, first, n_gn)
        return sysm

    fresh = first = lin()  # the first round's system (and the start's)
    if system0 is None:
        _refuse_ill_conditioned_full(terms, first)
    if start is None and system0 is None and ridge_start:
        start = _geometric_start(terms, fresh, include)
    rnd = 0
    while rnd < max_rounds:
        sysm = fresh if fresh is not None else lin()
        fresh = None
        fit = refit(sysm, include=include, start=start if hyper is None else hyper[0])
        same = hyper is not None and _same_hyper(hyper[0], fit.alpha)
        hyper, start = (fit.alpha, fit.noise_var), fit.alpha
        step(sysm, fit)
        for _ in range(max_gn):
            sysm = lin()
            fit = refit(sysm, include=include, hyper=hyper)
            n_gn += 1
            if step(sysm, fit, search=True):
                break
        rnd += 1
        if whiten and sysm.blocks and (same or rnd == max_rounds):
            # the rigid error per posture is what the converged model leaves: estimated from an unfinished fit
            # (one whose evidence search still prunes a needed parameter) it absorbs that parameter's signal
            # and the search never gets it back
            psi, s2 = random_effect(_residual(sysm, fit, np.arange(len(sysm.t))), sysm.blocks)
            hyper, whiten, rnd = None, False, 0  # the whitening changes the evidence: search afresh (warm)
            continue
        if same:
            converged = True
            break
    sysm = lin()
    fit = refit(sysm, include=include, hyper=hyper)
    step(sysm, fit, last=True)
    return RelevanceFit(theta, frames, fit, sysm, np.ones(len(ipen), bool) if include is None
                        else np.asarray(include, bool), n_gn, converged)


def _overflowed(sysm: System) -> bool:
    """Whether the whitened system holds a non-finite number, or finite ones whose squares overflow (the
    evidence's sums of squares: a fit that ran away)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return not (np.isfinite(np.einsum("ij,ij->", sysm.Xw, sysm.Xw)) and np.isfinite(float(sysm.tw @ sysm.tw)))


#: the largest condition number of the scaled unpenalised columns that ``geometric="full"`` fits: 1 / the
#: identification's data-level tolerance 1e-4 (GECARO's rank growth, docs/identification.md)
FULL_COND_MAX = 1e4


def _full_conditioning(terms, first) -> tuple[float, str]:
    """The condition number of the scaled unpenalised columns of the first linearisation (registration and, with
    ``geometric="full"``, every geometric parameter), and the words that say what it means."""
    F = first.X[:, : first.n_free] if first is not None else None
    cond = float(np.linalg.cond(F / np.maximum(np.linalg.norm(F, axis=0), 1e-300))) if F is not None else np.nan
    return cond, (f"With geometric='full' the {len(terms.geometric)} geometric parameters have no prior, and on these "
                  f"data they are nearly collinear (condition number {cond:.1e} of their scaled columns): the default "
                  f"geometric='sparse' (`--geometric sparse`) holds the directions the data do not determine near "
                  f"their nominal values")


def _refuse_ill_conditioned_full(terms, first) -> None:
    """``geometric="full"`` on data that do not identify the geometry is refused before any step: the
    Gauss–Newton steps of near-collinear unpenalised parameters run away or not by rounding (TALOS, 40 postures:
    condition number 5e4–1e5, an overflow on one draw of 1e-12 m, an "expected error" of 4e5 mm on another)."""
    from estcal.base.errors import NumericalRefusal

    if terms.geometric_mode != "full":
        return
    cond, words = _full_conditioning(terms, first)
    if cond > FULL_COND_MAX:
        raise NumericalRefusal(f"these data do not identify the geometry at the identification tolerance 1e-4 "
                               f"(condition number above {FULL_COND_MAX:.0e}). {words}")


def _diverged(terms, first, n_gn: int):
    """The refusal of a fit whose residuals overflowed (its Gauss–Newton steps left every plausible robot):
    names the model and, for the unpenalised geometry, the conditioning that let it run away."""
    from estcal.base.errors import NumericalRefusal

    msg = f"the fit diverged after {n_gn} Gauss–Newton step(s): the residuals overflowed"
    if terms.geometric_mode == "full":
        msg += ". " + _full_conditioning(terms, first)[1]
    else:
        msg += "; check the data for a mislabelled joint or unit (estcal check) before a diagnosis"
    return NumericalRefusal(msg)


def _geometric_start(terms, sysm: System, include=None) -> np.ndarray:
    """Precisions to start the evidence search from: every geometric column in the model under one shared
    precision chosen by the evidence (ridge with its width by type-II maximum likelihood:
    :func:`estcal.estimate.sparse.shared_precision`, the registration unpenalised), every effect column out.

    Grown from the empty model instead, the sequential search starts with the noise at a tenth of the data's
    variance — on a robot whose geometric error is a hundred times the noise, far above it — and stops where
    the remaining geometric columns no longer pay at the noise it has reached: a simulated PUMA with 1 mm /
    1 mrad errors measured by one point kept 9 of its 18 identifiable parameters and fitted 0.59 mm where the
    least-squares fit reaches the 0.05 mm noise (``tests/test_diagnose.py``). From the full geometric model
    the search prunes what the evidence does not support; the shared prior keeps the directions the data do not
    determine near the nominal values (a least-squares start would give them wide priors)."""
    from estcal.estimate.sparse import shared_precision

    tidx = terms.term_index()
    geo = np.array([i < 0 for i in tidx], bool)
    if include is not None:
        geo &= np.asarray(include, bool)
    start = np.full(geo.size, np.inf)
    if not geo.any():
        return start
    P = sysm.X[:, sysm.n_free:][:, geo]
    alpha, _ = shared_precision(P, sysm.t, sysm.X[:, : sysm.n_free])
    start[geo] = alpha * np.linalg.norm(P, axis=0) ** 2
    return start


def _same_hyper(a, b, rtol: float = 0.01) -> bool:
    """The same columns kept, every precision within ``rtol`` (relative)."""
    fa, fb = np.isfinite(a), np.isfinite(b)
    return bool(np.array_equal(fa, fb) and np.all(np.abs(a[fa] - b[fb]) <= rtol * np.abs(a[fa])))


# ------------------------------------------------------------------------------------------ CV and naming
def cross_validate(system: System, folds, include=None, start=None) -> dict:
    """Linear cross-validation of the evidence model on ``folds`` (:class:`~estcal.validation.groups.Fold`):
    ``{"sq": per-fold summed squared point errors (m²), "n": per-fold number of points, "errors": (held-out
    position rows,) physical residuals in fold order, "active": (k, M) bool, "fits": the fold fits}``."""
    sq, cnt, act, fits, errs = [], [], [], [], []
    for f in folds:
        tr = system.rows_of(f.train)
        fit = refit(system, tr, include, start)
        e = held_out_errors(system, fit, f.test, f.register)
        pos = system.kind[system.rows_of(f.test)] == 0
        ep = e[pos]
        sq.append(float(ep @ ep))
        cnt.append(int(pos.sum() // 3))
        act.append(fit.active)
        fits.append(fit)
        errs.append(ep)
    return {"sq": np.array(sq), "n": np.array(cnt), "active": np.array(act), "fits": fits, "errors": errs}


def cv_rmse_mm(cv: dict) -> float:
    """RMSE (mm) of the held-out point-error norms of :func:`cross_validate`."""
    return float(np.sqrt(cv["sq"].sum() / max(cv["n"].sum(), 1)) * 1e3)


def fold_mse(sq, n) -> tuple[float, float]:
    """The pooled mean squared error of per-fold squared sums ``sq`` over ``n`` points (m²), and the standard error
    of the per-fold mean squared errors (their spread / √K; NaN with one fold)."""
    per_fold = sq / np.maximum(n, 1)
    se = float(per_fold.std(ddof=1) / np.sqrt(len(per_fold))) if len(per_fold) > 1 else float("nan")
    return float(sq.sum() / max(n.sum(), 1)), se


@dataclass
class Selection:
    """What :func:`select_terms` decided: ``include`` (M,) the penalised columns in the model, ``records`` one
    dict per tested term (label, ln_bf, folds, k_folds, cv_with_mm, cv_without_mm, named, reason), ``named``
    the indices (into ``terms.terms``) of the named terms, ``fit`` the evidence fit with ``include``, ``cv`` its
    cross-validation."""

    include: np.ndarray
    records: list
    named: list
    fit: SparseFit
    cv: dict


def select_terms(terms, system: System, folds, rows=None, start=None, name_load: bool = True,
                 time_folds=None, final_cv: bool = True) -> Selection:
    """The model's terms on the system rows ``rows`` (None: all), naming by the tests of the module docstring
    on ``folds`` (of those rows).

    Naming is a forward search by evidence: from the geometry alone, every candidate (a term the model with
    every term keeps) is scored by its Bayes factor against the causes named so far; in that order the
    first that also survives in most folds and lowers the cross-validated error joins them, and the search
    stops when none does. The Bayes factor of a term is taken against the named causes, not against every
    other relevant term: near-collinear terms of one family (the tilt of neighbouring joints under one
    load) would otherwise explain each other away and none would be named.

    The model: the geometry, every load term the evidence keeps, and the special terms named.
    ``name_load=False`` (the nested prediction): only special terms are candidates — the load terms' names do
    not change the model; ``final_cv=False``: the model's own cross-validation is not needed."""
    tidx = terms.term_index()
    load = np.array([terms.terms[i].load if i >= 0 else True for i in tidx], bool)
    geo = tidx < 0
    start = refit(system, rows, None, start).alpha if start is None else start
    terms_of = [int(i) for i in sorted(set(tidx[tidx >= 0].tolist())) if name_load or not terms.terms[i].load]
    chain = geo.copy()
    cur = refit(system, rows, chain, start)
    cur_cv = cur_tcv = None
    records, named = [], []
    pool = list(terms_of)
    while pool:
        # a shortlist by the cheap screen of the chain's fit — what adding each term alone gains with every other
        # precision held (Tipping & Faul's ℓ, summed over the term's columns) —, then each scored exactly (a
        # refit: its Bayes factor against the causes named so far) and tested in that order; the first that
        # passes every test joins the causes
        screen = {i: float(cur.extra["add_gain"][tidx == i].sum()) for i in pool}
        short = [i for i in sorted(pool, key=lambda i: -screen[i])[:SHORTLIST] if screen[i] >= SCREEN_MIN]
        scored = []
        for i in short:
            f = refit(system, rows, chain | (tidx == i), start)
            scored.append((f.log_evidence - cur.log_evidence, i, f))
        accepted, tried = None, 0
        for ln_bf, i, f in sorted(scored, key=lambda c: -c[0]):
            m = tidx == i
            rec = _term_record(terms.terms[i], ln_bf, f.active[m].any())
            if not rec["reason"] and tried >= TRIED:
                rec.update(named=False, reason=f"not cross-validated: {TRIED} candidates of higher evidence failed "
                                               f"at this step")
            elif not rec["reason"]:
                tried += 1
                if cur_cv is None:
                    cur_cv = cross_validate(system, folds, chain, start)
                cv = cross_validate(system, folds, chain | m, start)
                _fold_tests(rec, cv, cur_cv, m, len(folds))
                if rec["named"] and time_folds:
                    if cur_tcv is None:
                        cur_tcv = cross_validate(system, time_folds, chain, start)
                    _time_test(rec, cross_validate(system, time_folds, chain | m, start), cur_tcv)
                if rec["named"]:
                    accepted = (i, f, cv, rec)
                    break
            records.append(rec)
        if accepted is None:
            break
        i, cur, cur_cv, rec = accepted
        cur_tcv = None
        records.append(rec)
        chain = chain | (tidx == i)
        named.append(i)
        pool.remove(i)
    if len(named) > 1:
        chain, cur, named = _backward(terms, system, rows, folds, start, chain, cur, cur_cv, named, records, tidx)
    final = None  # the cross-validation of the final model, when the last test has made it
    if name_load and any(not terms.terms[i].load for i in named):
        chain, named, final = _against_load(terms, system, rows, folds, start, chain, load, named, records, tidx)
    tested = {r["term"] for r in records}
    for i in pool:  # candidates never scored past the stopping point: their last Bayes factor
        if terms.terms[i].label not in tested:
            records.append(_term_record(terms.terms[i], float("nan"), True))
    # the model: the named causes and the load terms the evidence keeps. Keeping the load terms only when they
    # lower the cross-validated error by more than one standard error was measured and changed nothing on UR10
    # (16 poses, where they raise the nested CV error 3.79 → 4.04 mm) or TALOS
    include = load | chain
    fit = refit(system, rows, include, start)
    cv = (final if final is not None else cross_validate(system, folds, include, start)) if final_cv else None
    return Selection(include, _last_records(records), named, fit, cv)


def _backward(terms, system, rows, folds, start, chain, cur, cur_cv, named, records, tidx):
    """Each named cause tested again against the others (Efroymson's stepwise selection: a forward step, then
    the backward check): a term named early can stand in for causes named after it — from the geometry alone
    a link tilt takes part of two joints' compliances, and once both are named it explains nothing — so every
    cause must still pass the naming tests against the model of the other causes (its Bayes factor, kept in most
    folds, a lower CV error). The one failing with the lowest Bayes factor leaves the causes and the model, and
    the others are tested again, until every one passes. Returns ``(chain, fit, named)``; the failed ones'
    records say what explained them."""
    last = named[-1]  # against the others it meets its own forward step's model: it passes again
    while len(named) > 1:
        fails = []
        for i in named:
            if i == last:
                continue
            rec, f = _retest(terms, system, rows, folds, start, i, chain, cur, cur_cv, tidx)
            if not rec["named"]:
                fails.append((rec["ln_bf"], i, f, rec))
        if not fails:
            break
        _, i, cur, rec = min(fails, key=lambda x: x[0])
        others = ", ".join(terms.terms[j].label for j in named if j != i)
        rec.update(named=False, reason=f"withdrawn after naming: explained by the other named causes ({others}): "
                                       f"{rec['reason']}")
        records.append(rec)
        chain = chain & ~(tidx == i)
        named = [j for j in named if j != i]
        cur_cv = cross_validate(system, folds, chain, start)
        last = None
    return chain, cur, named


def _against_load(terms, system, rows, folds, start, chain, load, named, records, tidx):
    """Each named special term (it enters the model only when named) tested again against the model it enters:
    the geometry, the load terms the evidence keeps and the other named causes — the forward search scored it
    against the named causes alone, and a harmonic or a drift can stand in for a load term kept unnamed. Every
    naming test again (Bayes factor, most folds, CV lower by one standard error); the one failing with the lowest
    Bayes factor leaves, the others are tested again. Returns ``(chain, named, the cross-validation of the model
    with the load terms and the causes left)``."""
    while True:
        include = load | chain
        cur = refit(system, rows, include, start)
        cur_cv = cross_validate(system, folds, include, start)
        fails = []
        for i in named:
            if terms.terms[i].load:
                continue
            rec, _ = _retest(terms, system, rows, folds, start, i, include, cur, cur_cv, tidx)
            if not rec["named"]:
                fails.append((rec["ln_bf"], i, rec))
        if not fails:
            return chain, named, cur_cv
        _, i, rec = min(fails, key=lambda x: x[0])
        rec.update(named=False, reason=f"withdrawn after naming: explained by the load terms the evidence keeps: "
                                       f"{rec['reason']}")
        records.append(rec)
        chain = chain & ~(tidx == i)
        named = [j for j in named if j != i]


def _retest(terms, system, rows, folds, start, i, include, cur, cur_cv, tidx):
    """The naming tests of term ``i`` against the model ``include`` without it (``cur``, ``cur_cv``: the fit and the
    cross-validation of ``include``, which holds it): ``(its record, the fit without it)``."""
    m = tidx == i
    without = include & ~m
    f = refit(system, rows, without, start)
    rec = _term_record(terms.terms[i], cur.log_evidence - f.log_evidence, cur.active[m].any())
    if not rec["reason"]:
        _fold_tests(rec, cur_cv, cross_validate(system, folds, without, start), m, len(folds))
    return rec, f


def _last_records(records) -> list:
    """One record per term: its last test (a term scored at several steps keeps the latest)."""
    out = {}
    for r in records:
        out[r["term"]] = r
    return list(out.values())


def _term_record(term, ln_bf, survives) -> dict:
    """The first tests of a term (it survives; its Bayes factor); ``reason`` lists the failures (a NaN Bayes
    factor: not scored — the search stopped before it)."""
    reasons = [] if survives else ["pruned by the evidence"]
    if np.isnan(ln_bf):
        reasons.append("not scored (the search stopped before it)")
    elif not ln_bf >= LN_BF_NAMED:
        reasons.append(f"ln B = {ln_bf:.1f} < {LN_BF_NAMED:g}")
    return {"term": term.label, "effect": term.effect, "joints": list(term.joints), "options": dict(term.options),
            "load": term.load, "ln_bf": float(ln_bf), "folds": None, "k_folds": None, "cv_with_mm": None,
            "cv_without_mm": None, "named": not reasons, "reason": "; ".join(reasons)}


def _time_test(rec, cv_with, cv_without) -> None:
    """The time test (in place): with the term, the time-blocked cross-validated error (contiguous blocks of the
    acquisition) is lower too — a term that fits interleaved folds but not a later stretch of the campaign
    describes the campaign, not the robot."""
    with_mm, without_mm = cv_rmse_mm(cv_with), cv_rmse_mm(cv_without)
    rec.update(cv_time_with_mm=with_mm, cv_time_without_mm=without_mm)
    if not with_mm < without_mm:
        rec["named"] = False
        rec["reason"] = f"time-blocked CV {with_mm:.3f} mm with it, {without_mm:.3f} without"


def _fold_tests(rec, cv_with, cv_without, m, k) -> None:
    """The last two tests (in place): kept in more than half of the folds of ``cv_with`` (the model with the
    term), and a lower cross-validated error with it than without it."""
    reasons = [rec["reason"]] if rec["reason"] else []
    n_folds = int(cv_with["active"][:, m].any(1).sum())
    with_mm, without_mm = cv_rmse_mm(cv_with), cv_rmse_mm(cv_without)
    # the gain must exceed one standard error of the per-fold gains (the one-standard-error rule: Breiman et
    # al. 1984; Hastie, Tibshirani & Friedman, ESL §7.10): a gain the folds disagree on is not a gain
    d = cv_without["sq"] - cv_with["sq"]
    se = float(d.std(ddof=1) * np.sqrt(len(d))) if len(d) > 1 else np.inf
    if not n_folds > k / 2:
        reasons.append(f"kept in {n_folds} of {k} folds")
    if not d.sum() > se:
        reasons.append(f"CV {with_mm:.3f} mm with it, {without_mm:.3f} without: not lower by one standard error")
    rec.update(folds=n_folds, k_folds=k, cv_with_mm=with_mm, cv_without_mm=without_mm, named=not reasons,
               reason="; ".join(reasons))
