"""Run the ```console blocks of a documentation page and compare their output with the page.

A console block is a shell session: lines starting with ``$ `` are commands (a trailing ``\\``
continues on the next line), the lines up to the next command are its documented output. A line
that is only ``…`` marks output the page trimmed; every other documented line must appear in the
real output of its command, where numbers may differ within a tolerance (``numbers_match``).

Usage (the README's path is tested by tests/test_readme.py; a whole page by hand)::

    python tests/console_runner.py docs/export.md --cwd /tmp/x      # run and compare every block
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from docs_runner import code_blocks  # noqa: E402

# a number not glued to a name (j1, puma560, σ0, base_tx stay words)
NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?(?![\w.])")
ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
TRIM = "…"


@dataclass
class Command:
    line: int                     # 1-based line of the ``$`` in the page
    cmd: str
    expected: list = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        """The documented exit status: a ``[exit N]`` output line (docs/reliability.md), else 0."""
        for e in self.expected:
            m = re.fullmatch(r"\s*\[exit (\d+)\]\s*", e)
            if m:
                return int(m.group(1))
        return 0


def console_commands(text: str, infos=("console",)) -> list[Command]:
    """The ``$`` commands of every ```console block (or of the blocks whose info string is in
    ``infos``, ``""`` for plain fences) of ``text`` with their documented output."""
    out = []
    for line, info, _extra, body in code_blocks(text):
        if info not in infos:
            continue
        lines, cur, i = body.rstrip("\n").split("\n"), None, 0
        while i < len(lines):
            if lines[i].startswith("$ "):
                cmd, k = lines[i][2:], i
                while cmd.endswith("\\") and k + 1 < len(lines):
                    k += 1
                    cmd = cmd[:-1].rstrip() + " " + lines[k].strip()
                cur = Command(line + 1 + i, cmd)
                out.append(cur)
                i = k + 1
                continue
            if cur is not None:
                cur.expected.append(lines[i])
            i += 1
    return out


def skeleton(line: str) -> str:
    """The line with its numbers replaced by ``#`` and whitespace collapsed."""
    return " ".join(NUMBER.sub("#", line).split())


def numbers_match(expected: float, actual: float, rtol: float = 1e-3, tiny: float = 1e-9) -> bool:
    """Equal within ``rtol`` (the last printed digit of a 4-significant-digit figure), except that a
    documented round-off residual (|expected| < ``tiny``, e.g. 3e-13 mm) only has to stay below 1e-6:
    its digits are the platform's floating-point noise."""
    if abs(expected) < tiny:
        return abs(actual) < 1e-6
    return abs(actual - expected) <= rtol * abs(expected) + 1e-12


def missing_lines(expected: list[str], actual: str, rtol: float = 1e-3) -> list[str]:
    """Documented lines (not ``…``, not blank) with no matching line in ``actual``."""
    act = [ANSI.sub("", a) for a in actual.splitlines()]
    index: dict[str, list[list[float]]] = {}
    for a in act:
        index.setdefault(skeleton(a), []).append([float(x) for x in NUMBER.findall(a)])
    missing = []
    for e in expected:
        if not e.strip() or e.strip() == TRIM or re.fullmatch(r"\[exit \d+\]", e.strip()):
            continue
        want = [float(x) for x in NUMBER.findall(e)]
        cands = index.get(skeleton(e), [])
        if not any(len(c) == len(want) and all(numbers_match(w, x, rtol) for w, x in zip(want, c)) for c in cands):
            missing.append(e)
    return missing


def run(cmd: str, cwd, timeout: float = 300) -> subprocess.CompletedProcess:
    """``cmd`` through bash in ``cwd``, with this interpreter's folder (the venv's ``estcal``) first
    on PATH and an 80-column, colourless terminal (the width the docs were pasted at)."""
    env = dict(os.environ, COLUMNS="80", NO_COLOR="1", TERM="dumb", MPLBACKEND="Agg",
               PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))
    env.pop("FORCE_COLOR", None)
    return subprocess.run(["bash", "-c", cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pages", nargs="+", type=Path)
    ap.add_argument("--cwd", type=Path, default=Path("."), help="folder to run the commands in")
    ap.add_argument("--plain", action="store_true", help="also the $ lines of plain ``` and ```bash blocks")
    args = ap.parse_args(argv)
    bad = 0
    infos = ("console", "", "bash", "sh", "shell") if args.plain else ("console",)
    for page in args.pages:
        for c in console_commands(page.read_text(encoding="utf-8"), infos):
            p = run(c.cmd, args.cwd)
            miss = missing_lines(c.expected, p.stdout + p.stderr)
            status = "ok" if p.returncode == c.exit_code and not miss else f"FAIL (exit {p.returncode})"
            bad += status != "ok"
            print(f"{page}:{c.line}: {status}: {c.cmd[:100]}")
            for m in miss[:8]:
                print(f"    not in the output: {m.strip()[:120]}")
            if p.returncode != c.exit_code and not miss:
                print("    " + (p.stderr.strip().splitlines() or [""])[-1][:200])
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
