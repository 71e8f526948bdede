"""Optimal measurement plans: discrete exchange, continuous multi-start, baselines.

A *plan* is an (m, n) array of joint readings. Its quality is a criterion of
the information matrix ``M = Σ J_iᵀ W J_i (+ Σ₀⁻¹)`` of a
:class:`~estcal.design.model.DesignModel` (see :mod:`estcal.design.criteria`).

* Discrete (choose m poses from K candidates, repetitions allowed):
  greedy addition, modified Fedorov exchange (Cook & Nachtsheim 1980: for each
  plan point in turn, the best exchange with any candidate) and DETMAX
  (Mitchell 1974: excursions that add k points then remove k), with restarts.
  Per-pose information blocks ``F_k = J_kᵀ W J_k`` are precomputed, so every
  move scores all K candidates with one batched eigen-decomposition.
* Continuous: the m·n joint values are optimised within the joint limits
  (L-BFGS-B, or SLSQP with user inequality constraints ``g(Q) ≥ 0``) from
  several starting plans; the gradient is a forward difference evaluated in one
  batched kinematics call. Starts are independent tasks of
  :func:`estcal.scale.run_tasks` (``scheduler=``: serial, local processes, a
  Dask cluster); the best plan does not depend on where they ran.
* Replication (Klimchik §5): an m-pose plan measured k times has information
  k·M, so ρ0² falls by k.
* Random-plan baseline: the criterion distribution over many random plans,
  computed in batches (no Python loop over poses or plans).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estcal.base.jsonio import to_jsonable
from estcal.base.progress import progress
from estcal.base.textinput import read_text
from estcal.scale.runner import TaskError, run_tasks

from .criteria import CRITERIA, criterion_loss, criterion_value, evaluate_all, larger_is_better, normalise_criterion
from .model import DesignModel
from .update import FAST_CRITERIA, added_criterion_value, whiten

__all__ = ["Plan", "BaselineStats", "random_candidates", "load_candidates", "greedy", "fedorov_exchange",
           "detmax", "optimise_discrete", "optimise_continuous", "replicate", "random_baseline",
           "evaluate_plan"]


# ------------------------------------------------------------------ results
@dataclass
class Plan:
    """An (m, n) plan of joint readings with its criterion value.

    ``value`` is the criterion (see :mod:`estcal.design.criteria`; for the
    test-pose criterion it is ρ0² in m²), ``method`` how it was found.
    """

    readings: np.ndarray
    criterion: str
    value: float
    method: str
    joint_names: list = field(default_factory=list)
    info: dict = field(default_factory=dict)

    @property
    def m(self) -> int:
        return int(self.readings.shape[0])

    def to_dict(self) -> dict:
        return {"criterion": self.criterion, "value": float(self.value), "method": self.method, "m": self.m,
                "joint_names": list(self.joint_names), "readings_rad": self.readings.tolist(),
                "readings_deg": np.degrees(self.readings).tolist(), "info": to_jsonable(self.info)}

    def __str__(self) -> str:
        head = f"{self.method} plan, m={self.m}, {self.criterion} = {self.value:.6g}"
        rows = ["  " + " ".join(f"{v:9.3f}" for v in np.degrees(r)) for r in self.readings]
        return head + "\n  joint readings (deg; prismatic in m·57.3):\n" + "\n".join(rows)


@dataclass
class BaselineStats:
    """Distribution of a criterion over random plans (``n_singular`` plans are singular)."""

    criterion: str
    m: int
    n_plans: int
    replicate: int
    min: float
    mean: float
    max: float
    percentiles: dict
    n_singular: int
    values: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {"criterion": self.criterion, "m": self.m, "n_plans": self.n_plans, "replicate": self.replicate,
                "min": self.min, "mean": self.mean, "max": self.max,
                "percentiles": {str(k): v for k, v in self.percentiles.items()}, "n_singular": self.n_singular}

    def __str__(self) -> str:
        pct = ", ".join(f"p{k}={v:.4g}" for k, v in self.percentiles.items())
        rep = f"×{self.replicate}" if self.replicate > 1 else ""
        return (f"random plans (m={self.m}{rep}, {self.n_plans} plans, {self.n_singular} singular): "
                f"{self.criterion} min {self.min:.4g}, mean {self.mean:.4g}, max {self.max:.4g}; {pct}")


# -------------------------------------------------------------- candidates
def random_candidates(model: DesignModel, n: int, rng=None, limits=None, constraint=None,
                      max_tries: int = 50) -> np.ndarray:
    """``n`` random readings uniform within ``limits`` that satisfy ``constraint(q) ≥ 0``.

    ``constraint`` maps (N, n) readings to (N,) or (N, c) values (all ≥ 0 = feasible).
    """
    rng = np.random.default_rng(rng)
    if constraint is None:
        return model.random_readings(n, rng, limits)
    out = []
    got = 0
    for _ in range(max_tries):
        Q = model.random_readings(max(2 * (n - got), 16), rng, limits)
        g = np.asarray(constraint(Q), float).reshape(len(Q), -1)
        Q = Q[np.all(g >= 0, axis=1)]
        out.append(Q)
        got += len(Q)
        if got >= n:
            break
    Q = np.concatenate(out)[:n]
    if len(Q) < n:
        raise RuntimeError(f"only {len(Q)} of {n} random candidates satisfy the constraint")
    return Q


def load_candidates(path, robot, degrees: bool = False) -> np.ndarray:
    """Candidate readings from a CSV file.

    One row per candidate; a header row naming the joints (in any order, matched
    to ``robot.joint_names``) is optional. Values are in rad / m unless
    ``degrees`` (revolute columns in degrees). Every message names the file and the
    line an editor shows (blank and ``#`` lines counted)."""
    from pathlib import Path

    from estcal.base.textinput import parse_csv_text

    path = Path(path)
    text = read_text(path, "candidates", ValueError)  # folder, binary, encoding: one clear message
    # '#' lines are comments here: blanked (not removed) so that line numbers stay physical
    text = "".join("\n" if ln.lstrip().startswith("#") else ln for ln in text.splitlines(keepends=True))
    if not text.strip():
        raise ValueError(f"{path}: no candidate rows")
    table = parse_csv_text(text, str(path), "candidates", ValueError)
    names = robot.joint_names
    first = [h.strip() for h in table.header]
    try:
        [float(v) for v in first]
        header, body, lines = None, [first] + table.rows, [table.header_line] + list(table.lines)
    except ValueError:
        header, body, lines = first, table.rows, list(table.lines)
    ncol = len(header) if header is not None else len(body[0])
    A = np.empty((len(body), ncol))
    for i, r in enumerate(body):
        if len(r) != ncol:
            raise ValueError(f"{path}, line {lines[i]}: {len(r)} fields, expected {ncol}")
        for j, v in enumerate(r):
            col = f", column {header[j]!r}" if header is not None else f", column {j + 1}"
            try:
                A[i, j] = float(v)
            except ValueError:
                raise ValueError(f"{path}, line {lines[i]}{col}: {v.strip()!r} is not a number") from None
            if not np.isfinite(A[i, j]):
                raise ValueError(f"{path}, line {lines[i]}{col}: value {v.strip()!r} is not a finite number — "
                                 f"a candidate pose needs every joint reading") from None
    if header is not None:
        missing = [n for n in names if n not in header]
        if missing:
            raise ValueError(f"{path}, line {table.header_line}: header {header} lacks joints {missing}")
        A = A[:, [header.index(n) for n in names]]
    if A.shape[1] != len(names):
        raise ValueError(f"{path}: expected {len(names)} columns ({names}), got {A.shape[1]}")
    if degrees:
        rev = np.array([t == "revolute" for t in robot.joint_types])
        A[:, rev] = np.radians(A[:, rev])
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    bad = np.argwhere((A < lo - 1e-9) | (A > hi + 1e-9))
    if len(bad):
        i, j = bad[0]
        raise ValueError(f"{path}, line {lines[i]}: joint {names[j]!r} = {A[i, j]:.6g} "
                         f"outside limits [{lo[j]:.6g}, {hi[j]:.6g}]")
    return A


# -------------------------------------------------------------- scoring
class _Scorer:
    """Loss of batches of information matrices for one criterion (picklable)."""

    def __init__(self, criterion, m, J_test=None, ridge=None):
        self.criterion = normalise_criterion(criterion)
        self.m = m
        self.J_test = J_test
        self.ridge = ridge

    def loss(self, M, regularise=False):
        if regularise and self.ridge is not None:
            M = M + self.ridge
        return criterion_loss(self.criterion, M, self.m, self.J_test)

    def loss_add(self, M, F, B):
        """Loss of ``M + ridge + F_k`` for every candidate k (``F_k = B_kᵀ B_k``).

        D, A, test-pose and G use the Woodbury update of ``C = (M + ridge)⁻¹``
        (:mod:`estcal.design.update`); the others a batched eigen-decomposition.
        """
        # O1 = det(M)^(1/2p)/√m ranks like D when all candidates give the same m
        fast = "D" if self.criterion == "O1" else self.criterion
        if fast in FAST_CRITERIA:
            Mr = M + self.ridge if self.ridge is not None else M
            try:
                L = np.linalg.cholesky(0.5 * (Mr + Mr.T))
            except np.linalg.LinAlgError:
                L = None
            if L is not None:
                Li = np.linalg.inv(L)
                C = Li.T @ Li
                logdet_C = -2.0 * np.sum(np.log(np.diag(L)))
                with np.errstate(divide="ignore", invalid="ignore"):
                    v = added_criterion_value(fast, C, B, self.J_test, logdet_C)
                    out = np.log(v)
                    if self.criterion == "O1":  # −log O1 = ½ log D + ½ log m
                        out = 0.5 * out + 0.5 * np.log(self.m)
                return np.where(np.isfinite(out), out, 1e6)
        return self.loss(M[None] + F, regularise=True)


def _ridge(F):
    """Tiny per-parameter ridge (1e-9 of the mean diagonal information): keeps partial
    plans invertible during greedy growth without changing full-rank rankings."""
    d = np.mean(np.einsum("kii->ki", F), axis=0)
    d = np.where(d > 0, d, max(d.max(), 1e-300))
    return np.diag(1e-9 * d)


def _needs_test(criterion):
    return CRITERIA[normalise_criterion(criterion)][1]


def _check_test(model, criterion, J_test, q_test):
    if J_test is None and q_test is not None:
        J_test = model.position_jacobian(np.atleast_2d(q_test))
    if _needs_test(criterion) and J_test is None:
        raise ValueError(f"criterion {criterion!r} needs test poses (q_test) or J_test")
    return J_test


def evaluate_plan(model: DesignModel, readings, q_test=None, J_test=None):
    """All criteria (:class:`~estcal.design.criteria.PlanCriteria`) of a plan, with parameter stds."""
    Q = np.atleast_2d(np.asarray(readings, float))
    J_test = _check_test(model, "A", J_test, q_test)
    return evaluate_all(model.information(Q), len(Q), J_test, model.free)


# ---------------------------------------------------------------- discrete
def _prior(model):
    P = model.prior_information
    return np.zeros((model.p, model.p)) if P is None else P


def greedy(model: DesignModel, candidates, m: int, criterion: str = "D", q_test=None, J_test=None,
           start=None, allow_repeats: bool = True) -> Plan:
    """Greedy addition: repeatedly add the candidate that most improves the criterion.

    While the plan is still rank deficient the loss is evaluated with a tiny ridge
    (1e-9 of the mean information per parameter), which rewards poses that add
    new directions. ``start`` (indices) seeds the plan.
    """
    J_test = _check_test(model, criterion, J_test, q_test)
    cand = np.asarray(candidates, float)
    F, B = _blocks(model, cand)
    idx = _greedy_idx(F, B, _prior(model), m, _Scorer(criterion, m, J_test, _ridge(F)), start, allow_repeats)
    Q = cand[idx]
    return Plan(Q, normalise_criterion(criterion),
                float(criterion_value(criterion, model.information(Q), m, J_test)), "greedy",
                model.robot.joint_names, {"candidate_indices": idx})


def _blocks(model, cand):
    """Whitened candidate Jacobians B (K, r, p) and information blocks F = BᵀB (K, p, p)."""
    B = whiten(model.jacobian(cand), model.row_sigma)
    return np.einsum("krp,krq->kpq", B, B), B


def _greedy_idx(F, B, M0, m, scorer, start=None, allow_repeats=True):
    idx = list(start or [])
    M = M0 + F[idx].sum(0) if idx else M0.copy()
    while len(idx) < m:
        scorer.m = len(idx) + 1
        loss = scorer.loss_add(M, F, B)
        if not allow_repeats and idx:
            loss[idx] = np.inf
        k = int(np.argmin(loss))
        idx.append(k)
        M = M + F[k]
    scorer.m = m
    return idx


def _fedorov_idx(F, B, M0, idx, scorer, max_iter=100, rtol=1e-10):
    """Modified Fedorov exchange on index list ``idx``; returns (idx, loss, n_swaps).

    Losses carry the tiny ridge of :func:`_ridge` so that rank-deficient
    intermediate plans still rank; the reported plan value is exact."""
    idx = list(idx)
    M = M0 + F[idx].sum(0)
    cur = float(scorer.loss(M, regularise=True))
    swaps = 0
    for _ in range(max_iter):
        improved = False
        for i in range(len(idx)):
            Mi = M - F[idx[i]]
            loss = scorer.loss_add(Mi, F, B)
            k = int(np.argmin(loss))
            if loss[k] < cur - rtol * max(1.0, abs(cur)):
                M = Mi + F[k]
                idx[i] = k
                cur = float(loss[k])
                improved = True
                swaps += 1
        if not improved:
            break
    return idx, cur, swaps


def _detmax_idx(F, B, M0, idx, scorer, max_excursion=4, max_iter=200, rtol=1e-10):
    """DETMAX excursions: add k best points one by one, then remove k least useful."""
    idx = list(idx)
    m = len(idx)
    M = M0 + F[idx].sum(0)
    cur = float(scorer.loss(M, regularise=True))
    for _ in range(max_iter):
        accepted = False
        for k_exc in range(1, max_excursion + 1):
            tid, TM = list(idx), M.copy()
            for _a in range(k_exc):
                scorer.m = len(tid) + 1
                j = int(np.argmin(scorer.loss_add(TM, F, B)))
                tid.append(j)
                TM = TM + F[j]
            for _r in range(k_exc):
                scorer.m = len(tid) - 1
                Mrem = TM[None] - F[tid]
                j = int(np.argmin(scorer.loss(Mrem, regularise=True)))
                TM = Mrem[j]
                tid.pop(j)
            scorer.m = m
            new = float(scorer.loss(TM, regularise=True))
            if new < cur - rtol * max(1.0, abs(cur)):
                idx, M, cur = tid, TM, new
                accepted = True
                break
        if not accepted:
            break
    return idx, cur


def fedorov_exchange(model: DesignModel, candidates, m: int, criterion: str = "D", q_test=None,
                     J_test=None, start=None, rng=None, max_iter: int = 100) -> Plan:
    """Modified Fedorov exchange from ``start`` indices (default: greedy plan)."""
    def run(F, B, M0, start, sc):
        idx, _, swaps = _fedorov_idx(F, B, M0, start, sc, max_iter)
        return idx, {"swaps": swaps}

    return _exchange(model, candidates, m, criterion, q_test, J_test, start, "fedorov", run)


def detmax(model: DesignModel, candidates, m: int, criterion: str = "D", q_test=None, J_test=None,
           start=None, max_excursion: int = 4) -> Plan:
    """Mitchell's DETMAX (generalised to any criterion) from ``start`` (default greedy)."""
    def run(F, B, M0, start, sc):
        return _detmax_idx(F, B, M0, start, sc, max_excursion)[0], {}

    return _exchange(model, candidates, m, criterion, q_test, J_test, start, "detmax", run)


def _exchange(model, candidates, m, criterion, q_test, J_test, start, name, run) -> Plan:
    """Shared frame of the exchange algorithms: blocks, scorer, greedy start, the plan.

    ``run(F, B, M0, start, scorer) -> (indices, extra details)`` is the algorithm itself.
    """
    J_test = _check_test(model, criterion, J_test, q_test)
    cand = np.asarray(candidates, float)
    F, B = _blocks(model, cand)
    M0 = _prior(model)
    sc = _Scorer(criterion, m, J_test, _ridge(F))
    if start is None:
        start = _greedy_idx(F, B, M0, m, sc)
    idx, extra = run(F, B, M0, start, sc)
    Q = cand[idx]
    return Plan(Q, sc.criterion, float(criterion_value(criterion, model.information(Q), m, J_test)), name,
                model.robot.joint_names, {"candidate_indices": idx, **extra})


def optimise_discrete(model: DesignModel, m: int, criterion: str = "D", candidates=None,
                      n_candidates: int = 2000, algorithm: str = "fedorov", restarts: int = 5, rng=None,
                      q_test=None, J_test=None, constraint=None) -> Plan:
    """Best plan over ``restarts`` (one greedy start + random starts) of an exchange algorithm.

    Parameters
    ----------
    algorithm : 'greedy', 'fedorov' or 'detmax'
    candidates : (K, n) readings; default ``n_candidates`` random ones within limits.
    """
    rng = np.random.default_rng(rng)
    J_test = _check_test(model, criterion, J_test, q_test)
    cand = random_candidates(model, n_candidates, rng, constraint=constraint) if candidates is None \
        else np.asarray(candidates, float)
    F, B = _blocks(model, cand)
    M0 = _prior(model)
    sc = _Scorer(criterion, m, J_test, _ridge(F))
    best_idx, best = None, np.inf
    history = []

    n_runs = 1 if algorithm == "greedy" else max(1, restarts)
    with progress(total=n_runs, desc=f"design ({algorithm}, m={m})", unit="restart") as bar:
        for r in range(max(1, restarts)):
            start = _greedy_idx(F, B, M0, m, sc) if r == 0 else list(rng.integers(0, len(cand), m))
            if algorithm == "greedy":
                if r > 0:
                    break
                idx, loss = start, float(sc.loss(M0 + F[start].sum(0), regularise=True))
            elif algorithm == "fedorov":
                idx, loss, _ = _fedorov_idx(F, B, M0, start, sc)
            elif algorithm == "detmax":
                idx, loss = _detmax_idx(F, B, M0, start, sc)
            else:
                raise ValueError(f"unknown algorithm {algorithm!r}; choose greedy, fedorov or detmax")
            history.append(loss)
            if loss < best:
                best, best_idx = loss, idx
            bar.update(1)
    Q = cand[best_idx]
    return Plan(Q, sc.criterion, float(criterion_value(criterion, model.information(Q), m, J_test)), algorithm,
                model.robot.joint_names, {"candidate_indices": best_idx, "restart_losses": history,
                                          "n_candidates": len(cand)})


# -------------------------------------------------------------- continuous
def _objective_and_grad(x, model, m, scorer, lo, hi, h=1e-6):
    """Loss and forward-difference gradient in one batched evaluation of m·n+1 plans."""
    n = model.n_joints
    k = x.size
    step = h * np.maximum(1.0, np.abs(x))
    # step backwards at the upper bound so every evaluated plan respects the limits
    sgn = np.where(x + step > hi, -1.0, 1.0)
    X = np.repeat(x[None], k + 1, 0)
    X[np.arange(1, k + 1), np.arange(k)] += sgn * step
    L = scorer.loss(model.information(X.reshape(k + 1, m, n)))
    f = float(L[0])
    g = (L[1:] - f) / (sgn * step)
    return f, g


def _local_continuous(args):
    """One multi-start run (module level so that process pools can pickle it)."""
    from scipy.optimize import minimize

    model, x0, m, criterion, J_test, constraint, maxiter = args
    sc = _Scorer(criterion, m, J_test)
    n = model.n_joints
    lo = np.tile(model.robot.limits[:, 0], m)
    hi = np.tile(model.robot.limits[:, 1], m)
    fun = lambda x: _objective_and_grad(x, model, m, sc, lo, hi)  # noqa: E731
    bounds = list(zip(lo, hi))
    if constraint is None:
        res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": maxiter})
    else:
        cons = {"type": "ineq", "fun": lambda x: np.asarray(constraint(x.reshape(m, n)), float).ravel()}
        res = minimize(fun, x0, jac=True, method="SLSQP", bounds=bounds, constraints=[cons],
                       options={"maxiter": maxiter})
    x = np.clip(res.x, lo, hi)
    feasible = True
    if constraint is not None:
        feasible = bool(np.all(np.asarray(constraint(x.reshape(m, n)), float) >= -1e-8))
    return x.reshape(m, n), float(sc.loss(model.information(x.reshape(m, n)))), int(res.nit), feasible


def optimise_continuous(model: DesignModel, m: int, criterion: str = "D", n_starts: int = 8, rng=None,
                        q_test=None, J_test=None, constraint=None, scheduler=None,
                        n_workers: int | None = None, starts=None, maxiter: int = 300,
                        prescreen: int = 0, executor=None) -> Plan:
    """Multi-start local optimisation of the m·n joint values within the joint limits.

    Parameters
    ----------
    constraint : callable, optional
        Per-pose feasibility, vectorised: ``constraint(Q (N, n)) -> (N,) or (N, c)``;
        a pose is feasible when all its entries are ≥ 0 (collision / workspace
        limits). Must be picklable for process pools (a module-level function).
    scheduler, n_workers
        Where the starts run (:func:`estcal.scale.run_tasks`: ``'serial'``,
        ``'processes'``, ``'local'``, a Dask address, a Dask ``Client`` or a
        ``concurrent.futures`` executor). ``None``: ``'processes'`` when there is
        more than one start, else ``'serial'``. A start that raises is reported
        in ``info["failed_starts"]``; the plan is the best of the others.
    executor : former name of ``scheduler`` (still accepted).
    starts : (S, m, n) initial plans (e.g. the best discrete plan); random ones fill up to ``n_starts``.
    prescreen : int
        If > 0, draw ``prescreen`` random feasible plans and start from the best
        ``n_starts`` of them (Klimchik: the problem is very sensitive to the start).
    """
    rng = np.random.default_rng(rng)
    J_test = _check_test(model, criterion, J_test, q_test)
    crit = normalise_criterion(criterion)
    S = [] if starts is None else [np.asarray(s, float).reshape(m, model.n_joints) for s in starts]
    need = max(0, n_starts - len(S))
    if need:
        pool_n = max(need, prescreen)
        Qs = random_candidates(model, pool_n * m, rng, constraint=constraint).reshape(pool_n, m, -1)
        if prescreen:
            L = criterion_loss(crit, model.information(Qs), m, J_test)
            Qs = Qs[np.argsort(L)]
        S += list(Qs[:need])
    tasks = [(model, s.ravel(), m, crit, J_test, constraint, maxiter) for s in S]

    if scheduler is None:
        scheduler = executor
    if scheduler is None:
        scheduler = "serial" if len(tasks) == 1 else "processes"
    run = run_tasks(_local_continuous, tasks, scheduler=scheduler, n_workers=n_workers, chunksize=1,
                    progress="auto", desc=f"design (continuous, m={m}): starts")
    results = [r for r in run.results if r is not None]
    if not results:
        raise TaskError(run.failures)
    feas = [r for r in results if r[3]] or results
    best = min(feas, key=lambda r: r[1])
    Q = best[0]
    return Plan(Q, crit, float(criterion_value(crit, model.information(Q), m, J_test)), "continuous",
                model.robot.joint_names,
                {"start_losses": [r[1] for r in results], "iterations": [r[2] for r in results],
                 "feasible": bool(best[3]), "n_starts": len(tasks),
                 "failed_starts": [str(f) for f in run.failures]})


# ------------------------------------------------------ replication, random
def replicate(plan: Plan, k: int, model: DesignModel | None = None, q_test=None, J_test=None) -> Plan:
    """The plan measured ``k`` times (Klimchik's 3×4 / 4×3): information k·M."""
    Q = np.tile(plan.readings, (k, 1))
    val = np.nan
    if model is not None:
        J_test = _check_test(model, plan.criterion, J_test, q_test)
        val = float(criterion_value(plan.criterion, model.information(Q), len(Q), J_test))
    return Plan(Q, plan.criterion, val, f"{plan.method}×{k}", plan.joint_names,
                {"base_plan_m": plan.m, "replications": k})


def _percentile(v, p) -> float:
    """``numpy.percentile(v, p)`` (linear interpolation) where a singular plan's criterion is infinite: two
    infinite neighbours give the infinity, not ``inf − inf`` (NaN and a RuntimeWarning)."""
    s = np.sort(np.asarray(v, float))
    k = (len(s) - 1) * float(p) / 100.0
    lo, hi = int(np.floor(k)), int(np.ceil(k))
    if s[lo] == s[hi]:
        return float(s[lo])
    return float(s[lo] + (s[hi] - s[lo]) * (k - lo))


def random_baseline(model: DesignModel, m: int, criterion: str = "D", n_plans: int = 1000, rng=None,
                    q_test=None, J_test=None, replicate: int = 1, chunk: int | None = None,
                    percentiles=(1, 5, 25, 50, 75, 95, 99), keep_values: bool = False,
                    constraint=None) -> BaselineStats:
    """Distribution of the criterion over ``n_plans`` random m-pose plans (vectorised).

    Plans are drawn uniformly within the joint limits (optionally filtered by
    ``constraint``) and, with ``replicate = k``, measured k times each. The
    information matrices of a chunk of plans come from one kinematics call and
    one ``einsum``; the criteria from one batched eigen-decomposition.
    """
    rng = np.random.default_rng(rng)
    J_test = _check_test(model, criterion, J_test, q_test)
    crit = normalise_criterion(criterion)
    chunk = chunk or max(1, 20000 // max(m, 1))
    vals = []
    done = 0
    while done < n_plans:
        b = min(chunk, n_plans - done)
        Q = random_candidates(model, b * m, rng, constraint=constraint).reshape(b, m, -1)
        M = model.information(Q, include_prior=False) * replicate
        if model.prior_cov is not None:
            M = M + model.prior_information
        vals.append(np.asarray(criterion_value(crit, M, m * replicate, J_test), float))
        done += b
    v = np.concatenate(vals)
    bad = ~np.isfinite(v) | ((v <= 0) if larger_is_better(crit) else np.zeros(v.shape, bool))
    vf = v[np.isfinite(v)]
    pct = {int(p) if float(p).is_integer() else p: _percentile(v, p) for p in percentiles}
    return BaselineStats(crit, m, int(n_plans), int(replicate), float(np.min(v)),
                         float(np.mean(vf)) if vf.size else math.inf, float(np.max(v)), pct, int(bad.sum()),
                         v if keep_values else None)
