"""Run the Python snippets of a documentation page, in order, in one namespace.

Every fenced block whose info string is exactly ``python`` is executed; the blocks of a page
share one namespace, so a page reads as one script (docs/api.md, "Documentation snippets").
Blocks meant as illustration only are fenced ``python no-run`` (or ``pycon`` for an interactive
session; a ```python block written with ``>>>`` prompts counts as one) and are skipped. A ```` ```text output ```` block that is the next fenced block after a
code block is its printed output and is compared with what the block prints. Tracebacks give the
page and its line: ``File "docs/api.md", line 42``.

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


def python_blocks(path) -> list[tuple[int, str, str | None]]:
    """``[(line, code, expected)]`` of the runnable blocks of a page (```python without ``no-run``).

    ``expected`` is the content of the next fenced block when it is a ```` ```text output ````
    block (the code block's printed output, checked; prose such as "prints" may stand between),
    else None.
    """
    text = Path(path).read_text(encoding="utf-8")
    blocks = code_blocks(text)
    out = []
    for i, (line, info, extra, code) in enumerate(blocks):
        if info != "python" or "no-run" in extra or code.lstrip().startswith(">>>"):
            continue  # illustrative, or an interactive session (like ```pycon)
        expected = None
        if i + 1 < len(blocks) and blocks[i + 1][1] == "text" and "output" in blocks[i + 1][2].split():
            expected = blocks[i + 1][3]
        out.append((line, code, expected))
    return out


def _normal(text: str) -> str:
    return "\n".join(ln.rstrip() for ln in text.strip("\n").splitlines())


def run_page(path, echo: bool = False, check_output: bool = True) -> dict:
    """Execute the runnable blocks of ``path`` in order in one namespace; returns the namespace.

    With ``check_output`` a block's printed output must equal its ```text output block
    (trailing spaces ignored); the error shows both so the page can be updated.
    """
    import contextlib
    import io

    import matplotlib

    matplotlib.use("Agg")  # a test/CLI driver, not library code
    ns: dict = {"__name__": "__docs__"}
    for line, code, expected in python_blocks(path):
        if echo:
            print(f"# --- {path}:{line}", flush=True)
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            # padded so that tracebacks give the page's own line numbers
            exec(compile("\n" * line + code, str(path), "exec"), ns)  # noqa: S102 - running our own docs
        sys.stdout.write(buf.getvalue())
        sys.stdout.flush()
        if check_output and expected is not None and _normal(buf.getvalue()) != _normal(expected):
            import difflib

            diff = "\n".join(difflib.unified_diff(_normal(expected).splitlines(), _normal(buf.getvalue()).splitlines(),
                                                  "documented", "printed", lineterm=""))
            raise AssertionError(f"{path}:{line}: the printed output differs from the page's "
                                 f"```text output block (paste the new output if the change is intended):\n{diff}")
    return ns


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pages", nargs="+", type=Path)
    ap.add_argument("--echo", action="store_true", help="print the page:line of each block before running it")
    ap.add_argument("--no-check", action="store_true", help="do not compare with the ```text output blocks")
    args = ap.parse_args(argv)
    for page in args.pages:
        run_page(page.resolve(), echo=args.echo, check_output=not args.no_check)
    return 0


if __name__ == "__main__":
    sys.exit(main())
