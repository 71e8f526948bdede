"""Helpers shared by the probabilistic and recursive estimators.

Every estimator here (factor graph, Kalman filters, MCMC) consumes a
:class:`~estcal.methods.problem.Problem` and splits its stacked rows into
*measurement groups*: the rows of one dataset row (pose) of one term. A group
is the unit a filter processes at a time and the unit of one factor in the
factor graph. :class:`GroupedProblem` builds, for any set of groups, a
sub-problem whose rows are exactly those groups' rows (via
``Dataset.subset``), so a filter step or a factor evaluates only its own poses.
Problem-like objects without splittable terms (e.g. the Gough adapter) fall
back to evaluating the full problem and selecting rows.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estcal.methods.base import Rows
from estcal.methods.problem import Problem, Term
from estcal.methods.reduced import PER_POSE_METHODS, chi2_and_rows, evaluate_chunks, use_chunks

from .result import CalibrationResult, score

__all__ = ["GroupedProblem", "evaluate_many", "resolve_free", "noise_known", "finish_result",
           "default_prior_std", "prior_std_vector"]


def resolve_free(problem, free=None):
    """``(problem, fidx, names)`` with the free set applied (patterns allowed)."""
    if free is not None:
        problem = problem.with_free(free)
    pv = problem.params
    fidx = pv.free_indices
    if fidx.size == 0:
        raise ValueError("no free parameter to estimate (give --free or set the robot's free mask)")
    return problem, fidx, [pv.names[i] for i in fidx]


def noise_known(problem) -> bool:
    """True when every term's noise is a trusted absolute value (``NoiseModel.known``)."""
    return all(bool(getattr(getattr(t, "noise", None), "known", False)) for t in getattr(problem, "terms", []))


def default_prior_std(problem, names, scale: float = 1.0) -> np.ndarray:
    """Documented default prior standard deviations (SI), per parameter kind.

    ``0.1`` m or rad for geometric, base, tool, offset, marker and other
    parameters, ``0.1`` for the dimensionless gains: wide compared with any
    plausible calibration correction (mm, mrad) yet proper, so the filter and
    the posterior are defined before the data make every parameter identifiable.
    """
    return np.full(len(names), 0.1 * scale)


def prior_std_vector(problem, names, prior_std=None) -> np.ndarray:
    """Prior stds of the free parameters from ``None`` (defaults), a scalar, an array, or
    ``{name or pattern: std}`` (others keep their default)."""
    import fnmatch

    s = default_prior_std(problem, names)
    if prior_std is None:
        return s
    if isinstance(prior_std, dict):
        for k, v in prior_std.items():
            hit = [i for i, n in enumerate(names) if fnmatch.fnmatchcase(n, k)]
            if not hit:
                raise ValueError(f"prior_std: {k!r} matches no free parameter (free: {names})")
            s[hit] = float(v)
        return s
    out = np.broadcast_to(np.asarray(prior_std, float), (len(names),)).copy()
    if np.any(out <= 0):
        raise ValueError("prior standard deviations must be positive")
    return out


def _units(term, n):
    """Unit id of every dataset row of a term: the row itself, or its ``group`` / ``pair`` id."""
    name = getattr(term.method, "name", "")
    cols = getattr(term.data, "columns", {}) or {}
    if name not in PER_POSE_METHODS:
        for c in ("pair", "group"):
            if c in cols:
                _, inv = np.unique(np.asarray(cols[c]), return_inverse=True)
                return inv.reshape(-1)
    return np.arange(n)


@dataclass
class Group:
    term: int
    poses: np.ndarray  # dataset rows of the term that form this measurement unit

    @property
    def pose(self) -> int:
        return int(self.poses[0])


class GroupedProblem:
    """A problem split into measurement groups (units processed together).

    A group is one dataset row of one term (``position``, ``location``, ``points``,
    planes with known/unknown plane), or — for methods comparing rows (``point-link``,
    ``frame-link``, ``plane-normal-*`` by their ``group`` column, ``distance`` by ``pair``)
    — all rows of one group / pair, so that a filter step or a factor sees a complete unit.

    Parameters
    ----------
    problem : Problem (or a Problem-like object with ``params`` and ``evaluate``).

    Attributes
    ----------
    groups : list of :class:`Group`, ordered term by term, unit by first row (or by the
        earliest ``t`` when every term has a ``t`` context column).
    row_group : (M,) group id of every row of ``problem.evaluate()``.
    """

    def __init__(self, problem):
        self.problem = problem
        terms = getattr(problem, "terms", None)
        self.splittable = bool(terms) and all(hasattr(t.data, "subset") for t in terms)
        ck = use_chunks(problem) if terms else None
        if ck is not None:  # large per-pose data (one term): the row → pose map chunk by chunk
            pose = np.concatenate([np.asarray(r.pose, int) + a for a, r in evaluate_chunks(problem, None, ck, False)])
            term = np.zeros(pose.size, int)
        else:
            rows = problem.evaluate(jacobian=False)
            pose = np.asarray(rows.pose, int)
            term = rows.term if rows.term is not None else np.zeros(pose.size, int)
        self.n_rows = pose.size
        if not self.splittable:
            keys = sorted(set(zip(term.tolist(), pose.tolist())))
            self.groups = [Group(int(a), np.array([b])) for a, b in keys]
            self.unit_of = None
            index = {(g.term, g.pose): i for i, g in enumerate(self.groups)}
            self.row_group = np.array([index[(a, b)] for a, b in zip(term.tolist(), pose.tolist())])
            return
        groups, self.unit_of = [], []
        for ti, t in enumerate(terms):
            u = _units(t, t.data.n)  # ids 0 … U−1
            _, first = np.unique(u, return_index=True)
            order = np.argsort(first)  # units in the order of their first row
            gid = np.empty(u.max() + 1 if u.size else 0, int)
            gid[order] = len(groups) + np.arange(order.size)
            # the rows of every unit in one stable sort (ascending within a unit), not one scan per unit
            rows_of_unit = np.split(np.argsort(u, kind="stable"), np.cumsum(np.bincount(u))[:-1]) if u.size else []
            groups.extend(Group(ti, rows_of_unit[uu]) for uu in order)
            self.unit_of.append(gid[u])
        if all("t" in getattr(t.data, "context", {}) for t in terms):
            tmin = [terms[g.term].data.context["t"][g.poses].min() for g in groups]
            perm = sorted(range(len(groups)), key=lambda i: (tmin[i], i))
            remap = np.empty(len(groups), int)
            remap[perm] = np.arange(len(groups))
            groups = [groups[i] for i in perm]
            self.unit_of = [remap[a] for a in self.unit_of]
        self.groups = groups
        self.row_group = np.empty(len(term), int)
        for a in range(len(terms)):
            m = term == a
            self.row_group[m] = self.unit_of[a][pose[m]]
        used = np.unique(self.row_group)
        if used.size < len(groups):  # units without rows (a singleton link group): drop them
            remap = np.full(len(groups), -1)
            remap[used] = np.arange(used.size)
            self.groups = [groups[i] for i in used]
            self.unit_of = [remap[a] for a in self.unit_of]
            self.row_group = remap[self.row_group]

    def __len__(self) -> int:
        return len(self.groups)

    def rows_of(self, ids) -> np.ndarray:
        """Indices (into the full stacked rows) of the rows of groups ``ids``."""
        return np.flatnonzero(np.isin(self.row_group, np.asarray(ids)))

    def subproblem(self, ids):
        """An object with ``evaluate(theta, jacobian)`` returning exactly the rows of groups ``ids``."""
        ids = np.atleast_1d(np.asarray(ids, int))
        if not self.splittable:
            return _SelectRows(self.problem, self.rows_of(ids))
        return self._split(ids)[0]

    def _split(self, ids):
        terms, back = [], []
        for ti, t in enumerate(self.problem.terms):
            poses = [self.groups[i].poses for i in ids if self.groups[i].term == ti]
            if poses:
                poses = np.sort(np.concatenate(poses))
                terms.append(Term(t.method, t.data.subset(poses), t.noise))
                back.append(self.unit_of[ti][poses])
        sub = Problem.__new__(Problem)
        sub.robot = self.problem.robot
        sub.terms = terms
        return sub, back

    def subproblem_rows(self, ids):
        """``(sub, row_group)``: the sub-problem of groups ``ids`` and the group id of each of its rows."""
        ids = np.atleast_1d(np.asarray(ids, int))
        if not self.splittable:
            idx = self.rows_of(ids)
            return _SelectRows(self.problem, idx), self.row_group[idx]
        sub, back = self._split(ids)
        r = sub.evaluate(jacobian=False)
        tt = r.term if r.term is not None else np.zeros(len(r.e), int)
        return sub, np.array([back[a][b] for a, b in zip(tt.tolist(), r.pose.tolist())], int)


class _SelectRows:
    """Fallback sub-problem: evaluate everything, keep some rows (non-splittable problems)."""

    def __init__(self, problem, idx):
        self.problem, self.idx = problem, idx

    @property
    def params(self):
        return self.problem.params

    def evaluate(self, theta=None, jacobian=True):
        r = self.problem.evaluate(theta, jacobian)
        i = self.idx
        return Rows(r.e[i], None if r.H is None else r.H[i], r.sigma[i], r.pose[i], r.kind[i],
                    None if r.term is None else r.term[i])


def finish_result(problem, method, names, fidx, estimate, cov, theta_full, nominal, n_iterations=0,
                  converged=True, covariance_source="model", theta_before=None, validation=(), t0=None,
                  extra=None):
    """Build the shared :class:`CalibrationResult` (χ² and dof from the problem's rows at the estimate)."""
    import time



    chi2, m = chi2_and_rows(problem, theta_full)
    dof = int(m - len(fidx))
    cov = np.asarray(cov, float)
    res = CalibrationResult(method=method, names=list(names), estimate=np.asarray(estimate, float).copy(),
                            std=np.sqrt(np.clip(np.diag(cov), 0, None)), covariance=cov,
                            nominal=np.asarray(nominal, float).copy(), theta=np.asarray(theta_full, float).copy(),
                            all_names=list(problem.params.names), n_iterations=int(n_iterations),
                            converged=bool(converged), chi2=chi2, dof=dof, covariance_source=covariance_source,
                            problem=problem, validation_data=list(validation))
    if extra:
        res.extra.update(extra)
    if t0 is not None:
        res.extra["time_s"] = time.perf_counter() - t0
    try:
        res.accuracy = score(problem, problem.params.values if theta_before is None else theta_before,
                             theta_full, validation)
    except (AttributeError, IndexError, TypeError):  # Problem-like objects without datasets
        res.accuracy = {}
    return res


def evaluate_many(problem, thetas) -> np.ndarray:
    """Residuals (W, M) at every row of ``thetas``: ``problem.evaluate_many`` (batched
    kinematics) when the problem has it, else θ by θ (problem-like objects, e.g. Gough)."""
    TH = np.atleast_2d(np.asarray(thetas, float))
    if hasattr(problem, "evaluate_many"):
        return problem.evaluate_many(TH)
    return np.stack([problem.evaluate(th, jacobian=False).e for th in TH])
