"""Figures of ``estcal diagnose``: partial joint residuals, residual norm, harmonic spectrum."""
from __future__ import annotations

import numpy as np

from . import joint_panels, new_figure

__all__ = ["partial_residuals_figure", "residual_norm_figure", "spectrum_figure"]


def partial_residuals_figure(x, dq, joint_names, xlabel: str, title: str):
    """δq̂_j (mrad for revolute, mm for prismatic joints; ``dq`` in rad / m) against ``x[:, j]``,
    one panel per joint."""
    x = np.asarray(x, float)
    dq = np.asarray(dq, float)
    fig, axes = joint_panels(len(joint_names), 3.2, 2.6)
    for j, ax in enumerate(axes):
        ax.plot(x[:, j], dq[:, j] * 1e3, ".", ms=4, gid=joint_names[j])
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(joint_names[j], fontsize=8)
        ax.set_xlabel(xlabel, fontsize=7)
        ax.set_ylabel("δq̂ (mrad | mm)", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=9)
    return fig


def residual_norm_figure(xs, pose_rms_mm, title: str):
    """Per-pose RMS error (mm) against each ``(label, x)`` of ``xs`` (time, tool x/y/z …)."""
    fig = new_figure(3.2 * len(xs), 2.8)
    axs = fig.subplots(1, len(xs), squeeze=False)[0]
    for ax, (lab, x) in zip(axs, xs):
        ax.plot(x, pose_rms_mm, ".", ms=4)
        ax.set_xlabel(lab, fontsize=7)
        ax.set_ylabel("pose RMS error (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=9)
    return fig


def spectrum_figure(spectrum: dict, title: str):
    """Amplitudes (mrad) of the harmonics of the partial joint residuals, grouped by joint.

    ``spectrum``: {joint: {"orders": [k…], "amplitude_rad": [a…]}} (the diagnosis's ``analysis``)."""
    names = list(spectrum)
    orders = spectrum[names[0]]["orders"]
    fig = new_figure(max(4.0, 0.9 * len(names) + 2), 2.8)
    ax = fig.subplots()
    wbar = 0.8 / len(orders)
    for i, k in enumerate(orders):
        ax.bar(np.arange(len(names)) + i * wbar, [spectrum[nm]["amplitude_rad"][i] * 1e3 for nm in names],
               wbar, label=f"k={k}")
    ax.set_xticks(np.arange(len(names)) + 0.4 - wbar / 2, names, rotation=30, fontsize=6)
    ax.set_ylabel("amplitude (mrad)", fontsize=7)
    ax.legend(fontsize=6)
    ax.set_title(title, fontsize=9)
    return fig
