"""Experiment design: an optimal measurement plan (``estcal design``) and the next measurement pose
from a current estimate (``estcal next-pose``); docs/design.md.

Units at the edge: test poses typed as ``q1,q2,…`` are degrees (revolute) / mm (prismatic), as the
plans print them (:func:`parse_poses`, :func:`format_readings`); noise σ in SI; the plan written
by :func:`write_plan` is a CSV in estcal's dataset column layout (one column per joint, rad / m):
the input of ``estcal fk`` (targets) and of ``--candidates``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estcal.base.errors import InputError, NumericalRefusal
from estcal.workflows.inputs import input_errors

__all__ = ["DesignRun", "NextPoseRun", "design", "next_pose", "parse_poses", "default_test_pose",
           "format_readings", "parse_free", "write_plan", "MEASURES"]

MEASURES = ("position", "pose", "points")


def parse_poses(specs, robot) -> np.ndarray | None:
    """``["10,-60,120,0,30,0", ...]`` → (K, n) readings: revolute joints in degrees,
    prismatic joints in millimetres (converted to rad / m)."""
    if not specs:
        return None
    rows = []
    for s in specs:
        try:
            vals = [float(v) for v in str(s).replace(";", ",").split(",") if v.strip()]
        except ValueError:
            raise InputError(f"--test-pose {s!r}: expected {robot.n_joints} comma-separated numbers") from None
        if len(vals) != robot.n_joints:
            raise InputError(f"--test-pose {s!r}: expected {robot.n_joints} values for joints "
                             f"{robot.joint_names}, got {len(vals)}")
        rows.append(vals)
    Q = np.asarray(rows, float)
    rev = np.array([t == "revolute" for t in robot.joint_types])
    Q[:, rev] = np.radians(Q[:, rev])
    Q[:, ~rev] *= 1e-3
    return Q


def default_test_pose(robot) -> np.ndarray:
    """Mid-range of every joint (documented default when a test pose is needed but not given)."""
    return robot.limits.mean(1)[None]


def format_readings(Q, robot) -> list[str]:
    """One line per pose: revolute joints in degrees, prismatic in mm."""
    rev = np.array([t == "revolute" for t in robot.joint_types])
    return ["  ".join(f"{np.degrees(v):9.3f}°" if r else f"{v * 1e3:9.2f}mm" for v, r in zip(q, rev))
            for q in np.atleast_2d(Q)]


def parse_free(spec, robot, measure) -> list[str]:
    """``--free`` (comma-separated names / shell patterns) or the identifiable subset of ``measure``."""
    from estcal.design.model import identifiable_subset

    if not spec:
        return identifiable_subset(robot, measure)
    pats = [s.strip() for s in spec.split(",") if s.strip()] if isinstance(spec, str) else list(spec)
    with input_errors("--free: "):
        return robot.params.with_free(pats).free_names


def write_plan(path, readings, robot) -> Path:
    """The plan's joint readings as a CSV in estcal's dataset column layout (one column per joint,
    rad / m; docs/dataset.md), written atomically."""
    from estcal.io.dataset import dataset_from_arrays, write_dataset

    ds = dataset_from_arrays(robot.joint_names, np.atleast_2d(readings))
    return write_dataset(path, ds)


def _check_measure(measure) -> str:
    if measure == "location":
        measure = "pose"
    if measure not in MEASURES:
        raise InputError(f"unknown measure {measure!r} for a design; choose one of {', '.join(MEASURES)}")
    return measure


@dataclass
class DesignRun:
    """What :func:`design` computed: the robot, the design model, the plan and its criteria, the
    random-plan baseline, the test poses, the predicted RMS position error at them (mm) and the
    accuracy map (or None)."""

    robot: object
    model: object
    criterion: str
    plan: object
    criteria: object
    baseline: object
    q_test: np.ndarray | None
    rho_mm: np.ndarray | None
    accuracy_map: object
    sigma_mm: float
    measure: str

    @property
    def beats_random(self) -> bool:
        from estcal.design.criteria import larger_is_better

        b = self.baseline
        return bool(self.plan.value > b.max if larger_is_better(self.criterion) else self.plan.value < b.min)

    def to_dict(self) -> dict:
        """The JSON of ``estcal design --json`` (SI, the unit in every key name)."""
        return {"robot": self.robot.name, "measure": self.measure, "sigma_mm": self.sigma_mm,
                "free": list(self.model.free), "criterion": self.criterion, "plan": self.plan.to_dict(),
                "criteria": self.criteria.to_dict(),
                "rho0_mm": None if self.rho_mm is None else self.rho_mm.tolist(),
                "test_poses_rad": None if self.q_test is None else self.q_test.tolist(),
                "baseline": self.baseline.to_dict(), "beats_random": self.beats_random,
                "accuracy_map": None if self.accuracy_map is None else self.accuracy_map.to_dict()}


def _check_candidates(model, cand, candidates) -> None:
    """A plan drawn from candidates can determine no more than the candidates together."""
    J = model.jacobian(cand).reshape(-1, model.p)
    scale = np.linalg.norm(J, axis=0)
    r = int(np.linalg.matrix_rank(J / np.where(scale > 0, scale, 1.0))) if J.size else 0
    if r < model.p:
        n_distinct = len(np.unique(np.asarray(cand), axis=0))
        raise NumericalRefusal(f"--candidates {candidates}: its {len(cand)} poses ({n_distinct} distinct) determine "
                               f"only {r} of the {model.p} free parameters — every plan drawn from them has a "
                               f"singular information matrix; give more and better-spread candidates, or fewer "
                               f"--free parameters")


def _map_box(robot, text):
    from estcal.design.model import ToolBox

    if not text:
        return None
    v = [float(x) * 1e-3 for x in text.split(",")]
    if len(v) != 6:
        raise InputError("--map-box needs 6 numbers xmin,ymin,zmin,xmax,ymax,zmax (mm)")
    return ToolBox(robot, v[:3], v[3:])


def design(robot, n: int, *, measure: str = "position", criterion: str = "D", test_poses=None, candidates=None,
           degrees: bool = False, algorithm: str = "fedorov", n_candidates: int = 2000, restarts: int = 4,
           sigma_mm: float = 0.1, sigma_rot_mrad: float = 1.0, free=None, random_plans: int = 1000,
           accuracy_map: int = 0, map_box: str | None = None, seed: int = 0, scheduler: str = "processes",
           workers: int | None = None, keep_baseline: bool = False) -> DesignRun:
    """An optimal plan of ``n`` poses for ``robot`` and ``measure`` — the job of ``estcal design``.

    ``test_poses``: ``"q1,q2,…"`` strings (deg / mm); ``candidates``: CSV of candidate readings
    (rad / m, or degrees with ``degrees``); ``accuracy_map``: poses of the predicted-error map
    (0 = none), ``map_box`` restricting it to a tool-position box (mm); ``keep_baseline``: keep
    the random plans' criterion values (for the report's histogram).
    """
    from estcal.design.criteria import CRITERIA, normalise_criterion
    from estcal.design.model import DesignModel, resolve_robot
    from estcal.design.plans import (evaluate_plan, load_candidates, optimise_continuous, optimise_discrete,
                                     random_baseline)

    measure = _check_measure(measure)
    with input_errors():
        crit = normalise_criterion(criterion)
        rb = resolve_robot(robot)
        model = DesignModel(rb, measure, parse_free(free, rb, measure), sigma=sigma_mm * 1e-3,
                            sigma_rot=sigma_rot_mrad * 1e-3 if measure == "pose" else None)
        need = -(-model.p // model.rows_per_pose)  # ceil: poses for as many equations as parameters
        if n < need and model.prior_information is None:
            raise NumericalRefusal(f"--n {n}: a plan of {n} poses gives {n * model.rows_per_pose} equations for "
                                   f"{model.p} free parameters — the information matrix is singular (every "
                                   f"criterion infinite or zero); use --n {need} or more, or fewer --free "
                                   f"parameters")
        q_test = parse_poses(test_poses, rb)
        if q_test is None and CRITERIA[crit][1]:
            q_test = default_test_pose(rb)
        cand = None if candidates is None else load_candidates(candidates, rb, degrees)
        if cand is not None and model.prior_information is None:
            _check_candidates(model, cand, candidates)
        if algorithm == "continuous":
            if cand is not None:
                raise InputError("--candidates applies to the discrete algorithms, not 'continuous'")
            plan = optimise_continuous(model, n, crit, n_starts=restarts, rng=seed, q_test=q_test,
                                       scheduler=scheduler if restarts > 1 else "serial", n_workers=workers,
                                       prescreen=200)
        else:
            plan = optimise_discrete(model, n, crit, candidates=cand, n_candidates=n_candidates, algorithm=algorithm,
                                     restarts=restarts, rng=seed, q_test=q_test)
        crits = evaluate_plan(model, plan.readings, q_test=q_test)
        base = random_baseline(model, n, crit, n_plans=random_plans, rng=seed + 1, q_test=q_test,
                               keep_values=keep_baseline)
        amap = None
        if accuracy_map > 0:
            amap = model.accuracy_map(model.covariance(plan.readings), n=accuracy_map, rng=seed + 2,
                                      constraint=_map_box(rb, map_box))
    rho = None
    if q_test is not None:
        J0 = model.position_jacobian(q_test)
        C = model.covariance(plan.readings)
        rho = np.sqrt(np.einsum("tap,pq,taq->t", J0, C, J0)) * 1e3
    return DesignRun(rb, model, crit, plan, crits, base, q_test, rho, amap, sigma_mm, measure)


@dataclass
class NextPoseRun:
    """What :func:`next_pose` computed: the robot, the design model, the state, the criterion, the
    proposal (:class:`~estcal.design.sequential.NextPose`), the test poses and, with ``accuracy_map``,
    the predicted position-error maps before and after measuring the pose."""

    robot: object
    model: object
    state: object
    criterion: str
    next: object
    q_test: np.ndarray | None
    maps: tuple | None = None
    measure: str = "position"

    def to_dict(self) -> dict:
        """The JSON of ``estcal next-pose --json`` (SI, the unit in every key name)."""
        out = {"robot": self.robot.name, "measure": self.measure, "criterion": self.criterion,
               "next": self.next.to_dict(), "test_poses_rad": None if self.q_test is None else self.q_test.tolist()}
        if self.maps is not None:
            out["accuracy_map"] = {"before": self.maps[0].to_dict(), "after": self.maps[1].to_dict()}
        return out


def next_pose(robot, state, *, criterion: str | None = None, measure: str = "position", test_poses=None,
              candidates=None, degrees: bool = False, n_candidates: int = 2000, sigma_mm: float = 0.1,
              sigma_rot_mrad: float = 1.0, refine: bool = True, seed: int = 0, accuracy_map: int = 0) -> NextPoseRun:
    """The pose that most reduces ``criterion`` of the state's covariance — ``estcal next-pose``.

    ``state``: a JSON file with ``parameters``, ``estimate`` and ``covariance`` (or a
    ``CalibrationResult`` JSON, or an online checkpoint); ``accuracy_map``: poses of the
    before/after predicted-error maps (0 = none). A state computed for another robot is warned about.
    """
    import warnings

    from estcal.base.errors import EstcalWarning
    from estcal.design.criteria import CRITERIA, normalise_criterion
    from estcal.design.model import DesignModel, resolve_robot
    from estcal.design.plans import load_candidates
    from estcal.design.sequential import CalibrationState, propose_next_pose

    measure = _check_measure(measure)
    with input_errors():
        rb = resolve_robot(robot)
        st = CalibrationState.from_json(state)
        st.check_robot(rb, str(state))
        if st.robot is not None and st.robot not in (robot, rb.name):
            warnings.warn(f"{state}: the state was computed for robot {st.robot!r}, not {robot!r} — its covariance "
                          f"describes that robot's parameters", EstcalWarning, stacklevel=2)
        q_test = parse_poses(test_poses, rb)
        crit = normalise_criterion(criterion or ("test-pose" if q_test is not None else "D"))
        if q_test is None and CRITERIA[crit][1]:
            q_test = default_test_pose(rb)
        model = DesignModel(rb, measure, list(st.parameters), sigma=sigma_mm * 1e-3,
                            sigma_rot=sigma_rot_mrad * 1e-3 if measure == "pose" else None)
        cand = None if candidates is None else load_candidates(candidates, rb, degrees)
        nxt = propose_next_pose(model, st, crit, q_test=q_test, candidates=cand, n_candidates=n_candidates, rng=seed,
                                refine=refine)
    run = NextPoseRun(rb, model, st, crit, nxt, q_test, measure=measure)
    if accuracy_map > 0:
        from estcal.design.sequential import covariance_after, model_for_state

        mdl = model_for_state(model, st)
        after = covariance_after(mdl, st, nxt.readings)
        run.maps = (mdl.accuracy_map(st.covariance, n=accuracy_map, rng=seed + 2),
                    mdl.accuracy_map(after, n=accuracy_map, rng=seed + 2))  # same poses: same seed
    return run
