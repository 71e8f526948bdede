"""Do the robot's kinematics explain the data at all? (``estcal check``, ``estcal frames``, the data
screening of the fitting commands)

A calibration corrects millimetres: once the unknown frames are registered — the base (where the
instrument stands) and the markers on the last link (point data) or the tool frame (pose data) —
the nominal model of the right robot leaves a residual of millimetres to centimetres, against
measured positions that spread over tens of centimetres. Random numbers under a joint/position
header, a file of another robot, or positions that do not follow the joint columns leave a
residual of the order of the positions' own spread: no kinematic fit can mend that, and a fit
would only report a huge σ0 — or converge on nonsense.

The figure is ``ratio = RMSE / spread``: the RMS residual after the registration
(:func:`estcal.intake.registration.register_points` / :func:`~estcal.intake.registration.register_pose`,
the nominal geometry) over the RMS distance of the measured points from their mean. Real files
give 0.01–0.02 (TIAGo 5.6 mm over 0.3 m; UR10 3.5 mm); unrelated data give 0.7–1. Above
:data:`UNEXPLAINED_RATIO` the data are said to be unexplained. At most :data:`SAMPLE_POSES` evenly
spaced poses are used (the figure is a ratio of two RMS values: a sample estimates it to a few per cent).
"""
from __future__ import annotations

import numpy as np

__all__ = ["explained", "unexplained_message", "UNEXPLAINED_RATIO", "SAMPLE_POSES"]

#: residual over spread above which no geometry of this robot explains the data
UNEXPLAINED_RATIO = 0.5
SAMPLE_POSES = 5000


def spread(points) -> float:
    """RMS distance (m) of measured points (N, k, 3) or positions (N, 3) from their mean (per point)."""
    P = np.asarray(points, float)
    P = P[:, None, :] if P.ndim == 2 else P
    return float(np.sqrt(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=-1))))


def explained(robot, ds, max_poses: int = SAMPLE_POSES) -> dict | None:
    """``{"rmse_m", "spread_m", "ratio", "poses", "of"}`` of ``ds`` under ``robot``'s nominal geometry
    (module docstring), or None when the data hold no positions (encoder-only or link data) or too
    few poses to register."""
    from estcal.kinematics.chunked import tool_poses

    from .registration import register_points, register_pose

    if ds.kind not in ("position", "points", "pose") or ds.n < 4:
        return None
    take = np.unique(np.linspace(0, ds.n - 1, min(ds.n, max_poses)).astype(int))
    sub = ds.subset(take)
    try:
        F = tool_poses(robot, sub.readings, context=sub.context, fields=("R", "p"))
    except (ValueError, KeyError, TypeError):  # effects needing context the file lacks: no figure
        return None
    if ds.kind == "pose":
        reg = register_pose(F["R"], F["p"], sub.R, sub.p)
        meas = sub.p
    else:
        reg = register_points(F["R"], F["p"], sub.points)
        meas = sub.points
    s = spread(meas)
    rmse = reg.rmse_mm / 1e3
    return {"rmse_m": rmse, "spread_m": s, "ratio": rmse / s if s > 0 else float("inf"), "poses": int(take.size),
            "of": int(ds.n)}


def unexplained_message(fig: dict, head: str) -> str:
    """``head`` (``"no candidate frame of arm.urdf explains these data"``) followed by the figure."""
    on = f" (on {fig['poses']:,} evenly spaced of {fig['of']:,} rows)" if fig["poses"] < fig["of"] else ""
    return (f"{head}: after registering the unknown frames, {1e3 * fig['rmse_m']:.0f} mm RMS "
            f"is left, {fig['ratio']:.0%} of the measured positions' own spread ({1e3 * fig['spread_m']:.0f} mm RMS "
            f"about their mean){on}, where a correct file leaves millimetres — random or unrelated numbers, "
            f"positions that do not follow the joint columns, another robot, or the wrong columns")
