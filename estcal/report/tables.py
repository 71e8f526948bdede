"""Table contents shared by the terminal output and the HTML reports (one source of numbers).

Each function returns a :class:`~estcal.report.html.Table` whose cells are the
numbers in display units (mm, mrad); the terminal renders it with fewer digits
(:func:`rich_table`), the report with six significant digits.
"""
from __future__ import annotations

import numpy as np

from .html import Table

__all__ = ["parameter_table", "accuracy_table", "mcmc_table", "rich_table"]


def parameter_table(res, unit, label=None) -> Table:
    """Initial value, estimate and std of every free parameter (display units).

    ``unit(name) -> (unit, factor)``; ``label(name)`` the readable regrouping (optional)."""
    rows = []
    for n, v, e, s in zip(res.names, res.nominal, res.estimate, res.std):
        u, f = unit(n)
        lab = label(n) if label is not None else n
        rows.append([n, float(v * f), float(e * f), float(s * f), u, lab[len(n):].strip() if lab != n else ""])
    return Table("parameters", "parameter estimates (display units)",
                 ["parameter", "initial", "estimate", "± std", "unit", "absorbs (regrouped)"], rows)


def accuracy_table(res, data_path, validate_paths) -> Table:
    """RMSE / mean / max position (mm) and orientation (mrad) errors before and after."""
    acc = res.accuracy or {}
    rows = []
    named = []
    if "train" in acc:
        named.append((f"calibration: {data_path}", acc["train"]))
    for p, v in zip(validate_paths, acc.get("validation", [])):
        named.append((f"validation: {p}", v))
    for label, d in named:
        b, a = d.get("before", {}), d.get("after", {})
        rows.append([label, a.get("n_poses"), b.get("rmse_mm"), a.get("rmse_mm"), a.get("mean_mm"), a.get("max_mm"),
                     b.get("rmse_mrad"), a.get("rmse_mrad"), a.get("max_mrad")])
    return Table("accuracy", "accuracy (position mm, orientation mrad)",
                 ["data", "poses", "RMSE before", "RMSE after", "mean after", "max after", "rot RMSE before",
                  "rot RMSE after", "rot max after"], rows,
                 note="'before' = initial guess: " + res.extra.get("initial_guess", "nominal"))


def mcmc_table(res, unit) -> Table | None:
    """Posterior credible interval, median, effective sample size and integrated
    autocorrelation time τ (steps) per parameter; None for non-MCMC results."""
    ex = res.extra
    if "credible_intervals" not in ex:
        return None
    level = float(ex.get("credible_level", 0.95))
    lo_p, hi_p = 100 * (1 - level) / 2, 100 * (1 + level) / 2
    med = np.asarray(ex["posterior_median"], float)
    ess = np.asarray(ex["ess"], float)
    tau = np.asarray(ex["tau"], float)
    rows, decimals = [], []
    for i, n in enumerate(res.names):
        u, f = unit(n)
        lo, hi = ex["credible_intervals"][n]
        rows.append([n, float(lo * f), float(med[i] * f), float(hi * f), float(ess[i]), float(tau[i]), u])
        w = abs(hi - lo) * f
        # two significant digits of the interval's width, whatever the parameter's magnitude
        decimals.append(int(np.clip(1 - np.floor(np.log10(w)), 0, 12)) if w > 0 and np.isfinite(w) else 3)

    def fmt(i, j, v, digits):  # terminal (5 digits): 2 significant digits of the width; reports: 4 more
        if j in (1, 2, 3):
            return f"{v:.{decimals[i] + (4 if digits > 5 else 0)}f}"
        return f"{v:.{digits}g}"

    note = (f"{ex.get('n_walkers')} walkers × {ex.get('n_steps')} steps, burn-in {ex.get('burn_in')}, "
            f"acceptance {ex.get('acceptance_fraction', float('nan')):.2f}; chain "
            f"{'converged' if res.converged else 'NOT converged (ESS target or 50 τ not reached)'}")
    return Table("mcmc", f"posterior: {level:.0%} credible interval, median, effective sample size, "
                         f"autocorrelation time",
                 ["parameter", f"{lo_p:g} %", "50 %", f"{hi_p:g} %", "ESS", "τ (steps)", "unit"], rows, note=note,
                 fmt=fmt)


def rich_table(table: Table, digits: int = 5):
    """The same table for the terminal (rich), ``digits`` significant digits."""
    from rich.table import Table as RichTable

    t = RichTable(title=table.title, title_justify="left")
    for i, c in enumerate(table.columns):
        t.add_column(str(c), justify="left" if i == 0 else "right")
    for i, r in enumerate(table.rows):
        t.add_row(*[table.cell(i, j, v, digits) for j, v in enumerate(r)])
    return t
