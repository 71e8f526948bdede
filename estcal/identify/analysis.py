"""Identifiability of a robot for a measurement method (GECARO App. III): :func:`identify`.

The analysis from random admissible configurations of a method (via :mod:`estcal.methods.generate`)
or from a dataset (with the excitation check: same identifiable set as random configurations, and
the condition number). The priority rules are :mod:`estcal.identify.priorities`; the identifiable
set itself is :func:`estcal.identify.select.identifiable` (the GECARO analysis of a matrix, through
the one entry :func:`estcal.identify.select.select_identifiable`).
"""
from __future__ import annotations

import numpy as np

from estcal.io.savedmodel import design_values
from estcal.methods import Problem, get_method
from estcal.methods.base import METHODS, Method, method_for_dataset
from estcal.methods.generate import generate
from estcal.methods.reduced import use_chunks

from .priorities import scan_priorities
from .select import IdentifiabilityResult, expand_patterns, identifiable, observation_matrix, reduced_observation_matrix

__all__ = ["identify"]


def _make_problem(robot, method, data, method_options):
    if method is None:
        m = method_for_dataset(data, robot)
    elif isinstance(method, Method):
        m = method
    else:
        m = get_method(method, **(method_options or {}))
    return Problem(robot, [(m, data)]), m


def _rows_per_config(method: str) -> float:
    return {"position": 3, "location": 6, "pose": 6, "point-link": 1.5, "frame-link": 3,
            "distance": 0.5}.get(method, 1.0)


def identify(robot, method: str | None = "position", data=None, n_poses: int = 60, seed: int = 0,
             priorities=None, rules: str = "gecaro", candidates=None, pivoting: bool = False,
             tol_factor: float = 1.0, method_options: dict | None = None, check_excitation: bool = True,
             generator_options: dict | None = None, tau_floor: float = 1e-10) -> IdentifiabilityResult:
    """Identifiable parameters of ``robot`` for ``method``.

    Parameters
    ----------
    robot : SerialRobot
    method : one of the nine GECARO names (``position``, ``location``, ``point-link``,
        ``frame-link``, ``plane-known``, ``plane-unknown``, ``plane-normal-known``,
        ``plane-normal-unknown``, ``distance``) or a Method; None infers it from ``data``.
    data : Dataset, optional. Given: W is built from its configurations at the nominal
        parameters, and (``check_excitation``) compared with random configurations.
        Otherwise ``n_poses`` random admissible configurations (``seed``) are generated;
        the number is raised until W has at least twice as many rows as columns.
    priorities : ``{name/pattern: int}`` overrides (0 = do not identify), an array, or
        ``{"__matrix__": M}`` (GECARO matrix, see :func:`priorities_from_matrix`).
    rules : ``"gecaro"`` default rules (module docstring) or ``"order"`` (all equal: the
        parameter-vector order decides; method unknowns first).
    candidates : names/patterns of the parameters to analyse (default: the robot's free
        parameters plus the method's unknowns); others are reported as excluded.
    pivoting, tol_factor, tau_floor : see :func:`estcal.identify.core.identifiable`.
    method_options : keyword arguments of the method (e.g. ``{"plane": (a, b, c)}``).
    generator_options : keyword arguments of the generator (:func:`estcal.methods.generate.generate`).
    """
    mname = method if isinstance(method, str) else getattr(method, "name", None)
    if isinstance(method, str):
        if method not in METHODS:
            raise ValueError(f"unknown measurement method {method!r}; available: {sorted(METHODS)}")
    meta = {"robot": robot.name, "method": mname}
    notes = []
    dv = design_values(robot)
    if dv is not None:  # a saved model: the structure of its design, not of its calibrated geometry
        robot = robot.with_values(dv)
        notes.append(f"a saved model: analysed at the design geometry of {robot.meta['calibration']['robot']!r} "
                     f"(joint model at design values, markers and effects as estimated)")
    if data is None:
        if mname is None:
            raise ValueError("give a method name or a dataset")
        n = int(n_poses)
        while True:
            ds = generate(robot, mname, n, rng=seed, **(generator_options or {}))
            problem, m = _make_problem(robot, method, ds, method_options)
            names = _candidates(problem, robot, candidates)
            W, names = observation_matrix(problem, names)
            if W.shape[0] >= 2 * len(names) or n > 100000:
                break
            n = int(np.ceil(2 * len(names) / _rows_per_config(mname) * 1.1)) + 2
            n = max(n, 2 * int(n_poses))
        if n != n_poses:
            notes.append(f"n_poses raised from {n_poses} to {n} so that W has ≥ 2× as many rows as parameters")
        meta.update({"source": "random admissible configurations", "seed": int(seed), "n_poses": int(n)})
    else:
        problem, m = _make_problem(robot, method, data, method_options)
        mname = m.name
        meta["method"] = mname
        names = _candidates(problem, robot, candidates)
        n_rows = None

        ck = use_chunks(problem)  # large per-pose data: the R factor (same analysis, bounded memory)
        if ck is not None:
            W, names, n_rows = reduced_observation_matrix(problem, names, chunk=ck)
        else:
            W, names = observation_matrix(problem, names)
        n_distinct = int(np.unique(np.asarray(data.readings), axis=0).shape[0]) if data.n else 0
        meta.update({"source": data.where, "n_poses": int(data.n), "n_distinct": n_distinct})
    prio = scan_priorities(problem, names, priorities, rules)
    res = identifiable(W, names, prio, pivoting=pivoting, tol_factor=tol_factor, tau_floor=tau_floor, meta=meta,
                       n_rows=None if data is None else n_rows)
    res.meta["rules"] = rules
    if notes:
        res.meta["notes"] = notes
    if data is not None and check_excitation and mname is not None:
        # the reference needs generic poses, not as many as the data: capped so that a large
        # dataset is not doubled by a random one (the column-scaled condition number of random
        # poses hardly depends on their number once W has many more rows than columns)
        ref = identify(robot, mname, None, max(int(n_poses), min(data.n, 5000)), seed, priorities, rules,
                       candidates,
                       pivoting, tol_factor, method_options, check_excitation=False,
                       generator_options=generator_options, tau_floor=tau_floor)
        a, b = set(res.identifiable), set(ref.identifiable)
        res.excitation = {"same_set": a == b, "missing": sorted(b - a, key=names.index),
                          "extra": sorted(a - b, key=names.index),
                          "condition_number": res.condition_number,
                          "random_condition_number": ref.condition_number}
    return res


def _candidates(problem, robot, candidates) -> list[str]:
    pv = problem.params
    if candidates is None:
        base = set(robot.params.free_names) | {n for n in pv.names if n not in robot.params}
        return [n for n in pv.names if n in base]
    names = expand_patterns(pv.names, candidates)
    extra = [n for n in pv.names if n not in robot.params and n not in names]
    return [n for n in pv.names if n in set(names) | set(extra)]
