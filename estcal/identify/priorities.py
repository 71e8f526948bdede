"""GECARO's priorities (§1.5): which of dependent parameters is kept.

* :func:`gecaro_priorities` — GECARO's default priority rules for estcal names (table below).
* :func:`priorities_from_matrix` — GECARO's (n+2)×6 priority matrix (α, d, θ, r, β, K per frame).
* :func:`load_priorities` — a priority file (YAML).
* :func:`scan_priorities` — the priority of each analysed column of a Problem (rules + overrides).
* :func:`gecaro_table2_priorities` — restrict a Khalil robot to GECARO's Table 2 parameter list.

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

from estcal.base.textinput import read_yaml

from .core import resolve_priorities

__all__ = ["gecaro_priorities", "priorities_from_matrix", "load_priorities", "scan_priorities",
           "gecaro_table2_priorities"]


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


def scan_priorities(problem, names, priorities=None, rules: str = "gecaro") -> np.ndarray:
    """Priority of each of ``names`` (parameters of ``problem``): GECARO's rules (``"gecaro"``) or the
    parameter-vector order with the method's unknowns first (``"order"``), overridden by
    ``priorities`` (``{name or pattern: int}``, an array aligned with ``names``, or
    ``{"__matrix__": M}``, :func:`priorities_from_matrix`)."""
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
