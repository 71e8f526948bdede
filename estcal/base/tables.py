"""Tables of results, built once and rendered by whoever shows them (docs/architecture.md).

A :class:`Table` holds a title, column names and rows of plain values (numbers in display
units: mm, mrad); the terminal renders it (``str(table)`` here, or rich in
:func:`estcal.report.tables.rich_table`), the reports as HTML (:mod:`estcal.report.html`), the
JSON as :meth:`Table.to_dict`. The builders below are the one place where the parameter,
accuracy and posterior tables of a result are made: every result's :meth:`table`, the command
line and the reports call them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["Table", "format_cell", "parameter_table", "accuracy_table", "mcmc_table", "si_unit"]


def format_cell(v, digits: int = 6) -> str:
    """Text of a table cell: floats with ``digits`` significant digits, None / NaN as '—'."""
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "—" if not math.isfinite(v) else f"{v:.{digits}g}"
    if hasattr(v, "item") and not isinstance(v, (str, bytes)):  # numpy scalars
        return format_cell(v.item(), digits)
    return str(v)


@dataclass
class Table:
    """A titled table of plain values; ``key`` names it (the HTML ``id`` is ``table-<key>``).

    ``fmt(row, col, value, digits)``, when given, formats the numeric cells (e.g. decimals
    chosen per row from an interval's width); otherwise :func:`format_cell`."""

    key: str
    title: str
    columns: list
    rows: list
    note: str = ""
    digits: int = 6
    fmt: Callable | None = field(default=None, repr=False)

    def cell(self, i: int, j: int, v, digits: int | None = None) -> str:
        d = self.digits if digits is None else digits
        if self.fmt is not None and isinstance(v, float) and math.isfinite(v):
            return self.fmt(i, j, v, d)
        return format_cell(v, d)

    def text(self, digits: int = 6) -> str:
        """Plain-text rendering: the title, then aligned columns (first left, others right)."""
        cells = [[str(c) for c in self.columns]] + [[self.cell(i, j, v, digits) for j, v in enumerate(r)]
                                                   for i, r in enumerate(self.rows)]
        w = [max(len(row[j]) for row in cells) for j in range(len(self.columns))]
        lines = [self.title] if self.title else []
        for row in cells:
            lines.append("  ".join(c.ljust(w[j]) if j == 0 else c.rjust(w[j]) for j, c in enumerate(row)).rstrip())
        if self.note:
            lines.append(self.note)
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"title": self.title, "columns": list(self.columns), "rows": [list(r) for r in self.rows],
                "note": self.note}

    def __str__(self) -> str:
        return self.text()


def si_unit(name: str) -> tuple[str, float]:
    """The unit of a table in SI: no conversion (``("SI", 1.0)``)."""
    return "SI", 1.0


def parameter_table(res, unit: Callable = si_unit, label: Callable | None = None, key: str = "parameters",
                    title: str = "parameter estimates (display units)") -> Table:
    """Initial value, estimate and std of every estimated parameter of ``res`` (display units).

    ``res`` has ``names``, ``estimate``, ``std`` and, optionally, ``nominal`` (the initial values;
    the column is left out when ``res`` has none). ``unit(name) -> (unit, factor from SI)``
    (:func:`estcal.base.units.display_unit` for a robot's parameters). ``label(name)``, when
    given, is the readable regrouping (``name [+β·other …]``), shown in a last column "absorbs
    (regrouped)"."""
    nominal = getattr(res, "nominal", None)
    rows = []
    for k, (n, e, s) in enumerate(zip(res.names, res.estimate, res.std)):
        u, f = unit(n)
        row = [n] + ([] if nominal is None else [float(nominal[k] * f)]) + [float(e * f), float(s * f), u]
        if label is not None:
            lab = label(n)
            row.append(lab[len(n):].strip() if lab != n else "")
        rows.append(row)
    cols = ["parameter"] + ([] if nominal is None else ["initial"]) + ["estimate", "± std", "unit"]
    return Table(key, title, cols + ([] if label is None else ["absorbs (regrouped)"]), rows)


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
