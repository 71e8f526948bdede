"""Online (recursive) calibration as a Python object: :class:`OnlineCalibrator`.

The object behind ``estcal online``, for scripts that calibrate a robot while it works::

    import estcal
    cal = estcal.OnlineCalibrator("puma560", free=["offset_*", "a_2"], noise=(1e-4, 1e-3))
    cal.update("first_rows.csv")            # a CSV path, a Dataset, or arrays: any number of rows
    cal.update(q, xyz)                      # joint readings (N, n) and measured points (N, 3)
    cal.save("state.json")                  # crash-safe checkpoint (state + journal, locked)
    print(cal.result().table())             # estimate ± σ, SI units; result().to_dict(): online --json
    cal = estcal.OnlineCalibrator.resume("state.json")   # after a crash: bit-identical continuation

The filter is the random-walk EKF (or UKF) of :mod:`estcal.estimate.kalman` (textbook §4.5,
eqs 4.104–4.112) over the free parameters; every row is one filter step and gets its own
innovation test record (NIS, whitened innovation: :mod:`estcal.estimate.innovation`).

**Speed.** Rows are linearised in segments (:func:`estcal.estimate.kalman.segment_of`): one
step at a time while the estimate moves by many σ, then up to 256 rows at one linearisation
point, evaluated with one vectorised kinematics call and applied as exact sequential updates in
blocks (:func:`estcal.estimate.kalman.block_update`): the per-row innovations, NIS, estimates
and σ are those of the row-by-row filter with that linearisation point. ``relinearize=1`` is
the classical EKF (every row at the current estimate, filterpy's update). The difference
between the two is second order in the move of the estimate within a segment
(docs/probabilistic.md, "Online at sensor rate").

**Checkpoints** (:mod:`estcal.estimate.checkpoint`): the state (x, P, Q, counters, options,
linearisation point) is one JSON file written atomically, the growing record (innovations,
history) is appended to its journal; the file is locked against a second writer.
"""
from __future__ import annotations

import csv
import itertools
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.blas import single_thread_blas
from estcal.base.errors import InputError
from estcal.base.result import Result
from estcal.base.tables import Table, parameter_table, si_unit
from estcal.estimate._common import prior_std_vector
from estcal.methods.reduced import PER_POSE_METHODS
from estcal.estimate.checkpoint import (CheckpointError, Journal, PrefixHasher, file_sha256, filter_checkpoint,
                                        load_checkpoint, option_differences, restore_filter, save_checkpoint)
from estcal.estimate.innovation import InnovationTests
from estcal.estimate.kalman import (BLOCK_GROUPS, BlockStep, ParameterFilter, concat_steps, default_burn_in,
                                    process_noise, run_steps, segment_of)
from estcal.io.columnmap import ColumnMap, column_map_from_dict, load_column_map
from estcal.io.dataset import Dataset, DatasetError
from estcal.methods.base import NoiseModel, get_method, method_for_dataset
from estcal.methods.problem import Problem, Term

__all__ = ["OnlineCalibrator", "OnlineUpdate", "OnlineResult", "CsvStream", "Chunk", "check_file", "file_free_set",
           "run_options"]

#: rows fed to the filter at a time when a whole file or a large Dataset is given to update()
FEED_ROWS = 4096


def _noise_model(noise) -> NoiseModel:
    """The (known, absolute) measurement noise of the filter: a NoiseModel, a pair
    ``(position m, orientation rad)`` or ``{"position": m, "orientation": rad}``; default 0.1 mm, 1 mrad."""
    if noise is None:
        return NoiseModel(1e-4, 1e-3, known=True)
    if isinstance(noise, NoiseModel):
        return NoiseModel(noise.position, noise.orientation, noise.scalar, known=True)
    if isinstance(noise, dict):
        return NoiseModel(float(noise["position"]), float(noise.get("orientation", 1e-3)), known=True)
    p, r = noise
    return NoiseModel(float(p), float(r), known=True)


def _column_map(column_map) -> ColumnMap | None:
    """The column map of the input (``--map``, docs/dataset.md): a path of its YAML file, a
    :class:`~estcal.io.columnmap.ColumnMap`, or the dict a checkpoint keeps (``ColumnMap.to_dict``)."""
    if column_map is None or isinstance(column_map, ColumnMap):
        return column_map
    if isinstance(column_map, dict):
        return column_map_from_dict(column_map, "<the checkpoint's column map>")
    return load_column_map(column_map)


def _names(free) -> list[str] | None:
    if free is None:
        return None
    if isinstance(free, str):
        free = free.split(",")
    return [s.strip() for s in free if s.strip()]


def run_options(robot, root=None, tip=None, free=None, q=0.0, filter="ekf", measure=None, noise=None,
                prior_std=0.1, relinearize="auto", column_map=None) -> dict:
    """The options that change the estimates, as a checkpoint stores them (SI): a resumed run must
    use the same. ``q`` as a ``{pattern: std}`` with one std is kept as the command line's
    ``q`` + ``--q-params``; a column map by its content (``"--map"``, present only when given, so
    checkpoints of runs without one keep resuming)."""
    nz = _noise_model(noise)
    q_params = None
    if isinstance(q, dict):
        vals = {float(v) for v in q.values()}
        if len(vals) == 1:
            q_params, q = ",".join(q), vals.pop()
        else:
            q = {k: float(v) for k, v in q.items()}
    elif np.ndim(q):
        q = np.asarray(q, float).tolist()
    else:
        q = float(q)
    names = _names(free)
    ps = prior_std
    ps = {k: float(v) for k, v in ps.items()} if isinstance(ps, dict) else (
        np.asarray(ps, float).tolist() if np.ndim(ps) else float(ps))
    spec = str(robot) if isinstance(robot, (str, Path)) else getattr(robot, "name", None)
    out = {"--robot": spec, "--root": root, "--tip": tip, "--free": ",".join(names) if names else None,
           "q (SI)": q, "--q-params": q_params, "--filter": filter, "--method": measure,
           "noise-pos (m)": nz.position, "noise-rot (rad)": nz.orientation, "prior-std (SI)": ps,
           "relinearize": relinearize}
    cmap = _column_map(column_map)
    if cmap is not None:
        out["--map"] = cmap.to_dict()
    return out


@dataclass
class OnlineUpdate:
    """What one :meth:`OnlineCalibrator.update` did.

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


class OnlineCalibrator:
    """Recursive calibration of a robot from rows that arrive over time.

    Parameters
    ----------
    robot : a robot object, a built-in name, a robot file or a URDF (with ``root``/``tip``).
    free : names or patterns of the parameters to estimate (list or comma-separated string);
        default: the robot's free mask (``file_free_set`` gives the identifiable set of a file).
    measure : measurement kind (``position``, ``pose``, ``points`` …); default: from each row's columns.
    noise : measurement noise std, ``(position m, orientation rad)``, a dict or a NoiseModel
        (default 0.1 mm, 1 mrad), trusted as absolute (the filter's R).
    q : process-noise std per row (SI): a number, ``{name or pattern: std}`` or an array;
        0 = constant parameters, > 0 = random walk (drift).
    prior_std : prior std of the free parameters (SI; a number, array or ``{pattern: std}``), around
        the robot's values.
    filter : ``"ekf"`` or ``"ukf"`` (filterpy); the UKF always steps row by row.
    relinearize : ``"auto"`` (segments, see the module docstring) or G rows per linearisation
        (1 = the classical row-by-row EKF).
    history_every : a status entry (row, NIS, running NIS per row, trace P, estimate, std) every N rows.
    column_map : the column map of the files given to :meth:`update` (a YAML path or a
        :class:`~estcal.io.columnmap.ColumnMap`; ``estcal online --map``, docs/dataset.md): files read as
        published. Datasets and arrays are taken as they are.
    """

    def __init__(self, robot, *, free=None, measure=None, noise=None, q=0.0, prior_std=0.1, filter: str = "ekf",
                 relinearize="auto", history_every: int = 10, root=None, tip=None, column_map=None):
        from estcal.io.robotfile import load_robot

        if relinearize != "auto" and not (isinstance(relinearize, (int, np.integer)) and relinearize >= 1):
            raise InputError(f"relinearize must be 'auto' or an integer ≥ 1 (rows per linearisation), "
                             f"got {relinearize!r}")
        if int(history_every) < 1:
            raise InputError(f"history_every must be an integer ≥ 1, got {history_every!r}")
        self.column_map = _column_map(column_map)
        self.options = run_options(robot, root, tip, free, q, filter, measure, noise, prior_std, relinearize,
                                   self.column_map)
        rb = load_robot(robot, root=root, tip=tip)
        names = _names(free)
        if names is not None:
            rb = rb.copy(rb.params.with_free(names))
        self.robot = rb
        self.method = get_method(measure) if measure else None
        if self.method is not None and self.method.name not in PER_POSE_METHODS:
            raise InputError(f"method {self.method.name!r} compares several rows (groups/pairs); online calibration "
                             f"streams rows and supports {', '.join(PER_POSE_METHODS)} — use `estcal calibrate "
                             f"--estimator kalman`")
        self.noise = _noise_model(noise)
        pv = rb.params
        self.names, self.fidx = pv.free_names, pv.free_indices
        if not self.names:
            raise InputError("no free parameter to estimate (give free=… or set the robot's free mask)")
        Q = process_noise(self.names, q)
        P0 = np.diag(prior_std_vector(None, self.names, prior_std) ** 2)
        self.flt = ParameterFilter(pv.values, self.fidx, P0, Q, kind=filter, names=self.names)
        self.relinearize = 1 if filter == "ukf" else relinearize
        self.history_every = int(history_every)
        self.history: list = []
        self.burn = None  # step after which the running NIS per row is averaged
        self.source = None
        self._lin = None  # the linearisation state after the last update (estcal.estimate.kalman.run_steps)
        self._rowwise = max(32, 4 * len(self.names))
        self._states: dict = {}  # path -> (lock, journal) of the checkpoints this object writes
        self._resumed = None  # (checkpoint dict, its path) after resume()

    # ------------------------------------------------------------------ state
    @property
    def n_rows(self) -> int:
        """Rows processed so far (one filter step each)."""
        return self.flt.n_steps

    @property
    def estimate(self) -> np.ndarray:
        return self.flt.x

    @property
    def std(self) -> np.ndarray:
        return self.flt.std

    @property
    def covariance(self) -> np.ndarray:
        return self.flt.P

    @property
    def nis(self) -> np.ndarray:
        """(n,) normalised innovation squared of every row (χ² with the row's dimension under the model)."""
        return self.flt.monitor.nis

    @property
    def running_nis(self) -> float:
        """Mean NIS per measured component since the burn-in (expected 1; NaN during the burn-in)."""
        return self.flt.monitor.running(self.burn or self.n_rows)["nis_per_row"]

    def innovation_tests(self, burn_in: int | None = None, lags: int = 10, alpha: float = 0.05) -> InnovationTests:
        """NIS, zero-mean and whiteness tests of the innovations after the burn-in
        (:meth:`estcal.estimate.innovation.InnovationMonitor.tests`; default burn-in: until 2 p rows)."""
        mon = self.flt.monitor
        bi = default_burn_in(mon.dims, len(self.names)) if burn_in is None else burn_in
        return mon.tests(burn_in=bi, lags=lags, alpha=alpha)

    def result(self) -> OnlineResult:
        """The estimate, covariance, innovation tests and history (the schema of ``estcal online --json``)."""
        try:
            tests = self.innovation_tests().to_dict()
        except ValueError as exc:
            tests = {"error": str(exc)}
        pv = self.robot.params
        return OnlineResult(self.robot.name, self.source, self.flt.kind, self.options["q (SI)"],
                            self.options["--q-params"], list(self.names), self.flt.x, self.flt.std,
                            pv.values[self.fidx].copy(), self.flt.P, self.n_rows, tests, list(self.history),
                            self.options["relinearize"], self.robot, self.noise)

    # ----------------------------------------------------------------- update
    def update(self, data, points=None, *, R=None, p=None, context=None, trace: bool = False) -> OnlineUpdate:
        """Process rows: a :class:`~estcal.io.dataset.Dataset`, a CSV path, or arrays — joint
        readings (N, n) with ``points`` (N, 3) / (N, k, 3), or ``R`` (N, 3, 3) and ``p`` (N, 3).

        Any number of rows; the result does not depend on how a stream is cut into updates
        (beyond rounding). ``trace``: also return the estimate and std after every row."""
        if isinstance(data, (str, Path)):
            from estcal.io.dataset import load_dataset

            ds = load_dataset(data, self.robot, column_map=self.column_map)
        elif isinstance(data, Dataset):
            ds = data
        else:
            from estcal.io.dataset import dataset_from_arrays

            ds = dataset_from_arrays(self.robot.joint_names, data, points, R, p, context)
        if self.source is None:
            self.source = ds.where
        parts = [self._feed(ds.subset(slice(i, i + FEED_ROWS)) if ds.n > FEED_ROWS else ds, trace)
                 for i in range(0, ds.n, FEED_ROWS)]
        if not parts:
            return OnlineUpdate((self.n_rows + 1, self.n_rows), np.zeros(0), np.zeros(0, int), [])
        if len(parts) == 1:
            return parts[0]
        return OnlineUpdate((parts[0].rows[0], parts[-1].rows[1]), np.concatenate([u.nis for u in parts]),
                            np.concatenate([u.dims for u in parts]), [h for u in parts for h in u.history],
                            np.concatenate([u.estimate for u in parts]) if trace else None,
                            np.concatenate([u.std for u in parts]) if trace else None)

    def _method_for(self, ds):
        m = self.method or method_for_dataset(ds, self.robot)
        if m.name not in PER_POSE_METHODS:
            raise InputError(f"{ds.where}: method {m.name!r} is not a per-row method")
        return m

    def _feed(self, ds, trace: bool) -> OnlineUpdate:
        m = self._method_for(ds)
        n0 = self.n_rows

        def sub(i, j):
            s = Problem.__new__(Problem)
            s.robot = self.robot
            s.terms = [Term(m, ds.subset(slice(i - n0, j - n0)) if (i - n0, j - n0) != (0, ds.n) else ds,
                            self.noise)]
            return s

        with single_thread_blas():  # small matrices: BLAS threads only spin (estcal.base.blas)
            st = self._steps(sub, n0, n0 + ds.n)
        return self._record(st, ds, n0, trace)

    def _steps(self, sub, a, b) -> BlockStep:
        if self.relinearize == 1:
            return self._rowwise_steps(sub, a, b)
        else:
            def evaluate(i, j, theta):
                r = sub(i, j).evaluate(theta)
                if np.any(np.diff(r.pose) < 0):  # rows stacked step by step
                    o = np.argsort(r.pose, kind="stable")
                    r.e, r.H, r.sigma, r.pose = r.e[o], r.H[o], r.sigma[o], r.pose[o]
                return r.H[:, self.fidx], r.e, r.sigma, np.bincount(r.pose, minlength=j - i)

            blocks, self._lin = run_steps(self.flt, a, b, evaluate, self.relinearize, self._lin,
                                          rowwise=self._rowwise)
            return concat_steps(blocks)

    def _rowwise_steps(self, sub, a, b) -> BlockStep:
        """Steps a … b−1 one at a time through filterpy (the classical EKF, or the UKF)."""
        f = self.flt
        B, p = b - a, len(self.names)
        nis, dims = np.empty(B), np.empty(B, np.int64)
        X, V, T = np.empty((B, p)), np.empty((B, p)), np.empty(B)
        for k in range(B):
            step = f.step(sub(a + k, a + k + 1))
            nis[k], dims[k] = step.nis, step.y.size
            X[k], V[k], T[k] = f.f.x, np.diag(f.f.P), np.trace(f.f.P)
        return BlockStep(nis, dims, X, V, T)

    def _record(self, st: BlockStep, ds, n0: int, trace: bool) -> OnlineUpdate:
        """Burn-in, status history entries and the update's summary from the steps just made."""
        k = n0 + np.arange(1, st.nis.size + 1)  # 1-based row numbers
        if self.burn is None:
            rows_before = self.flt.n_rows - int(st.dims.sum())
            hit = np.flatnonzero(rows_before + np.cumsum(st.dims) >= 2 * len(self.names))
            if hit.size:
                self.burn = int(k[hit[0]])
        new = []
        sel = np.flatnonzero(k % self.history_every == 0)
        if sel.size:
            kk = k[sel]
            # the running NIS as it stood after row k: from the burn-in on, undefined (NaN) before it
            b = kk if self.burn is None else np.where(kk >= self.burn, self.burn, kk)
            run = self.flt.monitor.running_at(kk, b)
            sd = st.std
            for j, i in enumerate(sel):
                new.append({"row": int(kk[j]), "line": int(ds.lines[i]), "nis": float(st.nis[i]),
                            "nis_per_row": float(run[j]), "trace_P": float(st.trace[i]),
                            "estimate": st.estimate[i].tolist(), "std": sd[i].tolist()})
            self.history.extend(new)
        return OnlineUpdate((n0 + 1, n0 + st.nis.size), st.nis, st.dims, new,
                            st.estimate if trace else None, st.std if trace else None)

    def boundary(self, n: int) -> bool:
        """True when the filter cuts its blocks after row n whatever the updates are: a stream cut
        there into updates gives the same floating-point operations as one not cut (cut a stream
        at such rows to reproduce a run bit for bit, e.g. to checkpoint and resume it)."""
        if self.relinearize == 1:
            return True
        return n % BLOCK_GROUPS == 0 or segment_of(n, self.relinearize, self._rowwise)[0] == n

    # ------------------------------------------------------------ next pose
    def next_pose(self, candidates=None, criterion: str = "D", n_candidates: int = 2000, q_test=None,
                  refine: bool = False, rng=None):
        """The pose whose measurement most improves ``criterion`` of the current covariance
        (:func:`estcal.design.sequential.propose_next_pose`): ``candidates`` (K, n) joint readings
        (default: ``n_candidates`` uniform within the joint limits)."""
        from estcal.design.model import DesignModel
        from estcal.design.sequential import CalibrationState, propose_next_pose

        kind = (self.method.name if self.method is not None else "position")
        kind = {"location": "pose"}.get(kind, kind)
        st = CalibrationState(list(self.names), self.flt.x, self.flt.P, self.robot.name)
        model = DesignModel(self.robot, kind, list(self.names), sigma=self.noise.position,
                            sigma_rot=self.noise.orientation if kind == "pose" else None)
        return propose_next_pose(model, st, criterion, q_test=q_test, candidates=candidates,
                                 n_candidates=n_candidates, rng=rng, refine=refine)

    # ------------------------------------------------------------ checkpoints
    def save(self, path, *, position: dict | None = None, finished: bool = False) -> Path:
        """Write a checkpoint to ``path`` (atomic; the innovation record and history go to its journal
        ``<path>.journal``). The first save to a path locks it for this object's life (or until
        :meth:`close`) and refuses an existing file this object did not resume from.

        ``position``: where the rows came from, for ``estcal online --resume`` (``line``,
        ``input_bytes``, ``input_sha256_prefix``, ``input_sha256``: :meth:`CsvStream.position`)."""
        path = Path(path)
        key = str(path.resolve())
        if key not in self._states:
            self._open_state(path, key)
        journal = self._states[key][1]
        ptr = journal.append(self.flt.monitor, self.history)
        pos = {"line": None, "input_bytes": 0, "input_sha256_prefix": PrefixHasher().hexdigest(),
               "input_sha256": None, **(position or {})}
        save_checkpoint(path, filter_checkpoint(self.flt, options=self.options, rows=self.n_rows, position=pos,
                                                burn=self.burn, journal=ptr, finished=finished,
                                                lin=self._lin, source=self.source))
        return path

    def _open_state(self, path: Path, key: str) -> None:
        resumed_here = self._resumed is not None and Path(self._resumed[1]).resolve() == path.resolve()
        if not resumed_here and path.exists():
            raise CheckpointError(f"{path}: the file exists (a previous run's checkpoint?) — continue it with "
                                  f"OnlineCalibrator.resume / --resume {path}, or remove it / choose another path")
        lock = _acquire(path)
        try:
            if self._resumed is not None:
                journal = Journal.resume(path, *self._resumed)
            else:
                journal = Journal.start(path)
        except OSError as exc:
            lock.release()
            raise CheckpointError(f"{path}: cannot write its journal ({exc.strerror or exc})") from None
        self._states[key] = (lock, journal)

    def close(self) -> None:
        """Release the locks of the checkpoint files (they go with the process too)."""
        for lock, _ in self._states.values():
            lock.release()
        self._states.clear()

    def __enter__(self) -> "OnlineCalibrator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @classmethod
    def resume(cls, path, robot=None, **options) -> "OnlineCalibrator":
        """Continue the run checkpointed in ``path``: its robot (by default the one it names), its
        options (those given must equal the checkpointed ones) and its state, bit for bit; later
        :meth:`save` calls to ``path`` continue its journal. Feed it the rows after
        ``checkpoint["rows"]`` (``.n_rows``)."""
        path = Path(path)
        if path.is_dir():
            raise CheckpointError(f"{path}: is a folder — give the checkpoint file written by save() / --state")
        lock = _acquire(path)
        try:
            saved = load_checkpoint(path)
            cal = cls._from_checkpoint(saved, path, robot, options)
            cal._resumed = (saved, path)
            cal._states[str(path.resolve())] = (lock, Journal.resume(path, saved, path))
        except OSError as exc:
            lock.release()
            raise CheckpointError(f"{path}: cannot write its journal ({exc.strerror or exc})") from None
        except BaseException:
            lock.release()
            raise
        return cal

    @classmethod
    def _from_checkpoint(cls, saved: dict, path, robot, options: dict) -> "OnlineCalibrator":
        so = dict(saved["options"])
        so.setdefault("relinearize", 1)  # checkpoints of version 2 come from the row-by-row filter
        kw = _kwargs_of(so)
        kw["free"] = list(saved["parameters"])  # the set the run started with
        kw.update({k: v for k, v in options.items() if v is not None})
        history_every = kw.pop("history_every", 10)
        cal = cls(robot if robot is not None else so["--robot"], history_every=history_every, **kw)
        mine = dict(cal.options)
        if "free" not in options:  # the set comes from the checkpoint: compare what the run was given
            mine["--free"] = so.get("--free")
        if robot is not None and not isinstance(robot, (str, Path)):  # an object: compared by its values
            mine["--robot"] = so.get("--robot")
        diff = option_differences(_comparable(so), _comparable(mine))
        if diff:
            raise CheckpointError(f"{path}: the options differ from the checkpointed run (SI values): "
                                  f"{'; '.join(diff)} — give the same options to continue it")
        cal.options = so
        cal.history = restore_filter(cal.flt, saved, path)
        cal.burn = saved["burn"]
        cal.source = saved.get("source")
        lin = saved.get("lin")
        cal._lin = None if lin is None else (int(lin["start"]), np.asarray(lin["x"], float), int(lin["at"]),
                                             int(lin["window"]))
        cal.checkpoint = saved
        return cal


def _acquire(path: Path):
    """The run lock of a checkpoint file (:class:`estcal.base.lock.RunLock`), as a CheckpointError if held."""
    from estcal.base.lock import LockedError, RunLock

    try:
        return RunLock(path, "--state").acquire()
    except LockedError as exc:
        raise CheckpointError(str(exc)) from None
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot create its lock file ({exc.strerror or exc})") from None


def _kwargs_of(so: dict) -> dict:
    """Constructor keywords from a checkpoint's options."""
    q = so.get("q (SI)", 0.0)
    if so.get("--q-params"):
        q = {s.strip(): q for s in so["--q-params"].split(",") if s.strip()}
    return {"root": so.get("--root"), "tip": so.get("--tip"), "q": q, "filter": so.get("--filter", "ekf"),
            "measure": so.get("--method"), "noise": (so["noise-pos (m)"], so["noise-rot (rad)"]),
            "prior_std": so.get("prior-std (SI)", 0.1), "relinearize": so.get("relinearize", 1),
            "column_map": so.get("--map")}


def _comparable(opts: dict) -> dict:
    """Options compared on resume: the free set and q-parameter lists without spaces, the robot
    spec as written (a robot object counts by name; its values are compared separately)."""
    out = dict(opts)
    for k in ("--free", "--q-params"):
        if isinstance(out.get(k), str):
            out[k] = ",".join(s.strip() for s in out[k].split(",") if s.strip())
    return out


# ---------------------------------------------------------------- files and streams
def check_file(path, robot, column_map=None) -> Dataset:
    """The whole-file checks ``estcal online FILE`` makes before streaming it: the loader's
    (units, ranges, spread), identical rows refused (:class:`~estcal.base.errors.NumericalRefusal`)
    and the loader's warnings (``EstcalWarning``) — so that a stream never runs on data the batch
    commands refuse. ``column_map``: the file's (docs/dataset.md). Returns the Dataset."""
    from estcal.io.dataset import load_dataset
    from estcal.workflows.inputs import check_distinct_poses, warn_datasets

    ds = load_dataset(path, robot, column_map=_column_map(column_map))
    check_distinct_poses(ds)
    warn_datasets([ds])
    return ds


def file_free_set(robot, data, free=None, measure=None, noise=None) -> list[str]:
    """The free set ``estcal online FILE`` uses: an identifiable set of the whole file (rank test,
    :func:`estcal.identify.select_identifiable`) when ``free`` is None, else ``free``,
    checked identifiable from the whole file as ``estcal calibrate`` checks it
    (:class:`~estcal.identify.select.UnidentifiableError` otherwise). ``data``: a Dataset."""
    from estcal.identify.select import check_identifiable, select_identifiable
    from estcal.methods.reduced import DenseSystem, ReducedSystem, use_chunks

    meth = get_method(measure) if measure else None
    nz = _noise_model(noise)
    names = _names(free)
    with single_thread_blas():  # a QR of a tall thin matrix: BLAS threads only spin
        if names is None:
            return select_identifiable(Problem(robot, [(meth, data, nz)])).identifiable
        rb = robot.copy(robot.params.with_free(names))
        problem = Problem(rb, [(meth, data, nz)])
        pv = problem.params
        ck = use_chunks(problem)
        system = (DenseSystem(problem, pv.free_indices) if ck is None
                  else ReducedSystem(problem, pv.free_indices, ck))
        check_identifiable(system.linear(pv.values)[0], pv.free_names)
    return names


_BINARY = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f]")  # never in CSV text (tab, LF, CR allowed)


def _lines(data: str, block: int = 1 << 20):
    """Lines of the input as they come, in bounded memory (a 10⁶-row file is never held whole).

    A file has been read and checked by the input layer already (folder, binary, encoding):
    here it is decoded block by block — UTF-8 with or without BOM, or UTF-16 with BOM — and
    split exactly as ``str.splitlines(keepends=True)`` splits the whole text (a block's last,
    possibly incomplete line, or a ``\\r`` whose ``\\n`` may start the next block, is carried
    over)."""
    if data == "-":
        yield from sys.stdin
        return
    import codecs

    with open(data, "rb") as fh:
        bom = fh.read(2)
    enc = "utf-16" if bom in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE) else "utf-8-sig"
    with open(data, encoding=enc, newline="") as fh:
        carry = ""
        while True:
            text = fh.read(block)
            if not text:
                break
            parts = (carry + text).splitlines(keepends=True)
            carry = parts.pop()
            yield from parts
        if carry:
            yield from carry.splitlines(keepends=True)


def _stdin_idle() -> bool:
    """True when standard input has no line ready now (a live stream between rows)."""
    import select

    try:
        return not select.select([sys.stdin], [], [], 0)[0]
    except (ValueError, OSError, TypeError, AttributeError):  # not a real file (tests): never idle
        return False


@dataclass
class Chunk:
    """Rows read from a stream: ``data`` (a Dataset, or None) and, when reading stopped at a bad
    row, ``error`` (the rows before it are in ``data``)."""

    data: Dataset | None
    error: Exception | None = None


class CsvStream:
    """The data rows of a CSV file or standard input (``"-"``), parsed in chunks through the
    dataset loader's checks (:func:`estcal.io.dataset.dataset_from_table`), with the SHA-256 of
    the input consumed so far for checkpoints.

    ``cut(n)`` says whether a chunk may end after data row n (counted from the start of the
    input, so a resumed run cuts where an uninterrupted one does); on standard input a chunk
    also ends when no row is waiting (a live stream is processed as it arrives). ``skip`` rows
    are hashed and not returned (a resumed run); ``expect`` = (bytes, sha256) of the
    checkpointed prefix, checked when they have been read. ``checked``: the file was checked
    whole (units, spread): chunks skip those checks. ``throttle``: seconds to wait after each
    row (a file replayed as a slow stream). :meth:`position` is the input up to the end of the
    last chunk returned."""

    def __init__(self, source: str, robot, *, cut=lambda n: n % 1024 == 0, measure=None, skip: int = 0,
                 expect=None, checked: bool = False, throttle: float = 0.0, column_map=None):
        self.source, self.robot, self.cut = source, robot, cut
        self.cmap = _column_map(column_map)
        self._pending = []  # the first line of a file without a header row: a data row
        self.where = "<stdin>" if source == "-" else source
        self.allow_none = measure is not None
        self.skip, self.expect, self.checked, self.throttle = int(skip), expect, checked, float(throttle)
        self.hasher = PrefixHasher()
        self.input_sha256 = None if source == "-" else file_sha256(source)
        self.rows = 0  # data rows read (skipped ones included)
        self._it = self._numbered()
        self._at = None
        self._header()
        if self._at is None:
            self._at = self._mark()

    def position(self) -> dict:
        """Where the stream stood after the last chunk returned, as a checkpoint records it."""
        h, n, line = self._at
        return {"line": line, "input_bytes": n, "input_sha256_prefix": h.hexdigest(),
                "input_sha256": self.input_sha256}

    @property
    def last_line(self) -> int:
        return self._at[2]

    def _mark(self, line=None):
        return self.hasher.h.copy(), self.hasher.n, self.header_line if line is None else line

    def _numbered(self):
        src = enumerate(_lines(self.source), start=1)
        while True:
            try:
                ln, text = next(src)
            except StopIteration:
                return
            except UnicodeDecodeError:
                raise DatasetError(f"{self.where}: input is not UTF-8 text — send the CSV as UTF-8") from None
            bad = _BINARY.search(text)
            if bad:
                raise DatasetError(f"{self.where}, line {ln}, column {bad.start() + 1}: control character "
                                   f"0x{ord(bad.group()):02x} — binary data, not CSV text")
            self.hasher.update(text.encode("utf-8"))  # the consumed prefix, named in checkpoints
            yield ln, text

    def _header(self) -> None:
        from estcal.base.textinput import sniff_delimiter

        while True:
            before = self.hasher.h.copy(), self.hasher.n
            try:
                self.header_line, text = next(self._it)
            except StopIteration:
                raise DatasetError(f"{self.where}: empty input (expected a header row)") from None
            if text.strip():
                break
        first = text.lstrip("\ufeff")
        self.delimiter = sniff_delimiter(first)
        self.header = [h.strip() for h in next(csv.reader([first], delimiter=self.delimiter))]
        self._header_checked = False
        cols = self.cmap.columns if self.cmap is not None else None
        if cols is not None and self.header != cols:  # a file without a header row (the map's columns:)
            from estcal.io.columns import is_number

            if not all(is_number(h) for h in self.header if h):
                raise DatasetError(f"{self.where}, line {self.header_line}: the input has a header row "
                                   f"({', '.join(self.header[:6])}{'…' if len(self.header) > 6 else ''}) that "
                                   f"differs from columns: ({self.cmap.at('columns')}) — remove columns: from the "
                                   f"map or make it the input's header")
            self._pending = [(self.header_line, text)]
            self.header, self.header_line = list(cols), 0
            self._at = (before[0], before[1], 0)  # the first data line is not consumed yet

    def _check_header(self) -> None:
        """The loader's header checks, once (after the first data line was read and found to be text);
        through the column map, its checks of the header (columns it names, joints it leaves unmapped)."""
        from estcal.base.textinput import CsvTable
        from estcal.io.dataset import dataset_from_table

        self._header_checked = True
        header = self.header
        if self.cmap is not None:
            from estcal.io.columnmap import ColumnMapError, apply_column_map

            rb = self.robot
            try:
                header = apply_column_map(CsvTable(header, [], [], self.header_line, self.delimiter, self.where),
                                          self.cmap, rb.joint_names, rb.joint_types)[0].header
            except ColumnMapError as exc:
                raise DatasetError(str(exc)) from None
        empty = CsvTable(header, None, [], self.header_line, self.delimiter, self.where,
                         numeric=np.zeros((0, len(header))))
        ds = dataset_from_table(empty, self.robot, check_units=False)
        if ds.kind == "none" and not self.allow_none:
            raise DatasetError(f"{self.where}, line {self.header_line}: no measurement columns (x,y,z / x1..zk / "
                               f"x,y,z,qw,qx,qy,qz)")

    def _check_prefix(self) -> None:
        """The input read so far (up to :meth:`position`) is the checkpointed run's."""
        h, n, _ = self._at
        if self.expect is not None and (n, h.hexdigest()) != tuple(self.expect):
            raise CheckpointError(f"{self.where} differs from the checkpointed input (SHA-256 of the rows already "
                                  f"processed does not match)")

    def __iter__(self):
        if self.skip == 0:
            self._check_prefix()
        texts, lines, raw = [], [], []
        for ln, text in itertools.chain(self._pending, self._it):
            raw.append(text)
            if not text.strip():
                continue
            if not self._header_checked:
                self._check_header()
            self.rows += 1
            if self.rows <= self.skip:  # already in the checkpoint: hashed, not processed again
                raw = []
                if self.rows == self.skip:
                    self._at = self._mark(ln)
                    self._check_prefix()
                continue
            texts.append(text)
            lines.append(ln)
            if self.throttle:
                time.sleep(self.throttle)
            if self.cut(self.rows) or (self.source == "-" and _stdin_idle()):
                yield from self._chunks(texts, lines, raw)
                texts, lines, raw = [], [], []
        if texts:
            yield from self._chunks(texts, lines, raw)
        if not self._header_checked:
            self._check_header()
        if self.rows < self.skip:
            raise CheckpointError(f"{self.where} has {self.rows} data rows, fewer than the {self.skip} already "
                                  f"processed")

    def _parse(self, texts, lines):
        from estcal.base.textinput import CsvTable
        from estcal.io.dataset import dataset_from_mapped_table, dataset_from_table

        try:
            records = list(csv.reader(texts, delimiter=self.delimiter))
        except csv.Error as exc:
            raise DatasetError(f"{self.where}, line {lines[0]}: not a valid CSV line ({exc})") from None
        if len(records) != len(texts):
            raise DatasetError(f"{self.where}, line {lines[0]}: a quoted field spans lines — one row per line")
        table = CsvTable(self.header, records, lines, self.header_line, self.delimiter, self.where)
        if self.cmap is not None:
            ds = dataset_from_mapped_table(table, self.cmap, self.robot, check_units=not self.checked)
        else:
            ds = dataset_from_table(table, self.robot, check_units=not self.checked)
        if ds.kind == "none" and not self.allow_none:
            raise DatasetError(f"{self.where}: no measurement columns (x,y,z / x1..zk / x,y,z,qw,qx,qy,qz)")
        return ds

    def _chunks(self, texts, lines, raw):
        """The rows as one Dataset; at a bad row, the rows before it with the row's own error (the
        position then ends with the last good row), then the rows after it the same way."""
        start = self._at
        try:
            ds = self._parse(texts, lines)
            self._at = self._mark(lines[-1])
            yield Chunk(ds)
            return
        except (DatasetError, ValueError) as exc:
            bad, err = None, exc
            for i in range(len(texts)):  # the first row that fails alone (the error path only)
                try:
                    self._parse(texts[i:i + 1], lines[i:i + 1])
                except (DatasetError, ValueError) as row_exc:
                    bad, err = i, row_exc
                    break
        if bad is None:  # only the rows together fail (e.g. their spread): no row to blame
            yield Chunk(None, err)
            return
        h, nbytes, line = start[0].copy(), start[1], start[2]
        seen = 0
        for text in raw:  # the input up to the last good row
            if seen == bad:
                break
            b = text.encode("utf-8")
            h.update(b)
            nbytes += len(b)
            seen += bool(text.strip())
        self._at = (h, nbytes, lines[bad - 1] if bad else line)
        yield Chunk(self._parse(texts[:bad], lines[:bad]) if bad else None, err)
        if bad + 1 < len(texts):  # a caller that skips bad rows goes on with the next ones
            self._at = start
            at = [j for j, t in enumerate(raw) if t.strip()][bad]  # the bad row among the lines read
            yield from self._chunks(texts[bad + 1:], lines[bad + 1:], raw[at + 1:])
