"""Identifiability of a robot for a measurement method: priorities, observation matrix, analysis.

* :func:`gecaro_priorities` — GECARO's default priority rules (§1.5) for estcal names.
* :func:`priorities_from_matrix` — GECARO's (n+2)×6 priority matrix (α, d, θ, r, β, K per frame).
* :func:`observation_matrix` — weighted ``W`` (rows ``H/σ``) of a :class:`Problem`.
* :func:`identify` — analysis from random admissible configurations of a method
  (via :mod:`estcal.methods.generate`) or from a dataset (with the excitation
  check: same identifiable set as random configurations, and the condition number).
* :func:`select_identifiable` — an identifiable free set for a Problem (for estimators).

Default precedence of GECARO's rules (the paper does not give one; first match wins,
in the order listed by the paper, plus two estcal-specific rules):

====  ==================================================================  =========
rule  parameters                                                          priority
====  ==================================================================  =========
0     unknowns added by the method (plane coefficients, normal angles)    6
1     joint offsets and transmission gains (and the joint-variable         5
      parameter of each joint, e.g. Khalil θ_j of a revolute joint, which
      *is* GECARO's joint offset)
2     lengths ``r_j, d_j`` (DH: ``d_j, a_j``) with non-zero nominal value   4
3     angles ``α_j, θ_j`` with nominal value not a multiple of π/2          3
4     base and tool frames (``base_*``, ``tool_*``, constant frames such    2
      as Khalil frames 0 and n+1) and marker coordinates
5     everything else                                                     1
====  ==================================================================  =========

Rule 0 ranks the method's own unknowns first because they must be estimated
whatever happens (GECARO counts only robot parameters in Table 2; giving them
top priority is what makes e.g. θ0, r0 "n" in its unknown-plane column).
Within one priority the parameter-vector order decides (stable sort).
"""
from __future__ import annotations

import fnmatch
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .core import IdentifiabilityResult, identifiable, resolve_priorities
from ..kinematics.parameters import summarize_names, unknown_name_message

__all__ = ["gecaro_priorities", "priorities_from_matrix", "load_priorities", "observation_matrix", "identify",
           "select_identifiable", "expand_patterns", "gecaro_table2_priorities"]


def _is_multiple_of_half_pi(v: float, tol: float = 1e-9) -> bool:
    k = v / (np.pi / 2)
    return abs(k - round(k)) < tol


def gecaro_priorities(robot, names: Sequence[str] | None = None) -> dict:
    """GECARO default priorities (table in the module docstring) for every parameter of ``robot``.

    ``robot`` may be a :class:`SerialRobot` or a :class:`Problem` (whose extra
    method unknowns then get rule 0).
    """
    if hasattr(robot, "terms"):  # a Problem: its robot carries the method unknowns (kind "other")
        robot = robot.robot
    pv = robot.params
    constant = {lk.label for lk in robot.links if lk.joint is None}
    jvar = {pv.names[lk.joint_param] for lk in robot.links if lk.joint is not None and lk.joint_param >= 0}
    out = {}
    for name, val, kind, frame in zip(pv.names, pv.values, pv.kinds, pv.frames):
        stem = name.rsplit("_", 1)[0] if "_" in name else name
        if kind == "other" and not name.startswith(("base_", "tool_")):
            p = 6  # rule 0: method unknowns (Problem extends with kind "other")
        elif kind in ("offset", "gain") or name in jvar:
            p = 5
        elif kind == "geometric" and stem in ("r", "d", "a") and abs(val) > 1e-12:
            p = 4
        elif kind == "geometric" and stem in ("alpha", "theta") and not _is_multiple_of_half_pi(val):
            p = 3
        elif kind in ("base", "tool", "marker") or (kind == "geometric" and frame in constant):
            p = 2
        else:
            p = 1
        out[name] = p
    if names is not None:
        return {n: out[n] for n in names}
    return out


def priorities_from_matrix(robot, matrix) -> dict:
    """GECARO's priority matrix → ``{name: priority}`` for a Khalil robot.

    ``matrix`` has one row per Khalil frame (frames in chain order, i.e. 0 … n+1, base
    and tool 6-parameter frames excluded) and the 6 columns α, d, θ, r, β, K
    (K is ignored on constant frames). Parameters not covered (``base_*``,
    ``tool_*``, offsets, markers) are not in the result (callers decide).
    """
    M = np.asarray(matrix, int)
    frames = [lk for lk in robot.links if lk.label not in ("base", "tool")]
    if M.shape != (len(frames), 6):
        raise ValueError(f"priority matrix must be {len(frames)}×6 (frames {[f.label for f in frames]} × "
                         f"α, d, θ, r, β, K), got {M.shape}")
    out = {}
    for row, lk in zip(M, frames):
        for col, stem in enumerate(("alpha", "d", "theta", "r", "beta")):
            name = f"{stem}_{lk.label}"
            if name in robot.params:
                out[name] = int(row[col])
        if lk.joint is not None:
            out[f"gain_{lk.label}"] = int(row[5])
    return out


def load_priorities(path) -> dict:
    """Read a priority file (YAML): a mapping ``{name or pattern: priority}``, or
    ``{matrix: [[α, d, θ, r, β, K], …]}`` (returned as ``{"__matrix__": array}``)."""
    from estcal.base.textinput import read_yaml

    path = Path(path)
    d = read_yaml(path, "priority", ValueError)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: expected a mapping {{parameter or pattern: priority}} or {{matrix: [...]}}")
    if "matrix" in d:
        return {"__matrix__": np.asarray(d["matrix"], int)}
    bad = {k: v for k, v in d.items() if not isinstance(v, int) or v < 0}
    if bad:
        raise ValueError(f"{path}: priorities must be integers ≥ 0; got {bad}")
    return {str(k): int(v) for k, v in d.items()}


def expand_patterns(names: Sequence[str], patterns) -> list[str]:
    """Names matching any of ``patterns`` (fnmatch; a comma-separated string is split), in ``names`` order.

    A wildcard pattern may match nothing (so one candidate list serves Khalil, DH and URDF
    robots); an explicit name that does not exist, or a list matching nothing, is an error.
    """
    if isinstance(patterns, str):
        patterns = [p.strip() for p in patterns.split(",") if p.strip()]
    out = []
    for p in patterns:
        hit = [n for n in names if fnmatch.fnmatchcase(n, p)]
        if not hit and not any(ch in p for ch in "*?["):
            raise ValueError(unknown_name_message(p, names))
        out += hit
    if not out:
        raise ValueError(f"patterns {list(patterns)} match no parameter. This model has {len(names)} parameters: "
                         f"{summarize_names(names)}")
    keep = set(out)
    return [n for n in names if n in keep]


def reduced_observation_matrix(problem, names: Sequence[str] | None = None, theta=None,
                               chunk: int | None = None):
    """``(R, names, n_rows)``: the triangular factor of ``W`` (``W = Q R``) built ``chunk`` poses at a
    time (R ← qr([R; W_chunk])), so that memory stays O(chunk · P) whatever the number of poses.

    Every quantity :func:`estcal.identify.core.identifiable` computes — column norms, the
    sequential QR's ``|R_jj|``, regrouping coefficients, singular values — is invariant under
    ``W → QᵀW``, so the analysis of R is that of W (tested to 1e-10 in
    ``tests/test_memory.py``). Single-term problems with a splittable dataset only; the factor
    is the leading block of :func:`estcal.estimate.reduced.reduce_system`'s (QR of ``[W b]``)."""
    from estcal.estimate.reduced import CHUNK_POSES, reduce_system

    names = list(problem.params.free_names if names is None else names)
    R, _, _, m = reduce_system(problem, theta, problem.params.indices(names), chunk or CHUNK_POSES)
    return R, names, m


def observation_matrix(problem, names: Sequence[str] | None = None, theta=None):
    """Weighted observation matrix ``W = H/σ`` (rows of all terms) and its column names."""
    rows = problem.evaluate(theta)
    pv = problem.params
    names = list(pv.free_names if names is None else names)
    W = rows.H[:, pv.indices(names)] / rows.sigma[:, None]
    return W, names


def _merge_priorities(problem, names, priorities, rules: str):
    if rules == "gecaro":
        base = gecaro_priorities(problem)
    elif rules == "order":
        base = {n: 1 for n in problem.params.names}
        for n, k in zip(problem.params.names, problem.params.kinds):
            if k == "other":
                base[n] = 6  # method unknowns first (see module docstring)
    else:
        raise ValueError(f"unknown priority rules {rules!r} (gecaro or order)")
    if priorities is not None:
        if isinstance(priorities, Mapping) and "__matrix__" in priorities:
            priorities = priorities_from_matrix(problem.robot, priorities["__matrix__"])
        if isinstance(priorities, Mapping):
            for key, val in priorities.items():
                hit = [n for n in base if fnmatch.fnmatchcase(n, key)] if any(c in key for c in "*?[") else \
                    [key] if key in base else []
                if not hit:
                    raise ValueError(f"priority given for {key!r}, which matches no parameter")
                for h in hit:
                    base[h] = int(val)
        else:
            arr = resolve_priorities(names, priorities)
            base.update(dict(zip(names, arr.tolist())))
    return np.array([base[n] for n in names], int)


def _make_problem(robot, method, data, method_options):
    from estcal.methods import Problem, get_method
    from estcal.methods.base import Method, method_for_dataset

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
    from estcal.methods.generate import generate

    mname = method if isinstance(method, str) else getattr(method, "name", None)
    if isinstance(method, str):
        import estcal.methods.links  # noqa: F401  (registers the GECARO methods)
        from estcal.methods.base import METHODS

        if method not in METHODS:
            raise ValueError(f"unknown measurement method {method!r}; available: {sorted(METHODS)}")
    meta = {"robot": robot.name, "method": mname}
    notes = []
    from estcal.io.savedmodel import design_values

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
        from estcal.estimate.reduced import use_chunks

        n_rows = None

        ck = use_chunks(problem)  # large per-pose data: the R factor (same analysis, bounded memory)
        if ck is not None:
            W, names, n_rows = reduced_observation_matrix(problem, names, chunk=ck)
        else:
            W, names = observation_matrix(problem, names)
        meta.update({"source": data.where, "n_poses": int(data.n)})
    prio = _merge_priorities(problem, names, priorities, rules)
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


def select_identifiable(problem, candidates=None, priorities=None, rules: str = "gecaro",
                        tol_factor: float = 1.0, tau_floor: float = 1e-10, theta=None) -> list[str]:
    """An identifiable free set for ``problem`` (from its own data, at its current values or ``theta``).

    ``candidates``: names/patterns to consider (default: the problem's free parameters,
    e.g. ``["alpha_*", "d_*", "theta_*", "r_*", "beta_*", "offset_*", "base_*", "marker*"]``);
    the method unknowns (plane, normal) are always included. Returns names in
    parameter-vector order; use with ``Problem.with_free`` or ``calibrate_lsq(free=...)``.
    """
    if theta is None:  # a saved model: the structure of its design (estcal.io.savedmodel.design_values)
        from estcal.io.savedmodel import design_values

        dv = design_values(problem.robot)
        if dv is not None:
            th = problem.params.values.copy()
            th[problem.params.indices(problem.robot.params.names)] = dv
            problem = problem.with_values(th)
    pv = problem.params
    if candidates is None:
        names = pv.free_names
    else:
        names = expand_patterns(pv.names, candidates)
    extras = [n for n, k in zip(pv.names, pv.kinds) if k == "other" and n not in names]
    names = [n for n in pv.names if n in set(names) | set(extras)]
    from estcal.estimate.reduced import use_chunks

    ck = use_chunks(problem)
    if ck is not None:  # large data: the R factor, built chunk by chunk (same analysis, bounded memory)
        W, names, m = reduced_observation_matrix(problem, names, theta, chunk=ck)
    else:
        W, names = observation_matrix(problem, names, theta)
        m = None
    prio = _merge_priorities(problem, names, priorities, rules)
    return identifiable(W, names, prio, tol_factor=tol_factor, tau_floor=tau_floor, n_rows=m).identifiable


def gecaro_table2_priorities(robot) -> dict:
    """Priorities restricting a Khalil robot to GECARO's parameter list (Table 2).

    GECARO's standard parameters are θ0, r0, (α, d, θ, r, β) of frames 1…n+1 and the
    gains K1…Kn (2 + 5(n+1) + n). estcal's Khalil chains carry more: the 6-parameter
    ``base_*``/``tool_*`` frames, α0, d0, β0 of frame 0 (GECARO sets α0 = d0 = 0 by
    construction) and ``offset_j`` — whose column equals that of the joint variable's
    parameter (θ_j of a revolute joint, r_j of a prismatic one), which *is* GECARO's
    joint offset. Returns ``{name: 0}`` for those (not identified); the priorities of the
    GECARO list come from the rules (``rules="order"``: parameter-vector order,
    ``rules="gecaro"``: GECARO's default rules).
    """
    first = next(lk.label for lk in robot.links if lk.label not in ("base", "tool"))
    out = {}
    for n, k in zip(robot.params.names, robot.params.kinds):
        if k in ("base", "tool", "offset", "marker") or n in (f"alpha_{first}", f"d_{first}", f"beta_{first}"):
            out[n] = 0
    return out
