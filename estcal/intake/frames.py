"""Which frame of a URDF do the data measure? (``estcal frames``)

A published dataset rarely says which link its measured pose or points belong to, nor where
the instrument stands. The candidates are the chains of the URDF whose actuated joints are
exactly the data's joint columns: the data's joints must lie on one path of the tree, the
**root** is the parent link of the first of them or any link above it through fixed joints,
the **tip** the child link of the last one or any link below it through fixed joints.
Every candidate's forward kinematics is therefore one chain ``F_i`` computed once, times
constant transforms: ``T_i = D_root⁻¹ · F_i · C_tip``.

Ranking (best first) by the RMSE left after registration:

* **pose data**: the base (where the instrument stands, 6 DoF) is registered for every tip at
  once (:func:`estcal.intake.registration.register_base_pose`, one batched SVD) and the tip
  frame is taken as the URDF places it — that is the hypothesis being tested. Registering the
  tool as well would make every tip below the last joint fit equally (the tool transform
  absorbs ``C_tip``); that fit (:func:`~estcal.intake.registration.register_pose`, once per
  chain) is reported as ``registered_rmse_mm``/``_mrad`` with the tool correction each tip
  would need (``tool_mm``, ``tool_mrad``: how far the measured frame is from the candidate).
* **point data**: the base and the marker points (unknown, k × 3) are registered once per
  chain (:func:`~estcal.intake.registration.register_points`); all tips then fit equally and
  are ordered by the distance of the markers from the tip origin (``marker_mm``).

Roots differ by a fixed transform that the base registration absorbs exactly: they are
reported together (``roots``), the URDF's root-most first.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from estcal.io.robotfile import RobotFileError
from estcal.kinematics.transforms import invert_transform, so3_log
from estcal.kinematics.urdf import fixed_subtree

from .registration import register_base_pose, register_points, register_pose

__all__ = ["find_frames", "chain_candidates", "data_joints"]


def chain_candidates(urdf, joints, path="URDF"):
    """``(roots, top, last_link, tips)`` for the chain whose actuated joints are ``joints``.

    ``roots``: links above the first joint through fixed joints (root-most first, ``top``);
    ``tips``: [(link, C)] with ``C`` the fixed transform last_link → link. Raises
    :class:`RobotFileError` when the joints are not one path of the tree."""
    by_name = {j.name: j for j in urdf.robot.joints}
    parent_joint = {j.child: j for j in urdf.robot.joints}
    missing = [j for j in joints if j not in by_name]
    if missing:
        raise RobotFileError(f"{path}: the data's joint(s) {missing} are not joints of the URDF")
    fixed = [j for j in joints if by_name[j].type == "fixed"]
    if fixed:
        raise RobotFileError(f"{path}: joint(s) {fixed} are fixed in the URDF but have data columns")

    def depth(link):
        d = 0
        while link in parent_joint:
            link = parent_joint[link].parent
            d += 1
        return d

    order = sorted(joints, key=lambda n: depth(by_name[n].child))
    last = by_name[order[-1]].child
    # walk up from the last joint's child to the first joint's parent: every actuated joint met
    # must be a data joint, and every data joint must be met
    met, link = [], last
    first_parent = by_name[order[0]].parent
    while link != first_parent:
        if link not in parent_joint:
            raise RobotFileError(f"{path}: the data's joints {order} do not lie on one chain of the URDF tree "
                                 f"(no path from {first_parent!r} to {last!r})")
        j = parent_joint[link]
        if j.type != "fixed":
            if j.name not in joints and j.mimic is not None:
                raise RobotFileError(f"{path}: joint {j.name!r} lies between the data's joints and is a <mimic> of "
                                     f"{j.mimic.joint!r}: estcal reads one column per independent joint and does not "
                                     f"couple joints from a URDF — describe the chain in a robot file (coupling)")
            if j.name not in joints:
                raise RobotFileError(f"{path}: joint {j.name!r} ({j.type}) lies between the data's joints but the "
                                     f"data have no column for it")
            met.append(j.name)
        link = j.parent
    if set(met) != set(joints):
        raise RobotFileError(f"{path}: the data's joints {sorted(set(joints) - set(met))} are not on the chain "
                             f"{first_parent!r} → {last!r}")
    ups = [(first_parent, None)]
    link = first_parent
    while link in parent_joint and parent_joint[link].type == "fixed":
        link = parent_joint[link].parent
        ups.append((link, None))
    top = ups[-1][0]
    roots = [name for name, _ in ups[::-1]]
    return roots, top, last, fixed_subtree(urdf.robot.joints, last)


def data_joints(urdf, header, column_map=None) -> list[str]:
    """The URDF's actuated joints that the data have a column for (directly or through the map)."""
    present = set(header)
    mapped = dict(column_map.joints) if column_map is not None else {}
    return [j.name for j in urdf.robot.joints
            if j.type != "fixed" and j.mimic is None and mapped.get(j.name, j.name) in present]


#: rows above which the candidates are ranked on an evenly spaced sample of this many rows (the RMSEs
#: of 20,000 rows are within ~1 % of the whole file's; memory and time stay bounded on any file)
FRAMES_MAX_ROWS = 20_000


def find_frames(urdf_path, data_path, column_map=None, points: int | None = None) -> dict:
    """Rank the (root, tip) candidates of ``urdf_path`` for the data file ``data_path``.

    Returns ``{"joints": [...], "kind": …, "n_poses": N, "candidates": [{"root", "tip", "roots",
    "rmse_mm", "rmse_mrad", …}, …]}`` best first (module docstring), with ``"sampled"`` (rows ranked on,
    when fewer than the file's), ``"notes"`` (what was left unused and why) and ``"explained"`` (the
    best candidate's residual against the measured positions' spread, :mod:`estcal.intake.explained`).
    ``column_map``: path or :class:`~estcal.io.columnmap.ColumnMap`."""
    from estcal.io.columnmap import ColumnMap, load_column_map
    from estcal.io.dataset import DatasetError
    from estcal.io.stream import read_dataset
    from estcal.base.textinput import read_csv_header
    from estcal.kinematics.urdf import load_urdf, robot_from_urdf

    urdf = load_urdf(urdf_path)
    cmap = column_map if column_map is None or isinstance(column_map, ColumnMap) else load_column_map(column_map)
    file_header = read_csv_header(Path(data_path), "dataset", DatasetError)
    header = [h.strip() for h in (cmap.columns if cmap is not None and cmap.columns else file_header)]
    joints = data_joints(urdf, header, cmap)
    if not joints:
        raise DatasetError(f"{data_path}: no column is a joint of {urdf_path} (its actuated joints are "
                           f"{[j.name for j in urdf.robot.joints if j.type != 'fixed'][:20]}) — map them with "
                           f"--map (joints: {{urdf_joint: column}})")
    roots, top, last, tips = chain_candidates(urdf, joints, urdf_path)
    robot = robot_from_urdf(urdf_path, root=top, tip=last)
    ds, total = read_dataset(Path(data_path), robot, column_map=cmap, max_rows=FRAMES_MAX_ROWS, check_units=False)
    if points is not None:
        ds = ds.with_points(points)
    if ds.kind == "none":
        raise DatasetError(f"{data_path}: no measured pose or points (x,y,z, x1..zk or a pose; map them with --map)")
    mimic = _mimic_notes(urdf, header, cmap, urdf_path)
    notes = [m for _, m in mimic] + _unused_notes(ds, robot, {c for c, _ in mimic})
    from estcal.kinematics.chunked import tool_poses

    F = tool_poses(robot, ds.readings)
    F_T = np.zeros((ds.n, 4, 4))
    F_T[:, :3, :3], F_T[:, :3, 3], F_T[:, 3, 3] = F["R"], F["p"], 1.0
    # the robot's tool frame already contains the fixed joints after the last actuated one up to
    # ``last`` (robot_from_urdf merges them), so F_T is ``last`` in ``top``
    C = np.stack([c for _, c in tips])
    T = np.einsum("nij,cjk->cnik", F_T, C)  # (tips, N, 4, 4)
    out = {"joints": list(robot.joint_names), "kind": ds.kind, "n_poses": int(total), "root": top,
           "roots": list(roots), "candidates": [], "sampled": int(ds.n) if ds.n < total else None, "notes": notes}
    rows = []
    if ds.kind == "pose":
        R_B, p_B, e_pos, e_rot = register_base_pose(T[..., :3, :3], T[..., :3, 3], ds.R, ds.p)
        full = register_pose(F_T[:, :3, :3], F_T[:, :3, 3], ds.R, ds.p, tools=C)
        X = np.eye(4)
        X[:3, :3], X[:3, 3] = full.R_X, full.p_X
        tool = np.einsum("cij,jk->cik", invert_transform(C), X)  # correction each tip would need
        for c, (name, _) in enumerate(tips):
            rows.append({"tip": name, "rmse_mm": 1e3 * float(np.sqrt(np.mean(e_pos[c] ** 2))),
                         "rmse_mrad": 1e3 * float(np.sqrt(np.mean(e_rot[c] ** 2))),
                         "registered_rmse_mm": full.rmse_mm, "registered_rmse_mrad": full.rmse_mrad,
                         "tool_mm": 1e3 * float(np.linalg.norm(tool[c, :3, 3])),
                         "tool_mrad": 1e3 * float(np.linalg.norm(so3_log(tool[c, :3, :3])))})
        # keys rounded to 1 nm / 1 nrad: tips one fixed rotation apart tie to the last bits, and the tie keeps
        # the chain's order (the sort is stable) rather than the platform's rounding
        rows.sort(key=lambda r: round(float(np.hypot(r["rmse_mm"], r["rmse_mrad"])), 6))
    else:
        reg = register_points(F["R"], F["p"], ds.points)
        # markers in every tip frame: C⁻¹ · m
        Ci = invert_transform(C)
        m_tip = np.einsum("cij,kj->cki", Ci[:, :3, :3], reg.markers) + Ci[:, None, :3, 3]
        for c, (name, _) in enumerate(tips):
            rows.append({"tip": name, "rmse_mm": reg.rmse_mm, "rmse_mrad": None,
                         "marker_mm": 1e3 * float(np.mean(np.linalg.norm(m_tip[c], axis=-1)))})
        rows.sort(key=lambda r: round(r["marker_mm"], 6))
    for r in rows:
        out["candidates"].append({"root": top, **r, "roots": list(roots)})
    out["explained"] = _explained(ds, rows)
    return out


def _explained(ds, rows) -> dict:
    """The best candidate's residual (with the tool registered, for pose data) against the spread of the
    measured positions: above :data:`~estcal.intake.explained.UNEXPLAINED_RATIO`, no candidate explains
    the data."""
    from .explained import UNEXPLAINED_RATIO, spread

    best = rows[0]
    rmse = 1e-3 * (best["registered_rmse_mm"] if ds.kind == "pose" else best["rmse_mm"])
    s = spread(ds.p if ds.kind == "pose" else ds.points)
    ratio = rmse / s if s > 0 else float("inf")
    return {"rmse_m": rmse, "spread_m": s, "ratio": ratio, "poses": int(ds.n), "of": int(ds.n),
            "explains": bool(ratio <= UNEXPLAINED_RATIO)}


def _mimic_notes(urdf, header, cmap, path) -> list[tuple[str, str]]:
    """A column that is a ``<mimic>`` joint of the URDF: said what is done with it (never dropped in
    silence) — estcal reads one column per independent joint and does not couple joints from a URDF.
    ``[(column, note)]``."""
    mapped = dict(cmap.joints) if cmap is not None else {}
    present = set(header)
    out = []
    for j in urdf.robot.joints:
        col = mapped.get(j.name, j.name)
        if j.type != "fixed" and j.mimic is not None and col in present:
            m = j.mimic
            out.append((col, f"column {col!r} is joint {j.name!r}, a <mimic> of {m.joint!r} in {Path(path).name} "
                             f"(q = {m.multiplier if m.multiplier is not None else 1:g}·q_{m.joint} + "
                             f"{m.offset if m.offset is not None else 0:g}): no candidate chain goes through it and "
                             f"its column is not used (estcal reads one column per independent joint and does not "
                             f"couple joints from a URDF)"))
    return out


def _unused_notes(ds, robot, skip) -> list[str]:
    """The file columns no candidate reads (besides the mimic joints'), with the map that would read them."""
    from .hygiene import unused_columns, unused_message

    unused, foreign, suggestion = unused_columns(ds, robot)
    unused = [c for c in unused if c not in skip]
    return [unused_message(ds, robot, unused, foreign, suggestion)] if unused else []
