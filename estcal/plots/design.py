"""Predicted accuracy over the workspace and the random-plan baseline of a design."""
from __future__ import annotations

import numpy as np

from . import new_figure

__all__ = ["accuracy_map_figure", "baseline_figure"]

_VIEWS = (("x", "y", 0, 1), ("x", "z", 0, 2), ("y", "z", 1, 2))


def accuracy_map_figure(maps, marks=(), title: str = "predicted position error std over the workspace"):
    """Scatter of the nominal tool positions of sampled reachable poses, coloured by the
    predicted position-error std; three projections (x-y, x-z, y-z) per map.

    Parameters
    ----------
    maps : list of ``(label, xyz (K, 3) in mm, std (K,) in mm)``; one row of panels per map,
        all on the same colour scale (so 'before' and 'after' compare).
    marks : list of ``(label, xyz (L, 3) in mm)`` drawn on every panel (plan poses, next pose).

    The scatter collections carry ``gid = label`` of their map; their colour arrays
    are the std values.
    """
    vmax = max(float(np.max(s)) for _, _, s in maps)
    vmin = min(float(np.min(s)) for _, _, s in maps)
    fig = new_figure(11.0, 3.3 * len(maps))
    axs = fig.subplots(len(maps), 3, squeeze=False)
    sc = None
    for r, (label, xyz, std) in enumerate(maps):
        xyz = np.asarray(xyz, float)
        std = np.asarray(std, float)
        order = np.argsort(std)  # largest errors drawn on top
        for c, (a, b, i, j) in enumerate(_VIEWS):
            ax = axs[r][c]
            sc = ax.scatter(xyz[order, i], xyz[order, j], c=std[order], s=8, cmap="viridis", vmin=vmin, vmax=vmax)
            sc.set_gid(label)
            for k, (ml, mxyz) in enumerate(marks):
                mxyz = np.atleast_2d(np.asarray(mxyz, float))
                ax.plot(mxyz[:, i], mxyz[:, j], "x" if k == 0 else "*", color="r" if k == 0 else "m",
                        ms=6 if k == 0 else 12, label=ml)
            ax.set_xlabel(f"{a} (mm)", fontsize=8)
            ax.set_ylabel(f"{b} (mm)", fontsize=8)
            ax.set_aspect("equal", adjustable="datalim")
            ax.tick_params(labelsize=7)
            if c == 0:
                ax.set_title(f"{label}: mean {std.mean():.3g} mm, max {std.max():.3g} mm", fontsize=9, loc="left")
            if r == 0 and c == 2 and marks:
                ax.legend(fontsize=7)
    fig.colorbar(sc, ax=axs, shrink=0.8, label="predicted position error std (mm)")
    fig.suptitle(title, fontsize=10)
    return fig


def baseline_figure(values, plan_value: float, criterion: str, larger_is_better: bool):
    """Histogram of the criterion over random plans with the optimised plan's value marked."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    fig = new_figure(6.0, 3.0)
    ax = fig.subplots()
    logx = v.size and v.min() > 0 and plan_value > 0 and max(v.max(), plan_value) / min(v.min(), plan_value) > 100
    if logx:
        bins = np.geomspace(min(v.min(), plan_value), max(v.max(), plan_value), 40)
        ax.set_xscale("log")
    else:
        bins = 40
    ax.hist(v, bins=bins, color="0.6", label=f"{v.size} random plans")
    ax.axvline(plan_value, color="r", lw=2, label=f"optimised plan {plan_value:.4g}", gid="plan")
    ax.set_xlabel(f"criterion {criterion} ({'larger' if larger_is_better else 'smaller'} is better)")
    ax.set_ylabel("plans")
    ax.legend(fontsize=8)
    ax.set_title("optimised plan against random plans of the same size", fontsize=9)
    return fig
