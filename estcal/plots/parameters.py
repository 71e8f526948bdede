"""Parameter estimates with ±2σ bars and the correlation of their covariance."""
from __future__ import annotations

import numpy as np

from . import new_figure

__all__ = ["parameter_figure", "correlation_figure", "correlation"]


def correlation(cov) -> np.ndarray:
    """Correlation matrix of a covariance (zero-variance rows/columns give 0 off the diagonal)."""
    C = np.asarray(cov, float)
    s = np.sqrt(np.clip(np.diag(C), 0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        R = C / np.outer(s, s)
    R[~np.isfinite(R)] = 0.0
    np.fill_diagonal(R, 1.0)
    return np.clip(R, -1.0, 1.0)


def parameter_figure(names, change, std, units):
    """Change from the initial value with a ±2σ bar, one panel per display unit.

    Parameters
    ----------
    names : parameter labels.
    change, std : (p,) estimate − initial value and standard deviation, in display units.
    units : (p,) unit of each parameter ('mm', 'mrad', '' …); one panel per distinct unit.

    The bars are matplotlib ``errorbar`` containers (``ax.containers``, label = the unit)
    whose half-length is 2·std — tests read them back.
    """
    change = np.asarray(change, float)
    std = np.asarray(std, float)
    groups = list(dict.fromkeys(units))
    sizes = [sum(u == g for u in units) for g in groups]
    fig = new_figure(7.0, 1.2 + 0.22 * sum(sizes) + 0.5 * len(groups))
    axs = fig.subplots(len(groups), 1, squeeze=False, height_ratios=[s + 1 for s in sizes])[:, 0]
    for ax, g in zip(axs, groups):
        idx = [i for i, u in enumerate(units) if u == g]
        y = np.arange(len(idx))[::-1]
        ax.errorbar(change[idx], y, xerr=2 * std[idx], fmt="o", ms=3, capsize=2, color="C0",
                    label=g or "dimensionless")
        ax.axvline(0, color="k", lw=0.5)
        ax.set_yticks(y, [names[i] for i in idx], fontsize=7)
        ax.set_xlabel(f"estimate − initial ({g or 'dimensionless'}), bars ±2σ", fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
    fig.suptitle("parameter estimates (change from the initial guess) with ±2σ", fontsize=10)
    return fig


def correlation_figure(names, cov):
    """Heat map of the correlation matrix of ``cov`` (colour scale −1 … 1)."""
    R = correlation(cov)
    p = len(names)
    size = min(12.0, 2.5 + 0.28 * p)
    fig = new_figure(size + 1.0, size)
    ax = fig.subplots()
    im = ax.imshow(R, cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
    im.set_gid("correlation")
    fs = 7 if p <= 30 else 5
    ax.set_xticks(range(p), names, rotation=90, fontsize=fs)
    ax.set_yticks(range(p), names, fontsize=fs)
    fig.colorbar(im, ax=ax, shrink=0.8, label="correlation")
    off = np.abs(R - np.eye(p))
    k = np.unravel_index(np.argmax(off), off.shape) if p > 1 else (0, 0)
    ax.set_title(f"correlation of the estimates (largest |ρ| = {off.max():.3f}: {names[k[0]]} / {names[k[1]]})"
                 if p > 1 else "correlation", fontsize=9)
    return fig
