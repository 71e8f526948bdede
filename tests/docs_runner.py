"""Run the Python snippets of a documentation page, in order, in one namespace.

Every fenced block whose info string is exactly ``python`` is executed; the blocks of a page
share one namespace, so a page reads as one script (docs/api.md, "Documentation snippets").
Blocks meant as illustration only are fenced ``python no-run`` (or ``pycon`` for an interactive
session) and are skipped. Tracebacks give the page and its line: ``File "docs/api.md", line 42``.

Usage (also what the tests do, one subprocess per page so that pages cannot leak state —
registered effects, matplotlib figures — into each other or into the test process)::

    python tests/docs_runner.py docs/api.md            # run in the current folder
    python tests/docs_runner.py docs/api.md --echo     # print each block before its output
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})\s*([^\s`]*)\s*(.*)$")


def code_blocks(text: str):
    """``[(line, info, extra, code)]`` of every fenced block (``line``: 1-based line of the fence)."""
    out, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, info, extra = m.groups()
        body, j = [], i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence):
            body.append(lines[j][len(indent):] if lines[j].startswith(indent) else lines[j])
            j += 1
        out.append((i + 1, info, extra.strip(), "\n".join(body) + "\n"))
        i = j + 1
    return out


def python_blocks(path) -> list[tuple[int, str]]:
    """``[(line, code)]`` of the runnable blocks of a page (```python without ``no-run``)."""
    text = Path(path).read_text(encoding="utf-8")
    return [(line, code) for line, info, extra, code in code_blocks(text)
            if info == "python" and "no-run" not in extra]


def run_page(path, echo: bool = False) -> dict:
    """Execute the runnable blocks of ``path`` in order in one namespace; returns the namespace."""
    import matplotlib

    matplotlib.use("Agg")  # a test/CLI driver, not library code
    ns: dict = {"__name__": "__docs__"}
    for line, code in python_blocks(path):
        if echo:
            print(f"# --- {path}:{line}", flush=True)
        # padded so that tracebacks give the page's own line numbers
        exec(compile("\n" * line + code, str(path), "exec"), ns)  # noqa: S102 - running our own docs
        sys.stdout.flush()
    return ns


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pages", nargs="+", type=Path)
    ap.add_argument("--echo", action="store_true", help="print the page:line of each block before running it")
    args = ap.parse_args(argv)
    for page in args.pages:
        run_page(page.resolve(), echo=args.echo)
    return 0


if __name__ == "__main__":
    sys.exit(main())
