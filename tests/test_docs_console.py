"""Every ```console block of the documentation runs and prints what the page shows.

For each page of ``docs/*.md`` and ``README.md`` with ```console blocks (tests/console_runner.py): the
``$`` commands run in order through bash, with the venv's ``estcal``, in one fresh folder ``TMP/work``
with ``../shared`` (the shared data), ``docs/maps`` and ``experiments`` reachable as from the
repository; each must exit with its documented status (``[exit N]``, else 0) and print the documented
lines in order — the whole output, or the parts a ``…`` line does not stand for — with the same words
and the same numbers within 1e-3 (the last digit of a 4-significant-digit figure, in case a BLAS
rounds differently). A block fenced ```` ```console no-run: REASON ```` is not run (it needs a cluster,
minutes of CPU, the repository itself); its reason is in the info string and in the page. Blocks
that read ``../shared`` are skipped when the shared data are absent.

Regenerate a page's outputs with ``python tests/console_runner.py docs/PAGE.md --show``.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from console_runner import console_commands, docs_layout, is_no_run, output_differs, run_page
from docs_runner import code_blocks

REPO = Path(__file__).resolve().parents[1]
ALL_PAGES = sorted([*(REPO / "docs").glob("*.md"), REPO / "README.md"])
PAGES = [p for p in ALL_PAGES if console_commands(p.read_text(encoding="utf-8"))]


def test_trims_order_and_numbers():
    real = "head\nσ0 = 1.234, RMSE 0.05 mm\nrow 1\nrow 2\ntail 3\n"
    assert output_differs(["head", "σ0 = 1.2341, RMSE 0.05 mm", "row 1", "row 2", "tail 3"], real) == ""
    assert output_differs(["head", "…", "tail 3"], real) == ""
    assert output_differs(["… (the table)", "row 2", "…"], real) == ""
    assert output_differs([], real) == ""                                  # a step shown without output
    assert "goes on" in output_differs(["head", "σ0 = 1.234, RMSE 0.05 mm"], real)   # a new line is stale
    assert output_differs(["head", "…", "row 2", "row 1", "…"], real) != ""           # order
    assert output_differs(["σ0 = 1.24, RMSE 0.05 mm", "…"], real) != ""              # a number moved
    assert output_differs(["head", "…", "tail 4"], real) != ""
    assert output_differs(["…", "[exit 3]", "tail 3"], real) == ""
    assert output_differs(["fleet — 7 robots (2 workers, 26.2 s)"], "fleet — 7 robots (2 workers, 9.4 s)\n") == ""
    assert output_differs(["fleet — 7 robots (2 workers, 26.2 s)"], "fleet — 6 robots (2 workers, 26.2 s)\n") != ""
    # a UR kinematics file's hash (of its numbers to the last bit): its place, not its digits
    assert output_differs(["wrote k.yaml (hash calib_estcal_31a1360cef278d23); 0.772 mrad"],
                          "wrote k.yaml (hash calib_estcal_b9f41c3c51286c31); 0.772 mrad\n") == ""
    assert output_differs(["wrote k.yaml (hash calib_estcal_31a1360cef278d23); 0.772 mrad"],
                          "wrote k.yaml (hash calib_estcal_b9f41c3c51286c31); 0.781 mrad\n") != ""
    assert output_differs(["hash: calib_estcal_31a1360cef278d23"], "hash: 31a1360cef278d23\n") != ""


def test_blocks_exits_heredocs_and_no_run(tmp_path):
    page = ("text\n```console\n$ printf 'a 1\\nb 2\\n'\na 1\nb 2\n$ false\n$ echo $?\n1\n$ (exit 4)\n[exit 4]\n```\n"
            "```console no-run: needs a cluster\n$ exit 7\n```\n"
            "```console\n$ echo more \\\n  words\nmore words\n$ cat > f.txt << 'EOF'\nkept $HOME\nEOF\n$ cat f.txt\nkept $HOME\n```\n")
    cmds = console_commands(page)
    assert [c.cmd for c in cmds] == ["printf 'a 1\\nb 2\\n'", "false", "echo $?", "(exit 4)", "echo more words",
                                     "cat > f.txt << 'EOF'\nkept $HOME\nEOF", "cat f.txt"]
    assert [c.exit_code for c in cmds] == [0, 1, 0, 4, 0, 0, 0]
    outcomes = run_page(page, docs_layout(tmp_path))
    assert all(o.ok for o in outcomes), [o.describe() for o in outcomes]
    bad = run_page(page.replace("b 2\n$ false", "b 3\n$ false").replace("[exit 4]", "[exit 3]"),
                   docs_layout(tmp_path / "again"))
    assert [o.ok for o in bad] == [False, True, True, False, True, True, True]


def test_blocks_with_commands_are_console_blocks():
    """A block that shows ``$`` commands is a ```console block (run here) or says why it is not
    (```console no-run: REASON); every no-run block gives its reason."""
    plain, no_reason = [], []
    for page in ALL_PAGES:
        for line, info, extra, body in code_blocks(page.read_text(encoding="utf-8")):
            if info != "console" and any(ln.startswith("$ ") for ln in body.splitlines()):
                plain.append(f"{page.name}:{line} (```{info})")
            if info == "console" and is_no_run(extra) and not re.sub(r"^no-run\W*", "", extra).strip():
                no_reason.append(f"{page.name}:{line}")
    assert not plain, "blocks with $ commands that are not ```console blocks: " + ", ".join(plain)
    assert not no_reason, "```console no-run blocks without a reason (```console no-run: REASON): " + ", ".join(no_reason)


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_console_blocks_print_what_the_page_shows(page, tmp_path):
    outcomes = run_page(page.read_text(encoding="utf-8"), docs_layout(tmp_path), timeout=240)
    if all(o.output is None for o in outcomes):
        pytest.skip(f"{page.name}: every console block reads ../shared (absent)")
    failures = [o.describe(show=True) for o in outcomes if not o.ok]
    assert not failures, (f"{page.relative_to(REPO)}: {len(failures)} of {len(outcomes)} commands differ from the page "
                          f"(regenerate with `python tests/console_runner.py {page.relative_to(REPO)} --show`):\n"
                          + "\n".join(failures))


def test_background_processes_end_with_their_page(tmp_path):
    """A command's background child (``cmd &``, a Dask scheduler) serves the page's later commands and is ended
    when the page is done — a documentation run leaves no process behind."""
    import time

    page = "```console\n$ sleep 300 > /dev/null 2>&1 & echo $! > pid\n$ kill -0 $(cat pid) && echo alive\nalive\n```\n"
    work = docs_layout(tmp_path)
    outcomes = run_page(page, work)
    assert all(o.ok for o in outcomes), [o.describe() for o in outcomes]
    pid = int((work / "pid").read_text())
    for _ in range(100):  # killed: gone, or a zombie until init reaps it
        stat = Path(f"/proc/{pid}/stat")
        try:
            if stat.read_text().split(") ")[1][0] in "ZX":
                return
        except (FileNotFoundError, ProcessLookupError):
            return
        time.sleep(0.02)
    pytest.fail(f"the page's background process {pid} outlived its page")
