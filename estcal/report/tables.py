"""Tables on the terminal: :func:`rich_table` renders a :class:`~estcal.base.tables.Table` with rich.

The tables themselves are built once, by :mod:`estcal.base.tables` (parameters, accuracy, posterior);
the terminal shows them with fewer digits than the reports (:mod:`estcal.report.html`).
"""
from __future__ import annotations

__all__ = ["rich_table"]


def rich_table(table, digits: int = 5):
    """A :class:`~estcal.base.tables.Table` for the terminal (rich), ``digits`` significant digits."""
    from rich.table import Table as RichTable

    t = RichTable(title=table.title, title_justify="left")
    for i, c in enumerate(table.columns):
        t.add_column(str(c), justify="left" if i == 0 or c == "unit" else "right")
    for i, r in enumerate(table.rows):
        t.add_row(*[table.cell(i, j, v, digits) for j, v in enumerate(r)])
    return t
