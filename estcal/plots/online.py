"""Row-by-row history of a recursive (Kalman) calibration with its innovation tests."""
from __future__ import annotations

import numpy as np

from . import grid_shape, new_figure

__all__ = ["online_history_figure", "nis_bounds"]


def nis_bounds(dims, level: float = 0.95):
    """Two-sided χ²(m_k) bounds of each row's NIS at ``level``."""
    from scipy import stats

    dims = np.asarray(dims, int)
    a = (1 - level) / 2
    return stats.chi2.ppf(a, dims), stats.chi2.ppf(1 - a, dims)


def online_history_figure(rows, change, std, names, units, nis, dims, burn_in: int = 0, verdict: str = "",
                          max_params: int = 12):
    """Estimate − initial value ± σ against the row number (one panel per parameter, at most
    ``max_params``) and the NIS of every row against its two-sided 95 % χ² bounds.

    Parameters
    ----------
    rows : (T,) row numbers (1-based step count).
    change, std : (T, p) estimate − initial value and std after each row, display units.
    units : (p,) display unit per parameter.
    nis, dims : (T,) normalised innovation squared of each row and its dimension.
    burn_in : rows left out of the tests (dashed line).
    verdict : the tests' one-line verdict (panel title).

    Rows after the burn-in whose NIS is outside the bounds are circled in red (``gid='nis_outside'``);
    the estimate lines carry ``gid = name``.
    """
    rows = np.asarray(rows)
    change = np.asarray(change, float)
    std = np.asarray(std, float)
    p = min(len(names), max_params)
    nr, nc = grid_shape(p + 1, 3)
    fig = new_figure(3.6 * nc, 2.4 * nr)
    axs = fig.subplots(nr, nc, squeeze=False)
    for i in range(nr * nc):
        ax = axs[i // nc][i % nc]
        if i < p:
            ax.fill_between(rows, change[:, i] - std[:, i], change[:, i] + std[:, i], color="C0", alpha=0.25,
                            lw=0)
            ax.plot(rows, change[:, i], color="C0", lw=1, gid=names[i])
            ax.axhline(0, color="k", lw=0.4)
            if burn_in:
                ax.axvline(burn_in, color="0.5", ls="--", lw=0.8)
            ax.set_title(f"{names[i]} ({units[i] or '—'})", fontsize=8)
            ax.tick_params(labelsize=6)
            # scale to the rows after the burn-in: the wide prior would flatten everything else
            tail = slice(min(max(burn_in, len(rows) // 4), max(len(rows) - 1, 0)), None)
            lim = np.nanmax(np.abs(change[tail, i]) + std[tail, i]) if len(rows) else 1.0
            if np.isfinite(lim) and lim > 0:
                ax.set_ylim(-1.5 * lim, 1.5 * lim)
        elif i == p:
            nis = np.asarray(nis, float)
            lo, hi = nis_bounds(dims)
            out = ((nis < lo) | (nis > hi)) & (rows > burn_in)  # the tests leave the burn-in out
            ax.plot(rows, nis, ".", ms=3, color="C0", gid="nis")
            ax.plot(rows, hi, color="k", lw=0.6)
            ax.plot(rows, lo, color="k", lw=0.6)
            ax.plot(rows[out], nis[out], "o", ms=4, mfc="none", color="r", gid="nis_outside",
                    label=f"{int(out.sum())} rows after burn-in outside 95 %")
            if burn_in:
                ax.axvline(burn_in, color="0.5", ls="--", lw=0.8, label="burn-in")
            ax.set_yscale("log")
            ax.set_title("NIS per row, χ² 95 % bounds", fontsize=8)
            ax.legend(fontsize=6)
            ax.tick_params(labelsize=6)
        else:
            ax.axis("off")
        if i // nc == nr - 1 or i + nc >= p + 1:
            ax.set_xlabel("row", fontsize=7)
    title = "online calibration: estimate − initial ± σ after each row"
    if len(names) > p:
        title += f" (first {p} of {len(names)} parameters)"
    if verdict:
        title += "\n" + verdict
    fig.suptitle(title, fontsize=9)
    return fig
