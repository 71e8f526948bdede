"""Docs use no deprecated flag (docs/conventions.md, "One vocabulary" and "Units on the command line"):
the deprecated spellings are read from the CLI itself (its hidden options, estcal.cli.options.deprecated_option
and method_option), and every page of docs/, README.md and docs/notebooks (markdown, scripts, notebooks)
is searched for them. Only a paragraph that documents a deprecation (it says "deprecat…", or is the table
of old and new spellings) may name one."""
from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

from estcal.cli.main import app

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted([*(REPO / "docs").rglob("*.md"), REPO / "README.md", *(REPO / "docs" / "notebooks").glob("*.py"),
                *(REPO / "docs" / "notebooks").glob("*.ipynb")])


def cli_options() -> tuple[dict, dict]:
    """``({deprecated spelling: commands}, {current spelling: commands})`` from the commands' signatures."""
    old, new = {}, {}
    for c in app.registered_commands:
        for p in inspect.signature(c.callback).parameters.values():
            info = p.default
            for o in getattr(info, "param_decls", None) or ():
                if o.startswith("--"):
                    (old if getattr(info, "hidden", False) else new).setdefault(o, set()).add(c.name)
    return old, new


def _paragraphs(text: str):
    """(first line number, text) of each block between blank lines."""
    start, buf = 1, []
    for i, line in enumerate(text.splitlines() + [""], 1):
        if line.strip():
            if not buf:
                start = i
            buf.append(line)
        elif buf:
            yield start, "\n".join(buf)
            buf = []


def _documents_a_deprecation(par: str) -> bool:
    return "deprecat" in par.lower() or re.search(r"^\s*\| old\b", par, re.M) is not None


def deprecated_uses(text: str, old: dict, new: dict) -> list[str]:
    """``line N: flag`` for each deprecated spelling in ``text`` outside a paragraph documenting it. A
    spelling that is current in another command (``--map``: design's old accuracy-map count, now the
    column map) counts only in its old form: followed by a number or ``N``."""
    found = []
    for start, par in _paragraphs(text):
        if _documents_a_deprecation(par):
            continue
        for k, line in enumerate(par.splitlines()):
            for flag in old:
                tail = r"\s+(?:N\b|\d)" if flag in new else r"(?![\w-])"
                if re.search(r"(?<![\w-])" + re.escape(flag) + tail, line):
                    found.append(f"line {start + k}: {flag}")
            if re.search(r"--regularize\s+\d[\d.e+-]*(?![\w.])", line):  # a prior std without its unit (SI)
                found.append(f"line {start + k}: --regularize without a unit")
    return found


def test_the_cli_has_deprecated_spellings_to_look_for():
    old, new = cli_options()
    assert {"--method", "--sigma-p", "--sigma-r", "--q", "--prior-std", "--noise-pos", "--sigma", "--map"} <= set(old)
    assert "--map" in new and "--q-mm" in new


def test_the_search_finds_a_deprecated_flag():
    old, new = cli_options()
    text = ("Run `estcal online d.csv --robot r --sigma-p 1e-4`.\n\n`design --map 500` or `--map N`.\n\n"
            "Reads `--map FILE.yaml`; `--q-mm 0.02`.\n\n`--sigma-p` is deprecated.\n\n"
            "| old | new |\n|---|---|\n| `--q` | `--q-mm` |\n\n`--regularize 0.002` and `--regularize 2mm`\n")
    assert deprecated_uses(text, old, new) == ["line 1: --sigma-p", "line 3: --map",
                                               "line 13: --regularize without a unit"]


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(REPO)) for p in PAGES])
def test_docs_use_no_deprecated_flag(page):
    old, new = cli_options()
    found = deprecated_uses(page.read_text(), old, new)
    assert not found, f"{page.relative_to(REPO)} uses deprecated spellings (docs/conventions.md lists the " \
                      f"current ones):\n  " + "\n  ".join(found)
