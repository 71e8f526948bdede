"""Figures of estcal's results, one module per concern.

Every function takes plain data (arrays in the display units the tables use —
mm, mrad, degrees — or result objects) and *returns* a
:class:`matplotlib.figure.Figure` built without :mod:`matplotlib.pyplot`: no
backend is chosen or switched (a notebook keeps its own), and nothing is
written. The CLI's ``--report DIR`` (:mod:`estcal.report`) saves them; in a
notebook, display the returned figure.

* :mod:`.errors` — per-pose error before/after, residual vs each joint;
* :mod:`.parameters` — estimates with ±2σ bars, correlation heat map;
* :mod:`.design` — predicted position error over the workspace, random-plan baseline;
* :mod:`.online` — row-by-row estimate ± σ and innovation tests;
* :mod:`.posterior` — MCMC corner plot (``corner`` package);
* :mod:`.diagnose` — partial joint residuals, residual norm, harmonic spectrum.
"""
from __future__ import annotations

__all__ = ["new_figure", "Figure"]


def __getattr__(name):
    # matplotlib is imported when a figure is drawn, not when a module that can draw one is imported
    # (0.3 s of CPU: a diagnosis or a calibration without --report never needs it)
    if name == "Figure":
        from matplotlib.figure import Figure

        return Figure
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def new_figure(width: float, height: float, **kwargs) -> "Figure":
    """A pyplot-free figure (``constrained`` layout unless told otherwise)."""
    from matplotlib.figure import Figure

    kwargs.setdefault("layout", "constrained")
    return Figure(figsize=(width, height), **kwargs)


def grid_shape(n: int, max_cols: int = 4) -> tuple[int, int]:
    """(rows, cols) of a panel grid for ``n`` panels."""
    cols = max(1, min(max_cols, n))
    return int(-(-n // cols)), cols


def joint_panels(n: int, width: float, height: float, max_cols: int = 4):
    """A figure with one panel per joint (``n`` panels, ``max_cols`` per row, spare panels
    hidden); returns ``(fig, axes)`` with ``len(axes) == n``."""
    rows, cols = grid_shape(n, max_cols)
    fig = new_figure(width * cols, height * rows)
    axs = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axs[n:]:
        ax.axis("off")
    return fig, list(axs[:n])
