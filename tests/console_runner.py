"""Run the ```console blocks of a documentation page and compare their output with the page.

A console block is a shell session: lines starting with ``$ `` are commands (a trailing ``\\``
continues on the next line; a command ending in a here-document ``<< 'EOF'`` takes the lines up to
``EOF``), the lines up to the next command are its documented output: stdout and stderr as a
terminal shows them, compared line by line and in order (``output_differs``), with numbers equal
within a tolerance (``numbers_match``; a duration, "26.2 s", only in its place). A line starting with ``…`` stands for real lines the page
left out (``… (parameter table)``); without one the documented output is the whole output. A
command shown without output is only run. A line ``[exit N]``, or the output of a following
``$ echo $?``, is the command's documented exit status (0 when absent); ``$?`` is the previous
command's status, as in one shell (each command runs in its own ``bash -c``: no ``cd`` or
variable carries over).

A block fenced `` ```console no-run: REASON `` is shown, not run (it needs a real cluster, minutes of
CPU, the repository itself …): the reason is in the info string and the page says it. Keep those few.

The commands of a page run in order in one fresh folder ``TMP/work`` (``docs_layout``): ``../shared``
is a copy of the shared data, ``docs/maps`` a copy of the repository's column maps and ``experiments``
a link to the repository's, so that a page's relative paths hold while its outputs stay in ``TMP``.
A block that reads the shared data (``needs_shared``) is skipped when they are absent.

Usage (the README's path is tested by tests/test_readme.py, every page by tests/test_docs_console.py)::

    python tests/console_runner.py docs/export.md            # run and compare every block
    python tests/console_runner.py docs/export.md --show     # and print the real output of what differs
    python tests/console_runner.py docs/export.md --rewrite  # paste the real output where it differs
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from docs_runner import code_blocks  # noqa: E402

# a number not glued to a name (j1, puma560, σ0, base_tx stay words)
NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?(?![\w.])")
REPO = Path(__file__).resolve().parents[1]
ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
TRIM = "…"
HEREDOC = re.compile(r"<<-?\s*['\"]?(\w+)['\"]?\s*$")


@dataclass
class Command:
    line: int                     # 1-based line of the ``$`` in the page
    cmd: str
    expected: list = field(default_factory=list)
    block: int = 0                # 1-based line of the block's fence
    span: int = 1                 # page lines of the command (continuations, here-document)
    indent: str = ""              # the block's indentation in the page

    echoed: int | None = None     # the status the next command (``echo $?``) prints

    @property
    def exit_code(self) -> int:
        """The documented exit status: a ``[exit N]`` output line (docs/reliability.md), or the
        output of a following ``$ echo $?``, else 0."""
        for e in self.expected:
            m = re.fullmatch(r"\s*\[exit (\d+)\]\s*", e)
            if m:
                return int(m.group(1))
        return 0 if self.echoed is None else self.echoed


def is_no_run(extra: str) -> bool:
    """The info string after ``console`` flags the block as shown, not run (``no-run: REASON``)."""
    return re.match(r"no-run\b", extra) is not None


def console_commands(text: str, infos=("console",), no_run: bool = False) -> list[Command]:
    """The ``$`` commands of every ```console block (or of the blocks whose info string is in
    ``infos``, ``""`` for plain fences) of ``text`` with their documented output; the blocks
    flagged ``no-run`` only with ``no_run=True``."""
    out = []
    page = text.splitlines()
    for line, info, extra, body in code_blocks(text):
        if info not in infos or (is_no_run(extra) and not no_run):
            continue
        indent = page[line - 1][:len(page[line - 1]) - len(page[line - 1].lstrip())]
        lines, cur, i = body.rstrip("\n").split("\n"), None, 0
        while i < len(lines):
            if lines[i].startswith("$ "):
                cmd, k = lines[i][2:], i
                while cmd.endswith("\\") and k + 1 < len(lines):
                    k += 1
                    cmd = cmd[:-1].rstrip() + " " + lines[k].strip()
                here = HEREDOC.search(cmd)
                if here:  # the document's lines up to its delimiter belong to the command
                    while k + 1 < len(lines):
                        k += 1
                        cmd += "\n" + lines[k]
                        if lines[k] == here.group(1):
                            break
                cur = Command(line + 1 + i, cmd, block=line, span=k - i + 1, indent=indent)
                out.append(cur)
                i = k + 1
                continue
            if cur is not None:
                cur.expected.append(lines[i])
            i += 1
    for prev, c in zip(out, out[1:]):
        shown = [e.strip() for e in c.expected if e.strip()]
        if c.cmd.strip() == "echo $?" and len(shown) == 1 and shown[0].isdigit():
            prev.echoed = int(shown[0])
    return out


#: a UR kinematics file's name, the hash of its 36 numbers to the last bit (estcal.kinematics.ur_kinematics):
#: the platform's rounding of a calibration changes it, so only its place is compared (tests/test_ur_kinematics.py
#: holds what it hashes)
UR_HASH = re.compile(r"calib_estcal_[0-9a-f]{16}")


def skeleton(line: str) -> str:
    """The line with its numbers replaced by ``#``, a UR kinematics hash by ``calib_estcal_<hash>`` and
    whitespace collapsed."""
    return " ".join(NUMBER.sub("#", UR_HASH.sub("calib_estcal_<hash>", line)).split())


def numbers_match(expected: float, actual: float, rtol: float = 1e-3, tiny: float = 1e-9) -> bool:
    """Equal within ``rtol`` (the last printed digit of a 4-significant-digit figure), except that a
    documented round-off residual (|expected| < ``tiny``, e.g. 3e-13 mm) only has to stay below 1e-6:
    its digits are the platform's floating-point noise."""
    if abs(expected) < tiny:
        return abs(actual) < 1e-6
    return abs(actual - expected) <= rtol * abs(expected) + 1e-12


def is_trim(line: str) -> bool:
    """A documented line that stands for output the page left out: ``…`` alone or followed by a
    comment (``… (parameter table)``)."""
    return line.strip().startswith(TRIM)


def is_exit(line: str) -> bool:
    return re.fullmatch(r"\[exit \d+\]", line.strip()) is not None


DURATION = re.compile(r"\s?s(?!\w)")  # after a number: seconds ("26.2 s", "(5.6 s)")


def numbers(line: str) -> list[tuple[float, bool]]:
    """The numbers of ``line``, each with whether it is a duration in seconds (wall-clock time:
    it differs from run to run, so only its place is compared)."""
    return [(float(m.group()), DURATION.match(line, m.end()) is not None) for m in NUMBER.finditer(line)]


def lines_match(expected: str, actual: str, rtol: float = 1e-3) -> bool:
    """The same words (whitespace collapsed) and the same numbers within ``numbers_match``,
    durations in seconds aside."""
    if skeleton(expected) != skeleton(actual):
        return False
    want, got = numbers(expected), numbers(actual)
    return len(want) == len(got) and all(dw or numbers_match(w, g, rtol) for (w, dw), (g, _) in zip(want, got))


def missing_lines(expected: list[str], actual: str, rtol: float = 1e-3) -> list[str]:
    """Documented lines (not ``…``, not blank) with no matching line anywhere in ``actual``."""
    act = [ANSI.sub("", a) for a in actual.splitlines()]
    index: dict[str, list[str]] = {}
    for a in act:
        index.setdefault(skeleton(a), []).append(a)
    return [e for e in expected if e.strip() and not is_trim(e) and not is_exit(e)
            and not any(lines_match(e, a, rtol) for a in index.get(skeleton(e), []))]


def output_differs(expected: list[str], actual: str, rtol: float = 1e-3) -> str:
    """Why the documented output is not the real one, or ``""`` when it is.

    Blank lines aside, the documented lines must be the real ones in order (``lines_match``),
    where a trim line (``is_trim``) stands for any number of real lines — doctest's ELLIPSIS
    on whole lines: a block without a trim shows the whole output, so a line the command
    newly prints makes the page stale too. A command shown without any output line is not
    compared (only its exit status)."""
    act = [a for a in (ANSI.sub("", x).rstrip() for x in actual.splitlines()) if a.strip()]
    exp = [e.rstrip() for e in expected if e.strip() and not is_exit(e)]
    if not exp:
        return ""  # a command shown without output (a step before the one whose output matters)
    segments, cur = [], []
    for e in exp:
        if is_trim(e):
            segments.append(cur)
            cur = []
        else:
            cur.append(e)
    segments.append(cur)
    # segments[0] is anchored at the start, segments[-1] at the end (empty when a trim is there)
    fits = lambda seg, j: j + len(seg) <= len(act) and all(lines_match(e, a, rtol) for e, a in zip(seg, act[j:]))  # noqa: E731
    if len(segments) == 1:
        ok = len(exp) == len(act) and fits(exp, 0)
        return "" if ok else _first_difference(exp, act, rtol)
    if not fits(segments[0], 0):
        return _first_difference(segments[0], act, rtol)
    pos = len(segments[0])
    for seg in segments[1:-1]:
        j = next((j for j in range(pos, len(act) - len(seg) + 1) if fits(seg, j)), None)
        if j is None:
            return "not found in order after the real line %d: %s" % (pos, _first_missing(seg, act[pos:], rtol))
        pos = j + len(seg)
    last = segments[-1]
    if last and (len(act) - len(last) < pos or not fits(last, len(act) - len(last))):
        return "the last documented lines are not the last real ones: " + _first_missing(last, act[pos:], rtol)
    return ""


def _first_missing(seg: list[str], act: list[str], rtol: float) -> str:
    miss = [e for e in seg if not any(lines_match(e, a, rtol) for a in act)]
    return repr(miss[0].strip()[:160]) if miss else "(every line is there, not contiguous: " + repr(seg[0].strip()[:120]) + " …)"


def _first_difference(exp: list[str], act: list[str], rtol: float) -> str:
    for k, e in enumerate(exp):
        if k >= len(act):
            return f"documented line {k + 1} is past the real output's end: {e.strip()[:160]!r}"
        if not lines_match(e, act[k], rtol):
            return f"line {k + 1}: documented {e.strip()[:160]!r}\n{'':>10}real {act[k].strip()[:160]!r}"
    return f"the real output goes on (line {len(exp) + 1}: {act[len(exp)].strip()[:160]!r}); end the block with … if that is meant"


def run(cmd: str, cwd, timeout: float = 300, merge: bool = False, status: int = 0,
        sessions: list | None = None) -> subprocess.CompletedProcess:
    """``cmd`` through bash in ``cwd``, with this interpreter's folder (the venv's ``estcal``) first
    on PATH and an 80-column, colourless terminal (the width the docs were pasted at).

    ``merge``: stderr into stdout, unbuffered, in the order a terminal shows them. ``status``: the
    value of ``$?`` the command starts with (the previous command's, as in one shell session).
    ``sessions``: a list the command's process group is added to (its background children may serve later
    commands; ``end_sessions`` ends them)."""
    env = dict(os.environ, COLUMNS="80", NO_COLOR="1", TERM="dumb", MPLBACKEND="Agg", PYTHONUNBUFFERED="1",
               PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))
    env.pop("FORCE_COLOR", None)
    if status:
        cmd = f"(exit {status}); {cmd}"
    err = subprocess.STDOUT if merge else subprocess.PIPE
    # a session of its own, so that a timeout ends the command's children too (estcal under bash)
    with subprocess.Popen(["bash", "-c", cmd], cwd=cwd, stdout=subprocess.PIPE, stderr=err, text=True, env=env,
                          start_new_session=True) as proc:
        try:
            out, errs = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            raise
    if sessions is not None:
        sessions.append(proc.pid)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, errs)


def end_sessions(sessions: list) -> None:
    """Kill what is left of these process groups (the background children of a page's commands)."""
    while sessions:
        try:
            os.killpg(sessions.pop(), signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


# the built-in robots read from ../shared (estcal.kinematics.robots)
SHARED_ROBOTS = re.compile(r"(?:-r|--robot)[ =](?:tiago|talos\w*|ur10\w*)\b")


def needs_shared(commands) -> bool:
    """Whether these commands read the shared data: a ``../shared`` path or a built-in robot read
    from it (``--robot tiago``)."""
    return any("../shared" in c.cmd or SHARED_ROBOTS.search(c.cmd) for c in commands)


def shared_data() -> Path:
    """The shared data folder next to the repository (tests/conftest.py's ``SHARED``)."""
    return REPO.parent / "shared"


def docs_layout(tmp: Path, repo: Path = REPO) -> Path:
    """``tmp/work``, the folder a page's commands run in: ``tmp/shared`` is a copy of the shared
    data (when present), ``tmp/work/docs/maps`` is a copy of the repository's column maps and
    ``tmp/work/experiments`` links to its experiment scripts (read, never written: their outputs
    are named on the command line)."""
    import shutil

    work = tmp / "work"
    (work / "docs").mkdir(parents=True)
    shutil.copytree(repo / "docs" / "maps", work / "docs" / "maps")
    (work / "experiments").symlink_to(repo / "experiments", target_is_directory=True)
    if shared_data().is_dir():  # a copy (150 kB): paths written relative to it stay ../shared/…
        shutil.copytree(shared_data(), tmp / "shared")
    return work


@dataclass
class Outcome:
    command: Command
    output: str | None            # stdout and stderr as a terminal shows them; None: skipped
    returncode: int = 0
    cpu: float = 0.0              # CPU seconds of the command and its children

    @property
    def difference(self) -> str:
        return "" if self.output is None else output_differs(self.command.expected, self.output)

    @property
    def ok(self) -> bool:
        return self.output is None or (self.returncode == self.command.exit_code and not self.difference)

    def describe(self, show: bool = False) -> str:
        c = self.command
        if self.output is None:
            return f"line {c.line}: skipped (reads ../shared, absent): {c.cmd.splitlines()[0][:100]}"
        state = "ok" if self.ok else f"FAIL (exit {self.returncode}, documented {c.exit_code})"
        head = f"line {c.line}: {state} [{self.cpu:.1f} s CPU]: {c.cmd.splitlines()[0][:100]}"
        if self.ok:
            return head
        lines = [head] + ["    " + ln for ln in self.difference.splitlines()]
        if show or not self.difference:
            lines.append("    --- real output:")
            lines += ["    | " + ln for ln in self.output.rstrip("\n").splitlines()[-100:]]
        return "\n".join(lines)


def run_page(text: str, work: Path, timeout: float = 300) -> list[Outcome]:
    """Run the commands of the ```console blocks of ``text`` in order in ``work``, each starting
    with ``$?`` = the previous one's status; the blocks that read the shared data are skipped
    (``output=None``) when those are absent."""
    import resource

    commands = console_commands(text)
    blocks: dict[int, list[Command]] = {}
    for c in commands:
        blocks.setdefault(c.block, []).append(c)
    have_shared = (work.parent / "shared").is_dir()
    out, status, sessions = [], 0, []
    try:
        for c in commands:
            if not have_shared and needs_shared(blocks[c.block]):
                out.append(Outcome(c, None))
                continue
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            try:
                p = run(c.cmd, work, timeout=timeout, merge=True, status=status, sessions=sessions)
                output, status = p.stdout, p.returncode
            except subprocess.TimeoutExpired:
                output, status = f"(killed after {timeout:.0f} s)\n", -9
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            out.append(Outcome(c, output, status,
                               (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)))
    finally:
        end_sessions(sessions)  # a background process a command started (`dask scheduler … &`) ends with its page
    return out


def rewrite(text: str, outcomes: list[Outcome]) -> tuple[str, list[str]]:
    """``text`` with the documented output of every differing command replaced by its real output
    (an ``[exit N]`` line added for a non-zero status not shown by a following ``echo $?``);
    the commands whose output the page trims (``…``) are left for a hand edit and listed."""
    lines, left = text.split("\n"), []
    for k, o in sorted(enumerate(outcomes), key=lambda ko: -ko[1].command.line):
        c = o.command
        if o.ok or o.output is None:
            continue
        if any(is_trim(e) for e in c.expected):
            left.append(f"line {c.line}: {c.cmd.splitlines()[0][:80]} (its output is trimmed with …: edit by hand)")
            continue
        new = [ln.rstrip() for ln in o.output.rstrip("\n").split("\n")]
        nxt = outcomes[k + 1].command if k + 1 < len(outcomes) else None
        if o.returncode and not (nxt is not None and nxt.cmd.strip() == "echo $?"):
            new.append(f"[exit {o.returncode}]")
        start = c.line - 1 + c.span            # 0-based index of the first output line
        lines[start:start + len(c.expected)] = [(c.indent + ln) if ln else "" for ln in new]
    return "\n".join(lines), left


def main(argv=None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pages", nargs="+", type=Path)
    ap.add_argument("--show", action="store_true", help="print the real output of every command that differs")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folders (their paths are printed)")
    ap.add_argument("--rewrite", action="store_true", help="write the real output into the page for every "
                    "differing command whose output is not trimmed with … (check the diff before committing)")
    args = ap.parse_args(argv)
    bad = 0
    for page in args.pages:
        tmp = Path(tempfile.mkdtemp(prefix=f"console_{page.stem}_"))
        outcomes = run_page(page.read_text(encoding="utf-8"), docs_layout(tmp))
        for o in outcomes:
            bad += not o.ok
            print(f"{page}:{o.describe(args.show)}", flush=True)
        print(f"{page}: {sum(o.cpu for o in outcomes):.1f} s CPU" + (f", kept in {tmp}" if args.keep else ""))
        if args.rewrite:
            text, left = rewrite(page.read_text(encoding="utf-8"), outcomes)
            page.write_text(text, encoding="utf-8")
            for msg in left:
                print(f"{page}:{msg}")
        if not args.keep:
            import shutil

            shutil.rmtree(tmp)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
