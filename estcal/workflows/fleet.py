"""Fleet calibration: calibrate (or diagnose) every robot of a folder, one task per robot —
``estcal fleet`` (docs/scaling.md).

Layout of a fleet folder ``DIR`` (what :func:`discover_fleet` reads):

* one sub-folder per robot; the folder name is the robot's name;
* in it, the calibration dataset — ``data.csv`` (or ``calibration.csv``, or the
  only CSV that is not a validation file) — and optional validation datasets
  ``validate*.csv`` (scored, never fitted);
* the robot file — ``robot.yaml``/``robot.yml`` or a single ``*.urdf`` in the
  robot's folder, else one shared robot file (``robot.yaml``, ``robot.yml`` or a
  single ``*.urdf``) at ``DIR``'s top level.

Folders whose name starts with ``.`` or ``_`` are skipped (``_models/``, ``_results/`` …).

A fleet generated on demand is a folder with a ``fleet.yaml`` (and the nominal
robot file it names) instead of robot folders
(:class:`estcal.simulate.fleet.FleetSpec`, ``estcal simulate --fleet N
--on-demand``): robot ``i`` is simulated in memory by the task that calibrates it.

Every robot is one task of :func:`estcal.scale.runner.run_tasks`: a robot
whose folder is incomplete or whose calibration fails is reported (name,
inputs, one-line error) and the others go on. Each worker writes its robot's
saved model itself (``--save-models``; :meth:`CalibrationResult.save_model` /
:meth:`DiagnosisResult.save_model`, docs/robot-file.md "Saved models"), so only
the summary row travels back. With a results folder (``--results``, default
``DIR/_results``), each row is saved as it arrives and a rerun skips the robots
already done (:mod:`estcal.workflows.fleet_results`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from estcal.base.errors import InputError, MissingExtraError
from estcal.io.columnmap import ColumnMap, load_column_map

__all__ = ["FleetJob", "FleetOptions", "FleetSummary", "FleetError", "discover_fleet", "process_robot",
           "run_fleet", "check_scheduler", "fleet_inputs"]


class FleetError(InputError):
    """A robot folder that cannot be processed (missing dataset or robot file)."""


def check_scheduler(scheduler) -> None:
    """``scheduler`` must be one the runner knows (:func:`estcal.scale.runner.check_scheduler`), and a
    Dask one needs the ``dask`` extra installed: a :class:`MissingExtraError` naming it, before the work."""
    from estcal.scale.runner import check_scheduler as check

    try:
        check(scheduler)
    except ValueError as exc:
        raise InputError(f"--scheduler: {exc}") from None
    if isinstance(scheduler, str) and (scheduler == "local" or "://" in scheduler):
        try:
            import distributed  # noqa: F401  (the run needs it: fail before the work)
        except ImportError:
            raise MissingExtraError(f"--scheduler {scheduler}", "dask", "dask.distributed") from None


@dataclass(frozen=True)
class FleetJob:
    """Inputs of one robot: its name, dataset, validation files and robot file (paths as strings)."""

    name: str
    folder: str
    data: str | None
    validate: tuple = ()
    robot: str | None = None
    problem: str | None = None  # why the folder is incomplete (the task then fails with this message)
    index: int | None = None    # a robot generated on demand: its index in ``spec``
    spec: object = None         # … and the fleet's :class:`~estcal.simulate.fleet.FleetSpec`

    def __repr__(self) -> str:  # the "inputs" of a failure report: short and readable
        if self.spec is not None:
            return f"{self.name}: generated (fleet.yaml, seed {self.spec.seed}, index {self.index})"
        return f"{self.name}: data={Path(self.data).name if self.data else None}, robot={self.robot}"


@dataclass(frozen=True)
class FleetOptions:
    """What to do with each robot (the ``estcal fleet`` options)."""

    level: str = "full"
    estimator: str = "lm"
    diagnose: bool = False
    noise_pos: float = 1e-4
    noise_rot: float = 1e-3
    known_noise: bool = False
    save_models: str | None = None
    seed: int = 0
    #: the column map of every robot's data files (docs/dataset.md): its YAML path or a parsed
    #: :class:`estcal.io.columnmap.ColumnMap`; :func:`run_fleet` parses it once, so that workers on other
    #: machines need not read the map file
    column_map: object = field(default=None, compare=False)


def _robot_file(folder: Path) -> Path | None:
    for name in ("robot.yaml", "robot.yml"):
        if (folder / name).is_file():
            return folder / name
    urdfs = sorted(folder.glob("*.urdf"))
    return urdfs[0] if len(urdfs) == 1 else None


def _datasets(folder: Path) -> tuple[Path | None, list[Path], str | None]:
    csvs = sorted(p for p in folder.glob("*.csv") if p.is_file())
    val = [p for p in csvs if p.name.lower().startswith("validat")]
    rest = [p for p in csvs if p not in val]
    for name in ("data.csv", "calibration.csv"):
        if folder / name in rest:
            return folder / name, val, None
    if len(rest) == 1:
        return rest[0], val, None
    if not rest:
        return None, val, "no calibration dataset (expected data.csv)"
    return None, val, f"{len(rest)} candidate datasets ({', '.join(p.name for p in rest[:4])}); name one data.csv"


def _generated(root: Path, folders) -> list[FleetJob]:
    from estcal.simulate.fleet import SPEC_FILE, FleetSpec

    if folders:
        raise FleetError(f"{root}: holds both {SPEC_FILE} (a fleet generated on demand) and robot folders "
                         f"({', '.join(p.name for p in folders[:3])}{' …' if len(folders) > 3 else ''}): keep one")
    spec = FleetSpec.read(root / SPEC_FILE)
    return [FleetJob(spec.name(i), str(root), None, (), spec.robot, None, i, spec) for i in range(spec.robots)]


def discover_fleet(root) -> list[FleetJob]:
    """One :class:`FleetJob` per robot folder of ``root`` (sorted by name), or per robot of the
    fleet described by ``root/fleet.yaml``; see the module docstring."""
    from estcal.simulate.fleet import SPEC_FILE

    root = Path(root)
    if not root.is_dir():
        raise FleetError(f"{root}: not a folder (expected one sub-folder per robot)")
    folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith((".", "_")))
    if (root / SPEC_FILE).is_file():
        return _generated(root, folders)
    shared = _robot_file(root)
    jobs = []
    for folder in folders:
        data, val, problem = _datasets(folder)
        rf = _robot_file(folder) or shared
        if rf is None and problem is None:
            problem = (f"no robot file (robot.yaml or one .urdf in {folder.name}/, or one shared at "
                       f"{root.name}/robot.yaml)")
        jobs.append(FleetJob(folder.name, str(folder), str(data) if data else None, tuple(map(str, val)),
                             str(rf) if rf else None, problem))
    if not jobs:
        raise FleetError(f"{root}: no robot folders (expected one sub-folder per robot with data.csv)")
    return jobs


def fleet_inputs(root) -> list[Path]:
    """Every file the robots of the fleet folder read (datasets, validation and robot files): the
    command's outputs must not land on them. Empty when the folder has no robot folder."""
    try:
        files = {Path(f) for j in discover_fleet(root) for f in (j.data, j.robot, *j.validate) if f}
    except InputError:
        return []
    return sorted(files | {p for p in [Path(root) / "fleet.yaml"] if p.is_file()})


def _load(job: FleetJob, column_map=None):
    if job.spec is not None:  # generated on demand: simulated here, in memory
        g = job.spec.generate(job.index)
        return g.nominal, g.dataset, [g.validation] if g.validation is not None else [], []
    from estcal.workflows.inputs import load_datasets, robot_for_data

    rob, n_markers = robot_for_data(job.robot, job.data, column_map=column_map)
    ds, *vals = load_datasets([job.data, *job.validate], rob, n_markers, column_map)
    warnings = [f"{Path(d.where).name}: {w}" if d.where else w for d in [ds] + vals for w in d.warnings]
    return rob, ds, vals, warnings


def _acc(acc, which="after", key="rmse_mm"):
    v = (acc or {}).get(which, {}).get(key)
    return None if v is None else float(v)


def _calibrate(job, opts, rob, ds, vals, warnings) -> dict:
    from estcal.methods import NoiseModel
    from estcal.workflows.calibrate import run_calibration

    noise = NoiseModel(position=opts.noise_pos, orientation=opts.noise_rot, scalar=opts.noise_pos,
                       known=opts.known_noise)
    res, sel, problem = run_calibration(rob, ds, estimator=opts.estimator, level=opts.level, validate=vals,
                                        noise=noise)
    if not res.converged:
        warnings.append("not converged")
    acc = res.accuracy or {}
    val = acc.get("validation", [])
    row = {"poses": int(ds.n), "n_parameters": len(res.names), "sigma0": float(res.sigma0),
           "converged": bool(res.converged),
           "rmse_before_mm": _acc(acc.get("train"), "before"), "rmse_after_mm": _acc(acc.get("train")),
           "rot_rmse_after_mrad": _acc(acc.get("train"), "after", "rmse_mrad"),
           "validation_rmse_before_mm": _acc(val[0], "before") if val else None,
           "validation_rmse_mm": _acc(val[0]) if val else None, "causes": []}
    if opts.save_models:
        path = Path(opts.save_models) / f"{job.name}.yaml"
        res.save_model(path, _provenance(job, {"source": "estcal fleet", "robot": job.name, "level": opts.level}))
        row["model"] = str(path)
    return row


def _diagnose(job, opts, rob, ds, vals, warnings) -> dict:
    """One robot's diagnosis: before = the registration alone, after = the diagnosis's model, both at new
    postures (cross-validation); each validation file's figure at its new postures."""
    from estcal.discrepancy import diagnose

    res = diagnose(rob, ds, validate=vals, noise=opts.noise_pos if opts.known_noise else None, rng=opts.seed)
    causes = [f"{c.effect}({','.join(c.joints) if c.joints else 'arm'})" for c in res.causes]
    val = res.accuracy.get("validation") or []
    row = {"poses": int(ds.n), "n_parameters": len(res.covariance_names),
           "rmse_before_mm": _first((res.budget or {}).get("nominal_mm")), "rmse_after_mm": res.answer["expected_mm"],
           "validation_rmse_before_mm": None, "validation_rmse_mm": val[0]["rmse_mm"] if val else None,
           "causes": causes, "verdict": res.verdict}
    if opts.save_models:
        path = Path(opts.save_models) / f"{job.name}.yaml"
        res.save_model(path, _provenance(job, {"source": "estcal fleet --diagnose", "robot": job.name}))
        row["model"] = str(path)
    return row


def _provenance(job, prov: dict) -> dict:
    if job.spec is not None:  # no data file to point at: how to regenerate the data instead
        prov["generated"] = {"fleet": str(Path(job.folder) / "fleet.yaml"), "seed": job.spec.seed,
                             "index": job.index}
    return prov


def _first(v):
    if isinstance(v, (list, tuple)):
        v = v[0] if v else None
    return None if v is None else float(v)


def process_robot(job: FleetJob, opts: FleetOptions) -> dict:
    """Calibrate (or diagnose) one robot and write its saved model; returns its summary row.

    Raises :class:`FleetError` for an incomplete folder and whatever loading or
    estimation raises otherwise (the runner reports it with the robot's inputs).
    """
    if job.problem:
        raise FleetError(f"{job.folder}: {job.problem}")
    rob, ds, vals, warnings = _load(job, opts.column_map)
    row = (_diagnose if opts.diagnose else _calibrate)(job, opts, rob, ds, vals, warnings)
    return {"robot": job.name, **row, "warnings": warnings}


def _process(job, opts):  # task signature of run_tasks: fn(task)
    return process_robot(job, opts)


@dataclass
class FleetSummary:
    """Rows of the robots processed (those of an earlier run included), failures (robot, inputs,
    error), and how the run went: ``n_skipped`` robots were found done in the ``results`` folder."""

    rows: list
    failures: list
    scheduler: str
    n_workers: int
    wall_s: float
    options: dict = field(default_factory=dict)
    n_skipped: int = 0
    results: str | None = None

    @property
    def n_ok(self) -> int:
        return len(self.rows)

    def to_dict(self) -> dict:
        return {"n_robots": len(self.rows) + len(self.failures), "n_ok": len(self.rows),
                "n_failed": len(self.failures), "n_skipped": self.n_skipped, "results": self.results,
                "scheduler": self.scheduler, "n_workers": self.n_workers, "wall_s": self.wall_s,
                "options": self.options, "robots": self.rows, "failures": self.failures}


#: robots per Dask task at most: a task of about a second (50 ms a robot), so that rows arrive
#: steadily and a lost worker costs at most that much work, for ~3 ms of Dask per task (docs/scaling.md)
ROBOTS_PER_TASK = 16


def run_fleet(root, opts: FleetOptions = FleetOptions(), scheduler="serial", n_workers: int | None = None,
              progress="auto", results=None) -> FleetSummary:
    """Process every robot of the fleet folder ``root``; failures are listed, never fatal.

    With ``results`` (a folder), every robot's row is saved there as it arrives and the robots
    already done with the same options and inputs are skipped (:mod:`estcal.workflows.fleet_results`);
    the summary then holds every robot's row, the earlier ones included, each once.
    """
    import contextlib
    import functools

    from estcal.workflows.fleet_results import ResultFolder

    check_scheduler(scheduler)
    cmap = opts.column_map
    if cmap is not None and not isinstance(cmap, ColumnMap):
        opts = replace(opts, column_map=load_column_map(cmap))
    jobs = discover_fleet(root)
    options = {k: getattr(opts, k) for k in opts.__dataclass_fields__}
    options["column_map"] = opts.column_map.path if opts.column_map is not None else None
    if opts.save_models:
        Path(opts.save_models).mkdir(parents=True, exist_ok=True)
    store = ResultFolder(results, options) if results is not None else None
    done = store.finished(jobs) if store is not None else {}
    todo = [k for k in range(len(jobs)) if k not in done]
    rows = dict(done)

    def arrived(i, row, failure):  # in this process, as each robot's result arrives
        if row is not None:
            rows[todo[i]] = row
            if store is not None:
                store.save(jobs[todo[i]], row)

    with store if store is not None else contextlib.nullcontext():
        rr = _run(functools.partial(_process, opts=opts), [jobs[k] for k in todo], scheduler, n_workers,
                  progress, arrived)
    fails = [{"robot": jobs[todo[f.index]].name, "folder": jobs[todo[f.index]].folder, "inputs": f.inputs,
              "error": f.error} for f in rr.failures]
    lost = store.errors() if store is not None else {}
    fails += [{"robot": jobs[k].name, "folder": jobs[k].folder, "inputs": repr(jobs[k]),
               "error": lost[jobs[k].name]} for k in sorted(rows) if jobs[k].name in lost]
    ok = [rows[k] for k in sorted(rows) if jobs[k].name not in lost]
    label = rr.scheduler if todo or not isinstance(scheduler, str) else scheduler
    return FleetSummary(ok, fails, label, rr.n_workers, rr.wall_s, options, len(done),
                        str(results) if results is not None else None)


def _run(fn, jobs, scheduler, n_workers, progress, on_done=None):
    from estcal.scale.runner import run_tasks

    return run_tasks(fn, jobs, scheduler=scheduler, n_workers=n_workers, progress=progress, desc="fleet",
                     max_chunksize=ROBOTS_PER_TASK, on_done=on_done)
