"""A small self-contained HTML report: headings, text, tables and PNG figures.

No template engine, no external assets: ``index.html`` references the PNG
files next to it, so the folder can be zipped, mailed or served as is.
Numbers in tables are printed with ``digits`` significant digits (6 by
default, more than the terminal tables) so that they can be compared with the
command's JSON.
"""
from __future__ import annotations

import html
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from estcal.base.atomic import atomic_write_text
from estcal.base.tables import Table

from .figures import save_figure

__all__ = ["Report", "table_html"]


def table_html(table: Table) -> str:
    """HTML of a :class:`~estcal.base.tables.Table` (``id="table-<key>"``)."""
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in table.columns)
    body = "\n".join("<tr>" + "".join(f"<td>{html.escape(table.cell(i, j, v))}</td>" for j, v in enumerate(r))
                     + "</tr>" for i, r in enumerate(table.rows))
    note = f'<p class="note">{html.escape(table.note)}</p>' if table.note else ""
    return (f'<h3>{html.escape(table.title)}</h3>\n<table id="table-{html.escape(table.key)}">\n'
            f"<thead><tr>{head}</tr></thead>\n<tbody>\n{body}\n</tbody></table>\n{note}")


_CSS = """body{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1em}td,th{border:1px solid #bbb;padding:2px 8px;text-align:right;
font-size:13px}th{background:#eee}td:first-child,th:first-child{text-align:left}
figure{margin:1em 0}img{max-width:100%;border:1px solid #ddd}figcaption{font-size:13px;color:#555}
.note{font-size:13px;color:#555}pre{background:#f6f6f6;padding:.5em;font-size:12px;white-space:pre-wrap}"""


@dataclass
class Report:
    """Collects the parts of a report in order; :meth:`write` produces ``index.html``.

    Figures are saved (PNG, atomic) as soon as they are added, so a run stopped
    half-way leaves complete images; ``index.html`` is written last.
    """

    folder: Path
    title: str
    subtitle: str = ""
    parts: list = field(default_factory=list)
    files: list = field(default_factory=list)

    def __post_init__(self):
        self.folder = Path(self.folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def heading(self, text: str) -> None:
        self.parts.append(f"<h2>{html.escape(text)}</h2>")

    def text(self, text: str, pre: bool = False) -> None:
        t = html.escape(text)
        self.parts.append(f"<pre>{t}</pre>" if pre else f"<p>{t}</p>")

    def table(self, table: Table) -> Table:
        self.parts.append(table_html(table))
        return table

    def figure(self, name: str, fig, caption: str = "") -> str:
        """Save ``fig`` as ``name`` (PNG) in the folder and show it in the page."""
        save_figure(fig, self.folder / name)
        return self.image(name, caption)

    def image(self, name: str, caption: str = "") -> str:
        """Show an image file already in the folder."""
        if name not in self.files:
            self.files.append(name)
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        self.parts.append(f'<figure><img src="{html.escape(name)}" alt="{html.escape(caption or name)}">'
                          f"{cap}</figure>")
        return name

    def json(self, name: str, obj, text: str = "") -> None:
        """Write ``obj`` as JSON (atomically) into the folder and link it from the page."""
        import json

        from estcal.base.jsonio import to_jsonable

        atomic_write_text(self.folder / name, json.dumps(to_jsonable(obj), indent=2))
        self.link(name, text or name)

    def link(self, name: str, text: str) -> None:
        self.parts.append(f'<p><a href="{html.escape(name)}">{html.escape(text)}</a></p>')

    def write(self) -> Path:
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        sub = f"<p>{html.escape(self.subtitle)}</p>" if self.subtitle else ""
        page = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
                f"<title>{html.escape(self.title)}</title><style>{_CSS}</style></head><body>\n"
                f"<h1>{html.escape(self.title)}</h1>\n{sub}<p class=\"note\">written by estcal, {stamp}</p>\n"
                + "\n".join(self.parts) + "\n</body></html>\n")
        return atomic_write_text(self.folder / "index.html", page)
