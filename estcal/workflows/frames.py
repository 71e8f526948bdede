"""``estcal frames``: which (root, tip) links of a URDF the data measure (:mod:`estcal.intake.frames`)."""
from __future__ import annotations

import warnings

from estcal.base.errors import EstcalWarning

__all__ = ["frames_file", "format_frames"]


def frames_file(data, urdf, *, column_map=None, points=None) -> dict:
    """Candidates of :func:`estcal.intake.frames.find_frames`, best first (a dict, JSON-ready)."""
    from pathlib import Path

    from estcal.intake.frames import find_frames
    from estcal.io.robotfile import RobotFileError

    if not str(urdf).lower().endswith(".urdf"):
        raise RobotFileError(f"{urdf}: estcal frames needs a URDF (its tree of links is searched)")
    out = find_frames(Path(urdf), Path(data), column_map, points)
    for note in out["notes"]:  # columns left unused: never in silence
        warnings.warn(f"{data}: {note}", EstcalWarning, stacklevel=2)
    return out


def format_frames(out: dict, most: int = 10) -> str:
    """A table of the best candidates."""
    from estcal.intake.explained import unexplained_message

    c = out["candidates"]
    pose = out["kind"] == "pose"
    sampled = (f" (ranked on an evenly spaced sample of {out['sampled']:,} rows)" if out.get("sampled") else "")
    head = (f"{out['n_poses']} {out['kind']} rows{sampled}, joints {', '.join(out['joints'])}; roots equivalent "
            f"under the base registration: {', '.join(out['roots'])}")
    ex = out.get("explained")
    rows = [] if ex is None or ex["explains"] else [
        unexplained_message(ex, "no candidate frame explains these data") + " — the ranking below means nothing"]
    rows += [head, f"{'rank':>4}  {'root':<16} {'tip':<32} {'RMSE mm':>8} " +
            (f"{'mrad':>8} {'tool mm':>8} {'tool mrad':>9}" if pose else f"{'markers mm':>10}")]
    for i, r in enumerate(c[:most]):
        line = f"{i + 1:>4}  {r['root']:<16} {r['tip']:<32} {r['rmse_mm']:8.2f} "
        line += (f"{r['rmse_mrad']:8.2f} {r['tool_mm']:8.1f} {r['tool_mrad']:9.1f}" if pose else
                 f"{r['marker_mm']:10.1f}")
        rows.append(line)
    if len(c) > most:
        rows.append(f"… {len(c) - most} more candidates in the JSON")
    if pose:
        rows.append(f"with the tool frame registered too, every tip leaves {c[0]['registered_rmse_mm']:.2f} mm / "
                    f"{c[0]['registered_rmse_mrad']:.2f} mrad; 'tool' is the correction each tip would need")
    else:
        rows.append("point data: the markers are registered in each tip's frame, so every tip leaves the same RMSE; "
                    "tips are ordered by the markers' distance from their origin")
    return "\n".join(rows)
