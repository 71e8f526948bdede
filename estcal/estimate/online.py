"""The online (recursive) filter's numerics over rows of measured data, below the workflow that drives it.

:class:`estcal.workflows.online.OnlineCalibrator` loads, checks, checkpoints and prints; the
arithmetic of feeding rows to the random-walk parameter filter (:mod:`estcal.estimate.kalman`,
textbook §4.5, eqs 4.104–4.112) lives here, as functions of the filter and the rows:

* :func:`row_problems` — the measurement model of rows ``i … j−1`` of a chunk (one
  :class:`~estcal.methods.problem.Term` on a subset of the Dataset, no copy when it is the whole chunk);
* :func:`filter_rows` — steps ``a … b−1``: row by row through filterpy (the classical EKF, the UKF), or
  linearised in segments and applied as exact sequential block updates
  (:func:`estcal.estimate.kalman.run_steps`; docs/probabilistic.md, "Online at sensor rate");
* :func:`record_steps` — the burn-in row (the first row after which 2 p measured components have
  been seen) and the status history entries every ``history_every`` rows, with the running NIS
  per row as it stood after each;
* :func:`block_boundary` — the rows after which the blocks are cut whatever the chunks are (where a
  stream may be cut and reproduced bit for bit, e.g. at a checkpoint).

:class:`OnlineUpdate` is what one update did; :class:`OnlineResult` the state as a result
(the result protocol, :class:`estcal.base.result.Result`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.errors import InputError
from estcal.base.result import Result
from estcal.base.tables import Table, parameter_table, si_unit
from estcal.estimate.innovation import InnovationTests
from estcal.estimate.kalman import BLOCK_GROUPS, BlockStep, concat_steps, run_steps, segment_of
from estcal.methods.problem import Problem, Term

__all__ = ["OnlineUpdate", "OnlineResult", "row_problems", "filter_rows", "rowwise_steps", "record_steps",
           "block_boundary"]


def row_problems(robot, method, noise, ds, n0: int):
    """``sub(i, j)``: the :class:`~estcal.methods.problem.Problem` of stream rows ``i … j−1`` of the
    chunk ``ds`` whose first row is stream row ``n0`` (0-based)."""

    def sub(i, j):
        s = Problem.__new__(Problem)
        s.robot = robot
        s.terms = [Term(method, ds.subset(slice(i - n0, j - n0)) if (i - n0, j - n0) != (0, ds.n) else ds, noise)]
        return s

    return sub


def filter_rows(flt, sub, a: int, b: int, relinearize="auto", lin=None, rowwise: int = 32):
    """Steps ``a … b−1`` of the filter ``flt`` on the rows ``sub(i, j)`` (:func:`row_problems`).

    ``relinearize == 1``: row by row (:func:`rowwise_steps`); otherwise segments of rows linearised at
    one estimate (``"auto"`` or G rows), applied in exact blocks (:func:`estcal.estimate.kalman.run_steps`;
    ``lin``: its linearisation state after the previous steps, ``rowwise``: the rows stepped one by one
    first). Returns ``(BlockStep, lin)``."""
    if relinearize == 1:
        return rowwise_steps(flt, sub, a, b), lin
    fidx = flt.fidx

    def evaluate(i, j, theta):
        r = sub(i, j).evaluate(theta)
        if np.any(np.diff(r.pose) < 0):  # rows stacked step by step
            o = np.argsort(r.pose, kind="stable")
            r.e, r.H, r.sigma, r.pose = r.e[o], r.H[o], r.sigma[o], r.pose[o]
        return r.H[:, fidx], r.e, r.sigma, np.bincount(r.pose, minlength=j - i)

    blocks, lin = run_steps(flt, a, b, evaluate, relinearize, lin, rowwise=rowwise)
    return concat_steps(blocks), lin


def rowwise_steps(flt, sub, a: int, b: int) -> BlockStep:
    """Steps a … b−1 one at a time through filterpy (the classical EKF, or the UKF)."""
    B, p = b - a, len(flt.names)
    nis, dims = np.empty(B), np.empty(B, np.int64)
    X, V, T = np.empty((B, p)), np.empty((B, p)), np.empty(B)
    for k in range(B):
        step = flt.step(sub(a + k, a + k + 1))
        nis[k], dims[k] = step.nis, step.y.size
        X[k], V[k], T[k] = flt.f.x, np.diag(flt.f.P), np.trace(flt.f.P)
    return BlockStep(nis, dims, X, V, T)


def record_steps(flt, st: BlockStep, lines, n0: int, burn, history_every: int, trace: bool = False):
    """Burn-in, status history entries and the update's summary from the steps ``st`` just made on
    stream rows ``n0 …`` (file ``lines`` of the chunk's rows). ``burn``: the burn-in row so far (None
    until 2 p measured components were seen). Returns ``(burn, OnlineUpdate)``; the update's
    ``history`` holds the new entries (every ``history_every``-th row)."""
    k = n0 + np.arange(1, st.nis.size + 1)  # 1-based row numbers
    if burn is None:
        rows_before = flt.n_rows - int(st.dims.sum())
        hit = np.flatnonzero(rows_before + np.cumsum(st.dims) >= 2 * len(flt.names))
        if hit.size:
            burn = int(k[hit[0]])
    new = []
    sel = np.flatnonzero(k % history_every == 0)
    if sel.size:
        kk = k[sel]
        # the running NIS as it stood after row k: from the burn-in on, undefined (NaN) before it
        b = kk if burn is None else np.where(kk >= burn, burn, kk)
        run = flt.monitor.running_at(kk, b)
        sd = st.std
        for j, i in enumerate(sel):
            new.append({"row": int(kk[j]), "line": int(lines[i]), "nis": float(st.nis[i]),
                        "nis_per_row": float(run[j]), "trace_P": float(st.trace[i]),
                        "estimate": st.estimate[i].tolist(), "std": sd[i].tolist()})
    return burn, OnlineUpdate((n0 + 1, n0 + st.nis.size), st.nis, st.dims, new,
                              st.estimate if trace else None, st.std if trace else None)


def block_boundary(n: int, relinearize="auto", rowwise: int = 32) -> bool:
    """True when the filter cuts its blocks after row n whatever the updates are: a stream cut
    there into updates gives the same floating-point operations as one not cut."""
    if relinearize == 1:
        return True
    return n % BLOCK_GROUPS == 0 or segment_of(n, relinearize, rowwise)[0] == n


@dataclass
class OnlineUpdate:
    """What one :meth:`estcal.workflows.online.OnlineCalibrator.update` did.

    ``rows`` (first, last) 1-based row numbers of the stream; ``nis`` and ``dims`` per row;
    ``history``: the status entries recorded (every ``history_every`` rows); with ``trace=True``
    the estimate and std after every row (SI, (N, p))."""

    rows: tuple
    nis: np.ndarray
    dims: np.ndarray
    history: list
    estimate: np.ndarray | None = None
    std: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.nis.size)


@dataclass(repr=False)
class OnlineResult(Result):
    """The state of an online calibration (SI units), following the result protocol
    (:class:`estcal.base.result.Result`): ``to_dict()`` is the JSON of ``estcal online --json``,
    ``table()`` the parameter table (display units), ``save_model`` the robot at the estimate."""

    robot: str
    input: str | None
    filter: str
    q: object
    q_params: str | None
    names: list
    estimate: np.ndarray
    std: np.ndarray
    nominal: np.ndarray
    covariance: np.ndarray
    n_rows: int
    innovation: dict
    history: list = field(default_factory=list)
    relinearize: object = "auto"
    robot_model: object = field(default=None, repr=False, compare=False)
    noise: object = field(default=None, repr=False, compare=False)

    def parameter(self, name: str) -> tuple[float, float]:
        """``(estimate, std)`` of a free parameter (SI units)."""
        i = self.names.index(name)
        return float(self.estimate[i]), float(self.std[i])

    def to_dict(self) -> dict:
        return {"robot": self.robot, "input": self.input, "filter": self.filter, "q": self.q,
                "q_params": self.q_params, "relinearize": self.relinearize, "n_rows": int(self.n_rows),
                "parameters": {n: {"estimate": float(e), "std": float(s), "nominal": float(v)}
                               for n, e, s, v in zip(self.names, self.estimate, self.std, self.nominal)},
                "covariance": np.asarray(self.covariance).tolist(), "innovation": self.innovation,
                "history": self.history}

    @property
    def inputs(self) -> tuple:
        """The file the rows came from (never written over by :meth:`to_json`)."""
        return (self.input,) if self.input and self.input != "<stdin>" else ()

    def table(self) -> Table:
        """Nominal, estimate and std of every free parameter in display units (mm, mrad; SI when the
        robot is not known), the innovation tests' verdict as its note (:func:`estcal.base.tables.parameter_table`)."""
        from estcal.base.units import display_unit

        rb = self.robot_model
        t = parameter_table(self, (lambda n: display_unit(n, rb)) if rb is not None else si_unit,
                            title=f"estimate after {self.n_rows} rows")
        inn = self.innovation
        t.note = str(InnovationTests(**inn)) if "error" not in inn else f"innovation tests: {inn['error']}"
        t.fmt = lambda i, j, v, digits: f"{v:.3g}" if j == 3 else f"{v:.{digits}g}"  # σ to 3 digits
        return t

    def summary(self) -> str:
        return f"OnlineResult({self.robot!r}, {self.n_rows} rows, filter {self.filter})"

    def save_model(self, path, provenance: dict | None = None) -> Path:
        """The robot at the estimate as a saved model (docs/robot-file.md, "Saved models"), the
        filter's covariance of the free parameters in its ``calibration:`` block."""
        from estcal.io.savedmodel import calibration_block, write_saved_model

        if self.robot_model is None:
            raise InputError("this OnlineResult does not know its robot (rebuilt from JSON)")
        pv = self.robot_model.params
        th = pv.values.copy()
        th[pv.indices(self.names)] = self.estimate
        block = calibration_block(estimator=f"online ({self.filter})", train=[], free=self.names,
                                  covariance=self.covariance, noise=self.noise, n_rows=int(self.n_rows),
                                  innovation=self.innovation, **(provenance or {}))
        return write_saved_model(self.robot_model.with_values(th), block, path)
