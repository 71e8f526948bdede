"""Figure of the error budget (docs/real-data.md): where the error at new postures goes."""
from __future__ import annotations

from . import new_figure

__all__ = ["budget_figure"]


def budget_figure(budget: dict, title: str = "error budget (posture-grouped CV)"):
    """Bars of ``nominal_mm``, ``geometric_mm``, ``named_mm`` and ``unstructured_mm`` (the RMSE left after the
    residual GP) of an error-budget dict (:meth:`estcal.discrepancy.budget.ErrorBudget.to_dict`), the
    repeatability floor and ``predicted_validation_mm`` as horizontal lines. Returns the Figure."""
    fig = new_figure(5.0, 3.0)
    ax = fig.add_subplot(111)
    labels = ["nominal", "geometric", "named", "after GP"]
    vals = [budget["nominal_mm"], budget["geometric_mm"], budget["named_mm"], budget["unstructured_mm"]]
    bars = ax.bar(labels, vals, color=["#b0b0b0", "#4c72b0", "#55a868", "#c44e52"])
    for b, v in zip(bars, vals):
        b.set_gid(f"bar:{v:.6g}")
        ax.text(b.get_x() + b.get_width() / 2, v, f"{v:.2f}", ha="center", va="bottom", fontsize=7)
    ax.axhline(budget["predicted_validation_mm"], ls="--", c="k", lw=1,
               label=f"predicted at new postures {budget['predicted_validation_mm']:.2f}", gid="predicted")
    if budget.get("repeatability_mm") is not None:
        ax.axhline(budget["repeatability_mm"], ls=":", c="#8172b2", lw=1.2,
                   label=f"repeatability floor {budget['repeatability_mm']:.2f}", gid="repeatability")
    ax.set_ylabel("RMSE (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=9)
    return fig
