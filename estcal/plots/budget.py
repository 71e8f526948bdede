"""Figure of the error budget (docs/discrepancy.md): the error at new postures, stage by stage."""
from __future__ import annotations

from . import new_figure

__all__ = ["budget_figure"]


def budget_figure(budget: dict, title: str = "error at new postures (cross-validation)"):
    """Bars of ``nominal_mm`` (registration only), ``geometry_mm`` and ``model_mm`` (the diagnosis's model,
    nested CV) — and the time-blocked figure when there is one — of a budget dict
    (:meth:`estcal.discrepancy.budget.Budget.to_dict`), with ``expected_mm`` and the repeatability floor as
    horizontal lines. Returns the Figure."""
    fig = new_figure(5.0, 3.0)
    ax = fig.add_subplot(111)
    labels = ["registration", "+ geometry", "model"]
    vals = [budget["nominal_mm"], budget["geometry_mm"], budget["model_mm"]]
    if budget.get("time"):
        labels.append("model, time-blocked")
        vals.append(budget["time"]["model_mm"])
    bars = ax.bar(labels, vals, color=["#b0b0b0", "#4c72b0", "#55a868", "#c44e52"][: len(vals)])
    for b, v in zip(bars, vals):
        b.set_gid(f"bar:{v:.6g}")
        ax.text(b.get_x() + b.get_width() / 2, v, f"{v:.2f}", ha="center", va="bottom", fontsize=7)
    ax.axhline(budget["expected_mm"], ls="--", c="k", lw=1,
               label=f"expected at new postures {budget['expected_mm']:.2f}", gid="predicted")
    if budget.get("repeatability_mm") is not None:
        ax.axhline(budget["repeatability_mm"], ls=":", c="#8172b2", lw=1.2,
                   label=f"repeatability floor {budget['repeatability_mm']:.2f}", gid="repeatability")
    ax.set_ylabel("RMSE (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=9)
    return fig
