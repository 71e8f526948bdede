"""``--report DIR``: PNG figures and an ``index.html`` that shows them with the tables.

* :mod:`.figures` — save a Figure as PNG atomically;
* :mod:`.html` — :class:`Report` (collects tables, figures and text, writes ``index.html``);
  the tables are :class:`estcal.base.tables.Table`, built by :mod:`estcal.base.tables`;
* :mod:`.tables` — the same tables on the terminal (rich);
* one builder per command: :mod:`.calibration`, :mod:`.online`, :mod:`.design`
  (``design`` and ``next-pose``), :mod:`.diagnose`.

The builders take the objects the commands already computed (result objects,
datasets, the JSON dict) and put the *same numbers* in the HTML tables as the
command prints and writes to JSON; the figures come from :mod:`estcal.plots`.
Documented in ``docs/reports.md``.
"""
from __future__ import annotations

from .html import Report

__all__ = ["Report"]
