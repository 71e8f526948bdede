"""Data hygiene before a fit (``estcal check``): the rows a calibration should not trust, named by line.

Each finding has a ``kind``, the file ``lines`` it concerns and a ``message``:

``duplicate_row``
    a row identical, bit for bit, to an earlier one (readings and measurements) — a copy, not
    a new measurement; it would count twice in the fit.
``repeated_pose``
    postures measured more than once (joint readings equal within 1 mrad / 1 mm on every
    joint, :func:`estcal.validation.posture_groups`), with the repeatability they show
    (:func:`estcal.validation.repeatability_floor`, mm): information, not a defect.
``out_of_limits``
    a joint reading beyond the robot's limits (a wild encoder value, a wrapped angle).
``non_rigid``
    points of one rigid body whose inter-point distances are off the file's median shape by
    more than ``max(1 mm, 8 σ)`` (σ: robust spread of all distances about the median shape) and
    that no relabelling repairs: an occluded or ghost marker.
``marker_swap``
    a row whose points match the rigid shape only after relabelling: the repaired order is
    given (``order[k]`` = the measured point that is point k + 1). When the shape has a
    symmetry (several labellings fit), the labelling closest to the registered model decides.
``outlier``
    a pose whose residual after a robust fit is beyond the Bonferroni limit (below).
``unexplained``
    the robot's nominal model leaves a residual of the order of the measured positions' own spread
    once the unknown frames are registered (:mod:`estcal.intake.explained`): random or unrelated
    numbers, positions that do not follow the joints, another robot — no row can be blamed.
``unused_column``
    file columns nothing reads (named so that a misspelt or unmapped column is seen); those
    that look like joints of the robot that the chain does not have are said so.

Outlier test
------------
The kinematic model is fitted with the Huber kernel (:func:`estcal.estimate.robust.calibrate_irls`)
at the richest level the data support (``full`` when the residual rows outnumber its candidate
parameters 5 times, else ``joint_offset``, else ``registration``). For every pose ``g`` (m
residual rows, Jacobian block ``J_g``) the externally studentised squared residual is
``q_g = e_gᵀ (I ∓ J_g (JᵀJ)⁻¹ J_gᵀ)⁻¹ e_g`` (JᵀJ of the poses not flagged; − for those, + for
flagged poses, whose residual is then a prediction). Real residuals are dominated by model
error — correlated between the rows of a pose and heavy-tailed — so the clean poses' ``q`` are
modelled as ``c·χ²_d`` with ``d`` (between 0.25 and m) matched to the ratio of their 90 % and
50 % quantiles and ``c`` to their median: a quantile match that up to 10 % of outliers cannot
move (moment matching, Satterthwaite's, let one blunder inflate the variance and mask itself).
Poses beyond 8× the median residual are set aside before the quantiles are taken (and judged
like the others afterwards). A pose is an outlier when ``q_g / c > χ²_d(1 − α/N)`` (Bonferroni over the N poses, α = 0.05);
iterated until the flagged set is stable. Simulated Gaussian data give ``d ≈ m``; the real
files give d ≈ 1 — that is why a 3 mm blunder is named among 0.1 mm noise but not among 2 mm
of model error.

Rows flagged as duplicates, out of limits, non-rigid or swapped are left out of that fit.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import permutations

import numpy as np

from estcal.estimate.robust import chi2_median, chi2_ppf

__all__ = ["Finding", "CheckReport", "check_data", "studentised_outliers", "DEFECTS", "KINDS"]

KINDS = ("unexplained", "marker_swap", "non_rigid", "outlier", "out_of_limits", "repeated_pose", "duplicate_row",
         "unused_column")
#: kinds that mark rows a fit should not use (``--drop-flagged`` removes them)
DEFECTS = ("marker_swap", "non_rigid", "outlier", "out_of_limits", "duplicate_row")
ALPHA = 0.05
LIMIT_SLACK = 0.01  # readings at a limit overshoot it by encoder noise (TIAGo torso: 0.35018 m for 0.35)
RIGID_FLOOR_M = 1e-3
MAX_PERM_POINTS = 6
RIGID_CHUNK_NUMBERS = 4_000_000  # floats per chunk of the relabelling test (32 MB)
ROWS_PER_PARAMETER = 5
QUANTILES = (0.5, 0.9)
GROSS = 8.0  # residual / median residual set aside before the quantiles are taken
D_MIN = 0.25  # matched dof floor (gamma shape 0.125: heavier tails than any real file showed)


@dataclass
class Finding:
    kind: str
    lines: list
    message: str
    details: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "lines": [int(x) for x in self.lines], "message": self.message, **self.details}


@dataclass
class CheckReport:
    """Findings of :func:`check_data`; ``to_dict()`` is the JSON of ``estcal check --json``."""

    path: str
    n_rows: int
    findings: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    def flagged_lines(self, kinds=DEFECTS) -> list[int]:
        return sorted({int(x) for f in self.findings if f.kind in kinds for x in f.lines})

    def to_dict(self) -> dict:
        return {"data": self.path, "rows": self.n_rows, "findings": [f.to_dict() for f in self.findings],
                "notes": list(self.notes)}

    def messages(self) -> list[str]:
        return [f"{f.kind}: {f.message}" for f in self.findings]


def _lines_text(lines, most: int = 12) -> str:
    lines = [int(x) for x in lines]
    s = ", ".join(str(x) for x in lines[:most])
    return s + (f" … ({len(lines)} lines)" if len(lines) > most else "")


# ----------------------------------------------------------------------------- duplicates, postures
def _duplicates(ds) -> tuple[list, np.ndarray]:
    from estcal.io.dataset import _row_keys

    keys = _row_keys(ds)
    _, first, inv, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
    dup = np.flatnonzero(first[inv] != np.arange(ds.n))
    out = []
    if dup.size:
        groups = {}
        for i in dup:
            groups.setdefault(int(first[inv[i]]), []).append(int(i))
        shown = sorted(groups.items())[:10]
        desc = "; ".join(f"line {ds.lines[a]} repeated at {_lines_text(ds.lines[b], 6)}" for a, b in shown)
        more = f"; … {len(groups) - 10} more rows repeated" if len(groups) > 10 else ""
        out.append(Finding("duplicate_row", list(ds.lines[dup]),
                           f"{dup.size} row(s) identical to an earlier row (readings and measurements, bit for bit): "
                           f"{desc}{more} — copies count twice in a fit"))
    return out, dup


def _repeated(ds, robot, skip) -> list:
    from estcal.validation import posture_groups, repeatability_floor

    keep = np.setdiff1d(np.arange(ds.n), skip)
    if keep.size < 2:
        return []
    g = posture_groups(ds.readings[keep], robot.joint_types)
    labels, counts = np.unique(g, return_counts=True)
    rep = labels[counts > 1]
    if not rep.size:
        return []
    pts = ds.points if ds.points is not None else ds.p
    rows = np.flatnonzero(np.isin(g, rep))
    fl = repeatability_floor(pts[keep], g) if pts is not None else None
    groups = [[int(ds.lines[keep[i]]) for i in np.flatnonzero(g == lab)] for lab in rep]
    rep_mm = None if fl is None else float(fl["raw_mm"])
    txt = "; ".join(", ".join(str(x) for x in grp) for grp in groups[:8]) + (" …" if len(groups) > 8 else "")
    msg = (f"{len(groups)} posture(s) measured more than once (joint readings equal within 1 mrad / 1 mm): lines {txt}"
           + (f"; repeatability {rep_mm:.3g} mm (RMS distance of a measurement from its posture's mean)"
              if rep_mm is not None else ""))
    return [Finding("repeated_pose", [int(ds.lines[keep[i]]) for i in rows], msg,
                    {"groups": groups, "repeatability_mm": rep_mm})]


# ----------------------------------------------------------------------------- limits
def _limits(ds, robot) -> tuple[list, np.ndarray]:
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    skip = set(robot.meta.get("continuous", ()))
    tol = LIMIT_SLACK * (hi - lo)
    bad = (ds.readings < lo - tol) | (ds.readings > hi + tol)
    for j, name in enumerate(robot.joint_names):
        if name in skip:
            bad[:, j] = False
    rows = np.flatnonzero(bad.any(axis=1))
    out = []
    for i in rows:
        parts = []
        for j in np.flatnonzero(bad[i]):
            unit = "m" if robot.joint_types[j] == "prismatic" else "rad"
            parts.append(f"{robot.joint_names[j]} = {ds.readings[i, j]:.6g} {unit} outside [{lo[j]:.4g}, {hi[j]:.4g}]")
        out.append(Finding("out_of_limits", [int(ds.lines[i])], f"line {ds.lines[i]}: " + "; ".join(parts)))
    return out, rows


# ----------------------------------------------------------------------------- rigid body
def _pair_distances(P):
    k = P.shape[-2]
    a, b = np.triu_indices(k, 1)
    return np.linalg.norm(P[..., a, :] - P[..., b, :], axis=-1), (a, b)


def _rigidity(ds, robot, skip, predicted=None) -> tuple[list, np.ndarray, np.ndarray]:
    """non_rigid and marker_swap findings for k ≥ 2 points (module docstring); ``predicted``:
    (N, k, 3) model points (after registration) to choose among symmetric labellings."""
    P = ds.points
    k = P.shape[1]
    if k < 2 or k > MAX_PERM_POINTS:
        return [], np.zeros(0, int), np.zeros(0, int)
    D, (a, b) = _pair_distances(P)
    use = np.setdiff1d(np.arange(ds.n), skip)
    ref = np.median(D[use], axis=0)
    spread = 1.4826 * np.median(np.abs(D[use] - ref))
    tol = max(RIGID_FLOOR_M, 8 * spread)
    perms = np.array(list(permutations(range(k))))
    # distance vector of every row under every labelling: D_π[i] uses points π(a), π(b) — in chunks of
    # rows, since (rows, perms, pairs, 3) is k!·k(k−1)/2·3 numbers a row (1.1 kB at k = 4, 600 kB at 6)
    dev = np.empty((ds.n, len(perms)))
    step = max(1, RIGID_CHUNK_NUMBERS // (len(perms) * len(a) * 3))
    for c in range(0, ds.n, step):
        Pc = P[c:c + step]
        Dp = np.linalg.norm(Pc[:, perms[:, a], :] - Pc[:, perms[:, b], :], axis=-1)  # (rows, perms, pairs)
        dev[c:c + step] = np.abs(Dp - ref).max(axis=-1)
    fits = dev <= tol
    out, non_rigid, swapped = [], [], []
    for i in range(ds.n):
        if i in skip:
            continue
        cand = np.flatnonzero(fits[i])
        if not cand.size:
            worst = int(np.argmax(np.abs(D[i] - ref)))
            non_rigid.append(i)
            out.append(Finding("non_rigid", [int(ds.lines[i])],
                               f"line {ds.lines[i]}: distance between points {a[worst] + 1} and {b[worst] + 1} is "
                               f"{1e3 * D[i, worst]:.1f} mm, the file's median shape has {1e3 * ref[worst]:.1f} mm "
                               f"(tolerance {1e3 * tol:.2g} mm) and no relabelling fits — an occluded or ghost marker?"))
            continue
        if predicted is not None and cand.size > 1:
            cost = np.linalg.norm(P[i, perms[cand]] - predicted[i], axis=-1).sum(axis=-1)
            best = cand[int(np.argmin(cost))]
        elif fits[i, 0]:
            best = 0
        else:
            best = cand[int(np.argmin(dev[i, cand]))]
        if best != 0:
            order = [int(x) + 1 for x in perms[best]]
            swapped.append(i)
            out.append(Finding("marker_swap", [int(ds.lines[i])],
                               f"line {ds.lines[i]}: the points are labelled in another order — read them as "
                               f"{', '.join(f'point {o}' for o in order)} (columns x{order[0]}… first) to match the "
                               f"rigid body", {"order": order}))
    return out, np.asarray(non_rigid, int), np.asarray(swapped, int)


# ----------------------------------------------------------------------------- outliers
def auto_level(robot, ds) -> str:
    """The richest level whose candidate parameters the data outnumber :data:`ROWS_PER_PARAMETER`
    times (a model error left in the residuals hides blunders; too many parameters absorb them)."""
    from estcal.estimate.levels import level_candidates

    per_pose = 6 if ds.kind == "pose" else 3 * max(ds.n_points, 1)
    rows = ds.n * per_pose
    for lev in ("full", "joint_offset"):
        n = sum(len(g) for g in level_candidates(robot.params, lev, ds.kind == "pose"))
        if rows >= ROWS_PER_PARAMETER * n:
            return lev
    return "registration"


def _robust_fit(robot, ds, level):
    """Huber IRLS fit of the identifiable set of ``level`` after the base registration (the steps
    of ``estcal calibrate`` without its refusals); ``(result, problem at the registration, level)``."""
    import warnings

    from estcal.estimate import register_base
    from estcal.estimate.levels import select_free
    from estcal.estimate.lsq import calibrate_lsq
    from estcal.methods import NoiseModel, Problem

    level = auto_level(robot, ds) if level == "auto" else level
    noise = NoiseModel()
    prob = Problem(robot, [(None, ds, noise)], noise)
    if ds.kind in ("position", "points", "pose") and "base_tx" in prob.params:
        prob = prob.with_values(register_base(prob.robot, ds, prob.params.values.copy()))
    last = None
    for lev in ((level, "registration") if level != "registration" else ("registration",)):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sel = select_free(prob, lev, known_noise=noise.known)
                # IRLS to 1e-4 in the weights: the test needs the outliers' weights, not 10 digits
                res = calibrate_lsq(prob.with_values(sel.theta), "lm", free=sel.identifiable, robust="huber",
                                    tol=1e-4)
            return res, prob, lev
        except (ValueError, np.linalg.LinAlgError) as exc:
            last = exc
    raise last


def _matched_chi2(q, d_max: float):
    """``(d, c)`` with ``q ≈ c·χ²_d``: ``d`` from the ratio of the 90 % and 50 % quantiles of ``q``
    (a ratio that depends on ``d`` only, and that up to 10 % of outliers cannot move), ``c`` from
    the median."""
    from scipy import optimize

    lo, hi = np.quantile(q, [QUANTILES[0], QUANTILES[1]])
    if not lo > 0:
        return d_max, float(np.mean(q)) / d_max if np.mean(q) > 0 else 1.0
    target = hi / lo

    def ratio(d):
        return chi2_ppf(QUANTILES[1], d) / chi2_ppf(QUANTILES[0], d) - target

    if ratio(d_max) >= 0:  # lighter tails than χ²_m: the nominal dof
        d = d_max
    elif ratio(D_MIN) <= 0:
        d = D_MIN
    else:
        d = float(optimize.brentq(ratio, D_MIN, d_max))
    return d, float(lo / chi2_ppf(QUANTILES[0], d))


def _pose_blocks(rows, n_poses: int):
    """Whitened Jacobian rows grouped by pose: ``(g, order, starts, dims)``."""
    g = np.asarray(rows.pose, int)
    dims = np.bincount(g, minlength=n_poses)
    order = np.argsort(g, kind="stable")
    return g, order, np.r_[0, np.cumsum(dims)], dims


def _studentised_q(J, e, blocks, Ai, predicted) -> np.ndarray:
    """``q_g = e_gᵀ (I ∓ J_g A⁻¹ J_gᵀ)⁻¹ e_g`` of every pose (− fitted, + ``predicted``), vectorised over
    the poses of each residual dimension m (m × m solves in one call)."""
    g, order, starts, dims = blocks
    q = np.zeros(dims.size)
    for m in np.unique(dims[dims > 0]):
        poses = np.flatnonzero(dims == m)
        rr = order[starts[poses][:, None] + np.arange(m)]  # (poses, m) rows of each pose
        Jg, eg = J[rr], e[rr]
        h = (Jg @ Ai) @ np.swapaxes(Jg, 1, 2)  # J_g A⁻¹ J_gᵀ per pose, two batched products
        sign = np.where(predicted[poses], 1.0, -1.0)[:, None, None]
        M = np.eye(m) + sign * h
        q[poses] = np.einsum("gi,gi->g", eg, np.linalg.solve(M, eg[..., None])[..., 0])
    return q


def _studentised(problem, theta, names, n_poses: int, alpha: float = ALPHA, max_iter: int = 20) -> dict:
    """The iteration of :func:`studentised_outliers`; also returns what scores other poses against the
    same fit: ``Ai`` = (JᵀJ)⁻¹ of the unflagged poses and the scale ``c`` of the statistic."""
    rows = problem.evaluate(theta)
    fi = problem.params.indices(list(names))
    J = rows.H[:, fi] / rows.sigma[:, None]
    e = rows.e / rows.sigma
    blocks = _pose_blocks(rows, n_poses)
    g, dims = blocks[0], blocks[3]
    N = n_poses
    flag = np.zeros(N, bool)
    F = np.zeros(N)
    d = float(dims.max())
    scale = 1.0
    for it in range(max_iter):
        keep = ~flag[g]
        Ai = np.linalg.pinv(J[keep].T @ J[keep])
        q = _studentised_q(J, e, blocks, Ai, flag)
        if it == 0:  # gross residuals out of the quantiles first (then judged like the others)
            flag = q > GROSS ** 2 * np.median(q)
            if flag.any():
                continue
        qk = q[~flag]
        if qk.size < 5:
            break
        d, scale = _matched_chi2(qk, float(dims.max()))
        F = q / scale
        new = F > chi2_ppf(1 - alpha / N, d)
        if np.array_equal(new, flag):
            break
        flag = new
    return {"flag": flag, "F": F, "d": d, "scale": scale, "Ai": Ai, "J_columns": fi}


def studentised_outliers(problem, theta, names, n_poses: int, alpha: float = ALPHA, max_iter: int = 20):
    """``(flag, F, d)``: poses beyond the Bonferroni limit of the studentised residual test (module
    docstring), their statistics ``F = q/c`` (≈ χ²_d for clean poses) and the matched dof ``d``."""
    out = _studentised(problem, theta, names, n_poses, alpha, max_iter)
    return out["flag"], out["F"], out["d"]


#: poses above which the outlier test fits its robust model, and sets the scale of its statistic, on an
#: evenly spaced sample of this many poses; every pose is then tested against that fit, chunk by chunk
#: (memory O(sample + chunk), not O(rows × parameters))
OUTLIER_FIT_MAX_POSES = 20_000
SCORE_CHUNK_POSES = 20_000


def _score_all(prob, theta, st: dict, sub, sample) -> np.ndarray:
    """``F`` of every pose of ``sub`` against the fit on ``sub.subset(sample)`` (predictions for the poses
    outside the sample, the sample's own statistics for the others), chunk by chunk."""
    from estcal.methods.problem import Problem, Term

    F = np.empty(sub.n)
    t = prob.terms[0]
    for a in range(0, sub.n, SCORE_CHUNK_POSES):
        part = sub.subset(slice(a, a + SCORE_CHUNK_POSES))
        cp = Problem.__new__(Problem)
        cp.robot, cp.terms = prob.robot, [Term(t.method, part, t.noise)]
        rows = cp.evaluate(theta)
        J = rows.H[:, st["J_columns"]] / rows.sigma[:, None]
        e = rows.e / rows.sigma
        F[a:a + part.n] = _studentised_q(J, e, _pose_blocks(rows, part.n), st["Ai"], np.ones(part.n, bool)) \
            / st["scale"]
    F[sample] = st["F"]
    return F


def _outliers(robot, ds, skip, level, alpha) -> tuple[list, dict]:
    keep = np.setdiff1d(np.arange(ds.n), skip)
    sub = ds.subset(keep)
    sample = None
    fit = sub
    if sub.n > OUTLIER_FIT_MAX_POSES:
        sample = np.unique(np.linspace(0, sub.n - 1, OUTLIER_FIT_MAX_POSES).astype(int))
        fit = sub.subset(sample)
    res, prob, lev = _robust_fit(robot, fit, level)
    st = _studentised(prob, res.theta, res.names, fit.n, alpha)
    d = st["d"]
    if sample is None:
        flag, F = st["flag"], st["F"]
    else:
        F = _score_all(prob, res.theta, st, sub, sample)
        flag = F > chi2_ppf(1 - alpha / sub.n, d)
    med = chi2_median(d)
    limit = float(np.sqrt(chi2_ppf(1 - alpha / sub.n, d) / med))
    out = []
    for i in np.flatnonzero(flag):
        ratio = float(np.sqrt(F[i] / med))
        out.append(Finding("outlier", [int(sub.lines[i])],
                           f"line {sub.lines[i]}: residual {ratio:.1f}× the median pose's after a robust fit "
                           f"({lev} level) — beyond the Bonferroni limit {limit:.1f}× (α = {alpha:g} over {sub.n} "
                           f"poses, {d:.2g} matched dof)", {"ratio": ratio}))
    info = {"level": lev, "effective_dof": d, "limit_ratio": limit, "theta": res.theta, "problem": prob,
            "kept": keep, "sampled": None if sample is None else int(sample.size)}
    return out, info


# ----------------------------------------------------------------------------- columns
def unused_columns(ds, robot) -> tuple[list, list, str | None]:
    """``(unused, joint_like, map)``: the file columns nothing reads (through a column map: also the file
    columns the map left out), those that look like joints the robot does not have, and a column map
    that would read the others as a measured orientation (:func:`estcal.io.columnmap.suggest_map`),
    else None."""
    from estcal.io.columnmap import suggest_map
    from estcal.io.columns import METHOD_COLUMNS
    from estcal.io.dataset import foreign_joint_columns

    window = ("t_start_robot", "t_end_robot")
    read = {c for c in METHOD_COLUMNS if c not in window}  # read by the measurement methods
    if "t" in ds.context and all(c in ds.columns for c in window) and "t" not in ds.renamed:
        read |= set(window)  # t is the middle of the window
    carried = [c for c in ds.columns if c not in read]
    if ds.source_header is None:
        unused, header = carried, None
    else:  # through a column map: also the file columns the map left out
        sources = {s for v in ds.renamed.values() for s in v.split("/")}
        unused = [h for h in ds.source_header if h and h not in sources and (h in carried or h not in ds.columns)]
        header = list(ds.source_header)
    foreign = foreign_joint_columns(unused, robot)
    suggestion = None
    if ds.kind == "position" and ds.coordinates and unused:
        pos = [ds.renamed.get(c, c) for c in ds.coordinates]
        suggestion = suggest_map(unused, header or list(ds.columns) + pos, [pos])
    return unused, foreign, suggestion


def unused_message(ds, robot, unused, foreign, suggestion) -> str:
    """The sentence naming the unused columns, with the column map that would read them."""
    msg = f"column(s) {', '.join(unused)} are not used"
    if foreign:
        msg += (f"; {', '.join(foreign)} look like joints the robot {robot.name!r} does not have (its joints: "
                f"{', '.join(robot.joint_names)}) — wrong chain (--root/--tip), a truncated robot file, or map them")
    if suggestion:
        from estcal.io.columnmap import published_map

        known = published_map((ds.source_header or []) + list(ds.columns) + [ds.renamed.get(c, c) for c in
                                                                              ds.coordinates or []],
                              [c for c in unused if c not in foreign])
        msg += (f" — they look like the measured orientation: read the file as a full pose with a column map "
                f"(--map MAP.yaml) holding `{suggestion}`" + (f" ({known} is that map)" if known else "")
                + "; without it only the positions are fitted")
    return msg


def _unused(ds, robot) -> list:
    unused, foreign, suggestion = unused_columns(ds, robot)
    if not unused:
        return []
    return [Finding("unused_column", [], unused_message(ds, robot, unused, foreign, suggestion),
                    {"columns": unused, "joint_like": foreign, "map": suggestion})]


def _unexplained(robot, ds) -> list:
    from .explained import UNEXPLAINED_RATIO, explained, unexplained_message

    fig = explained(robot, ds)
    if fig is None or not fig["ratio"] > UNEXPLAINED_RATIO:
        return []
    msg = unexplained_message(fig, f"the nominal model of {robot.name!r} does not explain these data")
    return [Finding("unexplained", [], msg, {k: fig[k] for k in ("rmse_m", "spread_m", "ratio")})]


# ----------------------------------------------------------------------------- entry point
def check_data(robot, ds, *, level: str = "auto", alpha: float = ALPHA, outliers: bool = True) -> CheckReport:
    """All checks of the module docstring on a loaded dataset (robot with one marker per measured point
    for point data). Returns a :class:`CheckReport`; lines are the file's."""
    report = CheckReport(ds.where, ds.n)
    report.findings += _unexplained(robot, ds)
    dup_f, dup = _duplicates(ds)
    lim_f, lim = _limits(ds, robot)
    report.findings += dup_f
    skip = np.union1d(dup, lim)
    rig_f = []
    if ds.points is not None and ds.n_points >= 2:
        rig_f, bad, sw = _rigidity(ds, robot, set(skip.tolist()))
        skip = np.union1d(skip, np.union1d(bad, sw))
    distinct = ds.n - dup.size
    out_f = []
    info = None
    if outliers and ds.kind in ("position", "points", "pose") and distinct >= 8:
        try:
            out_f, info = _outliers(robot, ds, skip, level, alpha)
        except (ValueError, np.linalg.LinAlgError) as exc:
            report.notes.append(f"no outlier test: the robust fit failed ({' '.join(str(exc).split())[:200]})")
    elif outliers:
        report.notes.append(f"no outlier test: {distinct} distinct rows (at least 8 needed)")
    if info is not None and ds.points is not None and ds.n_points >= 2:
        # symmetric shapes: relabel by the registered model where several labellings fit
        from estcal.kinematics.chunked import tool_poses

        pred = tool_poses(robot, ds.readings, info["theta"], ds.context, fields=("points",))["points"]
        if pred.shape[1] >= ds.n_points:
            rig_f, _, _ = _rigidity(ds, robot, set(np.union1d(dup, lim).tolist()), pred[:, :ds.n_points])
    report.findings += rig_f + lim_f + out_f
    report.findings += _repeated(ds, robot, dup)
    report.findings += _unused(ds, robot)
    if info is not None:
        on = (f" on an evenly spaced sample of {info['sampled']:,} of {len(info['kept']):,} rows (the memory stays "
              f"bounded; every row is tested against that fit)" if info["sampled"] else "")
        report.notes.append(f"outlier test: robust fit at the {info['level']} level{on}, Bonferroni α = {alpha:g}, "
                            f"{info['effective_dof']:.2g} matched dof")
    order = {k: i for i, k in enumerate(KINDS)}
    report.findings.sort(key=lambda f: (order[f.kind], f.lines[:1]))
    return report
