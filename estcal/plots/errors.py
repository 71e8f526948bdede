"""Per-pose errors before and after calibration, and the residual against each joint.

Inputs are in display units: position errors in mm, orientation errors in mrad,
joint readings in degrees (revolute) or mm (prismatic).
"""
from __future__ import annotations

import numpy as np

from . import joint_panels, new_figure

__all__ = ["pose_error_figure", "residual_vs_joints_figure"]


def pose_error_figure(sets, quantity: str = "position", unit: str = "mm"):
    """One panel per dataset (calibration first, each validation file separately):
    error of every pose before (grey) and after (blue) calibration.

    Parameters
    ----------
    sets : list of dicts ``{"label": str, "before": (N,), "after": (N,)}``; arrays in ``unit``.
    quantity : 'position' or 'orientation' (axis label).
    """
    sets = [s for s in sets if s.get("after") is not None and len(s["after"])]
    fig = new_figure(max(5.0, 4.0 * len(sets)), 3.0)
    axs = fig.subplots(1, max(len(sets), 1), squeeze=False)[0]
    for ax, s in zip(axs, sets):
        after = np.asarray(s["after"], float)
        idx = np.arange(len(after))
        if s.get("before") is not None:
            before = np.asarray(s["before"], float)
            ax.plot(idx, before, "o", ms=3, color="0.6", label=f"before (RMSE {np.sqrt(np.mean(before ** 2)):.3g})",
                    gid="before")
        ax.plot(idx, after, "o", ms=3, color="C0", label=f"after (RMSE {np.sqrt(np.mean(after ** 2)):.3g})",
                gid="after")
        ax.set_yscale("log")
        ax.set_xlabel("pose (row of the file)")
        ax.set_ylabel(f"{quantity} error ({unit})")
        ax.set_title(s["label"], fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle(f"{quantity} error per pose, before / after calibration", fontsize=10)
    return fig


def residual_vs_joints_figure(sets, joint_names, joint_units, unit: str = "mm"):
    """Error after calibration against each joint reading, one panel per joint.

    Parameters
    ----------
    sets : list of dicts ``{"label", "readings" (N, n) in joint display units, "error" (N,) in unit}``.
    joint_units : per joint 'deg' or 'mm'.
    """
    fig, axes = joint_panels(len(joint_names), 3.0, 2.5)
    for j, ax in enumerate(axes):
        for k, s in enumerate(sets):
            ax.plot(np.asarray(s["readings"])[:, j], s["error"], "o", ms=3, color=f"C{k}", label=s["label"],
                    alpha=0.8, gid=f"set{k}")
        ax.set_title(joint_names[j], fontsize=8)
        ax.set_xlabel(f"reading ({joint_units[j]})", fontsize=7)
        ax.set_ylabel(f"error after ({unit})", fontsize=7)
        ax.tick_params(labelsize=6)
        if j == 0:
            ax.legend(fontsize=6)
    fig.suptitle("residual after calibration vs joint reading (structure = unmodelled effect)", fontsize=10)
    return fig
