"""Online (recursive) calibration as a Python object: :class:`OnlineCalibrator`.

The object behind ``estcal online``, for scripts that calibrate a robot while it works::

    import estcal
    cal = estcal.OnlineCalibrator("puma560", free=["offset_*", "a_2"], noise=(1e-4, 1e-3))
    cal.update("first_rows.csv")            # a CSV path, a Dataset, or arrays: any number of rows
    cal.update(q, xyz)                      # joint readings (N, n) and measured points (N, 3)
    cal.save("state.json")                  # crash-safe checkpoint (state + journal, locked)
    print(cal.result().table())             # estimate ± σ (mm, mrad); result().to_dict(): online --json (SI)
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

**Layers.** This module orchestrates: options, loading and checking, checkpoints, results. The
filter's arithmetic over rows (segments, blocks, burn-in, history) is
:mod:`estcal.estimate.online`; the rows of a file or of standard input are read by
:class:`estcal.io.stream.CsvStream` (docs/architecture.md).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from estcal.base.blas import single_thread_blas
from estcal.base.errors import InputError
from estcal.estimate._common import prior_std_vector
from estcal.methods.reduced import PER_POSE_METHODS
from estcal.estimate.checkpoint import (CheckpointError, Journal, PrefixHasher, filter_checkpoint, load_checkpoint,
                                        option_differences, restore_filter, save_checkpoint)
from estcal.estimate.innovation import InnovationTests
from estcal.estimate.kalman import ParameterFilter, default_burn_in, process_noise
from estcal.estimate.online import (OnlineResult, OnlineUpdate, block_boundary, filter_rows, record_steps,
                                    row_problems)
from estcal.io.columnmap import as_column_map
from estcal.io.stream import Chunk, CsvStream  # noqa: F401  (the stream estcal online reads; public here too)
from estcal.io.dataset import Dataset
from estcal.methods.base import NoiseModel, get_method, method_for_dataset
from estcal.methods.problem import Problem

__all__ = ["OnlineCalibrator", "OnlineUpdate", "OnlineResult", "CsvStream", "Chunk", "check_file", "file_free_set",
           "default_free_set",
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
    cmap = as_column_map(column_map)
    if cmap is not None:
        out["--map"] = cmap.to_dict()
    return out


class OnlineCalibrator:
    """Recursive calibration of a robot from rows that arrive over time.

    Parameters
    ----------
    robot : a robot object, a built-in name, a robot file or a URDF (with ``root``/``tip``).
    free : names or patterns of the parameters to estimate (list or comma-separated string);
        default: the identifiable subset of the robot's free mask for the measurement of the first rows
        given to :meth:`update` (:func:`default_free_set`) — the set ``estcal online`` estimates.
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
        self.column_map = as_column_map(column_map)
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
        self._filter_options = (q, prior_std, filter)
        self.names = self.fidx = self.flt = None
        if names is not None:
            self._start(rb.params.free_names)
        self.relinearize = 1 if filter == "ukf" else relinearize
        self.history_every = int(history_every)
        self.history: list = []
        self.burn = None  # step after which the running NIS per row is averaged
        self.source = None
        self._lin = None  # the linearisation state after the last update (estcal.estimate.kalman.run_steps)
        self._states: dict = {}  # path -> (lock, journal) of the checkpoints this object writes
        self._resumed = None  # (checkpoint dict, its path) after resume()

    def _start(self, names) -> None:
        """The filter over ``names`` (the free set: given, or chosen from the first rows' measurement)."""
        q, prior_std, kind = self._filter_options
        if not names:
            raise InputError("no free parameter to estimate (give free=… or set the robot's free mask)")
        self.robot = self.robot.copy(self.robot.params.with_free(list(names)))
        pv = self.robot.params
        self.names, self.fidx = pv.free_names, pv.free_indices
        Q = process_noise(self.names, q)
        P0 = np.diag(prior_std_vector(None, self.names, prior_std) ** 2)
        self.flt = ParameterFilter(pv.values, self.fidx, P0, Q, kind=kind, names=self.names)
        self._rowwise = max(32, 4 * len(self.names))

    def start(self, data) -> list[str]:
        """Choose the free set now from the measurement of ``data`` (a Dataset of any number of rows — the
        layout a stream's header gives, :meth:`CsvStream.layout`) when ``free`` was not given; :meth:`update`
        does it with its first rows otherwise. Returns the free parameters."""
        if self.flt is None:
            self._start(default_free_set(self.robot, data, self.method and self.method.name, self.noise))
        return list(self.names)

    def _started(self) -> ParameterFilter:
        if self.flt is None:
            raise InputError("no rows yet: the free set (free=None: the identifiable set of the measurement) is "
                             "chosen from the first rows given to update() — give free=… to start without rows")
        return self.flt

    # ------------------------------------------------------------------ state
    @property
    def n_rows(self) -> int:
        """Rows processed so far (one filter step each)."""
        return 0 if self.flt is None else self.flt.n_steps

    @property
    def estimate(self) -> np.ndarray:
        return self._started().x

    @property
    def std(self) -> np.ndarray:
        return self._started().std

    @property
    def covariance(self) -> np.ndarray:
        return self._started().P

    @property
    def nis(self) -> np.ndarray:
        """(n,) normalised innovation squared of every row (χ² with the row's dimension under the model)."""
        return self._started().monitor.nis

    @property
    def running_nis(self) -> float:
        """Mean NIS per measured component since the burn-in (expected 1; NaN during the burn-in)."""
        return self._started().monitor.running(self.burn or self.n_rows)["nis_per_row"]

    def innovation_tests(self, burn_in: int | None = None, lags: int = 10, alpha: float = 0.05) -> InnovationTests:
        """NIS, zero-mean and whiteness tests of the innovations after the burn-in
        (:meth:`estcal.estimate.innovation.InnovationMonitor.tests`; default burn-in: until 2 p rows)."""
        mon = self._started().monitor
        bi = default_burn_in(mon.dims, len(self.names)) if burn_in is None else burn_in
        return mon.tests(burn_in=bi, lags=lags, alpha=alpha)

    def result(self) -> OnlineResult:
        """The estimate, covariance, innovation tests and history (the schema of ``estcal online --json``).
        Warns (``EstcalWarning``) when the rows give no more equations than free parameters — data
        ``estcal calibrate`` refuses (degrees of freedom ≤ 0): the estimates are then the prior's."""
        m, p = int(np.sum(self._started().monitor.dims)), len(self.names)
        if self.n_rows and m <= p:
            import warnings

            from estcal.base.errors import EstcalWarning

            warnings.warn(f"{self.source}: {self.n_rows} rows give {m} equations for {p} free parameters (degrees of "
                          f"freedom {m - p} ≤ 0), which `estcal calibrate` refuses: the estimates below are held by "
                          f"the prior, not by the data — feed more rows, or estimate fewer parameters",
                          EstcalWarning, stacklevel=2)
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
        self.start(ds)  # free=None: the identifiable set of this measurement (docs/conventions.md)
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
        method, n0 = self._method_for(ds), self.n_rows
        sub = row_problems(self.robot, method, self.noise, ds, n0)
        with single_thread_blas():  # small matrices: BLAS threads only spin (estcal.base.blas)
            st, self._lin = filter_rows(self.flt, sub, n0, n0 + ds.n, self.relinearize, self._lin, self._rowwise)
        self.burn, up = record_steps(self.flt, st, ds.lines, n0, self.burn, self.history_every, trace)
        self.history.extend(up.history)
        return up

    def boundary(self, n: int) -> bool:
        """True when the filter cuts its blocks after row n whatever the updates are: a stream cut
        there into updates gives the same floating-point operations as one not cut (cut a stream
        at such rows to reproduce a run bit for bit, e.g. to checkpoint and resume it)."""
        return block_boundary(n, self.relinearize, self._rowwise)

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
        st = CalibrationState(list(self.names), self._started().x, self.flt.P, self.robot.name)
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
        flt = self._started()
        path = Path(path)
        key = str(path.resolve())
        if key not in self._states:
            self._open_state(path, key)
        journal = self._states[key][1]
        ptr = journal.append(flt.monitor, self.history)
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

    ds = load_dataset(path, robot, column_map=as_column_map(column_map))
    check_distinct_poses(ds)
    warn_datasets([ds])
    return ds


def default_free_set(robot, data, measure=None, noise=None) -> list[str]:
    """The free set of ``OnlineCalibrator(robot)`` and ``estcal online`` by default: the identifiable subset
    of the robot's free mask (gains and offsets included: a filter that follows a stream tracks what
    drifts) for the measurement of ``data`` — the rank test (:func:`estcal.identify.select_identifiable`,
    GECARO's priority order) on generic poses, uniform within the joint limits and measured exactly at
    the robot's values (:func:`estcal.estimate.checks.generic_dataset`). It belongs to the robot and the
    measurement, not to the rows: a stream fed in any chunks gets the set the whole file gets.
    ``data``: a Dataset of the measurement (any number of rows, none: a header's layout)."""
    from estcal.estimate.checks import generic_dataset
    from estcal.identify.select import select_identifiable

    if data.kind not in ("position", "points", "pose"):
        raise InputError(f"{data.where}: no measured position, points or pose to choose the free set by — give "
                         f"free=… (--free)")
    meth = get_method(measure) if measure else None
    per_pose = 6 if data.kind == "pose" else 3 * max(data.n_points, 1)
    n = max(8, int(np.ceil(2 * len(robot.params.free_names) / per_pose)))
    gen = generic_dataset(robot, data, robot.params.values, n)
    with single_thread_blas():
        return select_identifiable(Problem(robot, [(meth, gen, _noise_model(noise))])).identifiable


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
