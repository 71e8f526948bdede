"""Checks every subcommand gets before it starts working (one place, keyed by option name).

:func:`option_checks` builds them from a subcommand's signature when
:func:`estcal.cli.app.command` registers it (they run in :func:`estcal.cli.run.guarded`),
so a new or renamed option is covered by the rules below without touching the
command's module:

* **numbers** — every float option must be finite; counts (``--n``, ``--every``,
  ``--restarts`` …) are integers ≥ 1; noise and prior widths are > 0 (≥ 0 in
  ``simulate``, where 0 means noise-free); process noise, resolutions and
  simulated error widths are ≥ 0; ``--alpha`` is in (0, 1) … The message names
  the option, its value and the accepted range (an ``InputError``: exit code 2).
* **output files** (``--json``, ``--output/-o``, ``--truth``, ``--save-model`` …)
  are checked *before* the work, so a long fit is never lost to a bad path: not a
  folder, their folder can be created and written, not also an input of the
  command (inputs are never overwritten), and two outputs are not the same file.

Rules by option name, first match wins: see :data:`NUMBER_RULES`.
"""
from __future__ import annotations

import inspect
import math
import os
from pathlib import Path

from estcal.base.errors import InputError

__all__ = ["option_checks", "check_number", "check_outputs", "NUMBER_RULES", "OUTPUT_OPTIONS"]

# (option names, commands the rule applies to (None = all), rule); first match wins. Every name is
# an option of some command (tests/test_cli_conventions.py), so no rule outlives its flag.
# rules: ("int", lo) integer >= lo; ("gt", lo) > lo; ("ge", lo) >= lo; ("open", lo, hi) lo < x < hi;
#        ("halfopen", lo, hi) lo <= x < hi
_NOISE = ("--noise-pos-mm", "--noise-rot-mrad", "--noise-joint-mrad", "--noise-leg-mm", "--prior-std-mm",
          "--noise-pos", "--noise-rot", "--noise-joint", "--noise-leg", "--sigma", "--sigma-rot", "--sigma-p",
          "--sigma-r", "--prior-std")  # the last eight: deprecated spellings, still accepted
_ERRORS = ("--error-angle-mrad", "--error-length-mm", "--error-offset-mrad", "--error-gain", "--error-angle",
           "--error-length", "--error-offset")
NUMBER_RULES: list[tuple[tuple, tuple | None, tuple]] = [
    (("--n", "--n-poses", "--n-candidates", "--restarts", "--random-plans", "--every", "--points",
      "--workers", "--max-iter", "--fleet", "--checkpoint-every"), None, ("int", 1)),
    (("--folds",), None, ("int", 2)),
    (("--show", "--map", "--accuracy-map", "--seed", "--recalibrate"), None, ("int", 0)),
    (_NOISE + _ERRORS, ("simulate",), ("ge", 0.0)),  # simulate: 0 = noise-free, error-free
    (_NOISE, None, ("gt", 0.0)),
    (("--q", "--q-mm", "--resolution", "--resolution-mrad", "--tau-floor", "--throttle") + _ERRORS, None,
     ("ge", 0.0)),
    (("--alpha",), None, ("open", 0.0, 1.0)),
    (("--margin",), None, ("halfopen", 0.0, 0.5)),
    (("--dt", "--tol-mm", "--tol-mrad", "--rot-weight-m"), None, ("gt", 0.0)),
]

# options whose value is a file the command writes (folders such as --report are not checked here)
OUTPUT_FOLDER_OPTIONS = ("--report", "--out", "--out-dir", "--output-dir", "--save-models")
OUTPUT_OPTIONS = ("--json", "--output", "--truth", "--save-model", "--save-state", "--checkpoint", "--plot",
                  "--html", "--urdf", "--ur-kinematics", "--robot-spec")


_EXAMPLE_NAME = {"--json": "result.json", "--truth": "truth.json", "--urdf": "robot.urdf", "--save-model": "model.yaml",
                 "--ur-kinematics": "kinematics.yaml", "--robot-spec": "robot_spec.yaml",
                 "--chain": "chain.h5", "--option chain": "chain.h5",
                 "--state": "online.state"}


def _describe(rule) -> str:
    kind = rule[0]
    if kind == "int":
        return f"an integer ≥ {rule[1]}"
    if kind == "gt":
        return f"a number > {rule[1]:g}"
    if kind == "ge":
        return f"a number ≥ {rule[1]:g}"
    if kind == "open":
        return f"a number strictly between {rule[1]:g} and {rule[2]:g}"
    return f"a number in [{rule[1]:g}, {rule[2]:g})"


def _ok(value, rule) -> bool:
    kind = rule[0]
    if kind == "int":
        return value >= rule[1]
    if kind == "gt":
        return value > rule[1]
    if kind == "ge":
        return value >= rule[1]
    if kind == "open":
        return rule[1] < value < rule[2]
    return rule[1] <= value < rule[2]


def check_number(option: str, value, command: str | None = None) -> None:
    """Exit (code 2) with a message naming ``option`` when ``value`` breaks its rule."""
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(f"{option} {value}: must be a finite number")
    for names, commands, rule in NUMBER_RULES:
        if option in names and (commands is None or command in commands):
            if not _ok(value, rule):
                raise InputError(f"{option} {value:g}: must be {_describe(rule)}")
            return


def _existing_ancestor(p: Path) -> Path:
    a = p.parent
    while not a.exists() and a != a.parent:
        a = a.parent
    return a


def check_outputs(outputs: dict[str, Path], inputs: list[Path], folders: dict[str, Path] | None = None) -> None:
    """``outputs`` {option: path}: refuse folders, unwritable places, inputs and duplicates;
    ``folders`` {option: path} are output folders: refuse an existing file."""
    for opt, p in (folders or {}).items():
        p = Path(p)
        if p.exists() and not p.is_dir():
            raise InputError(f"{opt} {p}: is a file — give a folder (it is created if missing)")
        anc = p if p.is_dir() else _existing_ancestor(p)
        if not anc.is_dir():
            raise InputError(f"{opt} {p}: {anc} is a file, not a folder — choose another place for the output")
        if not os.access(anc, os.W_OK | os.X_OK):
            raise InputError(f"{opt} {p}: the folder {anc} is not writable — choose another place for the output")
    seen: dict[str, str] = {}
    ins = {}
    for p in inputs:
        try:
            if p.is_file():
                ins[os.path.realpath(p)] = p
        except OSError:
            continue
    for opt, p in outputs.items():
        if p is None:
            continue
        if str(p) == "-":  # without this, a file literally named '-'
            raise InputError(f"{opt} -: output files are written atomically and cannot go to standard output — give "
                             f"a file name (the summary is printed on standard output)")
        p = Path(p)
        if p.is_dir():
            example = _EXAMPLE_NAME.get(opt, "out.csv")
            raise InputError(f"{opt} {p}: is a folder — give a file name (e.g. {p / example})")
        anc = _existing_ancestor(p)
        if not anc.is_dir():
            raise InputError(f"{opt} {p}: {anc} is a file, not a folder — choose another place for the output")
        if not os.access(anc, os.W_OK | os.X_OK):
            raise InputError(f"{opt} {p}: the folder {anc} is not writable — choose another place for the output")
        if p.exists() and not os.access(p, os.W_OK):
            raise InputError(f"{opt} {p}: the file exists and is read-only — choose another name")
        real = os.path.realpath(p)
        if real in ins:
            raise InputError(f"{opt} {p}: is also an input file of this command ({ins[real]}) — write the output to "
                             f"another file (inputs are never overwritten)")
        if real in seen:
            raise InputError(f"{opt} {p}: the same file as {seen[real]} — give each output its own file")
        seen[real] = opt


def _option_names(sig: inspect.Signature) -> dict[str, tuple[str, str]]:
    """{python parameter: (long option name or '', 'file' / 'folder' output or '')}"""
    from typer.models import ArgumentInfo, OptionInfo

    out = {}
    for name, par in sig.parameters.items():
        d = par.default
        if isinstance(d, OptionInfo):
            decls = [s for dcl in (d.param_decls or ()) for s in dcl.split("/") if s.startswith("--")]
            opt = decls[0] if decls else "--" + name.replace("_", "-")
            out[name] = (opt, "file" if opt in OUTPUT_OPTIONS else "folder" if opt in OUTPUT_FOLDER_OPTIONS else "")
        elif isinstance(d, ArgumentInfo):
            out[name] = ("", "")
    return out


def option_checks(command: str, sig: inspect.Signature):
    """The checks of ``command``'s options (signature ``sig``): a function of the bound arguments
    ``{parameter: value}`` that raises :class:`~estcal.base.errors.InputError` on the first
    number out of its range or output path that cannot be written (every input file is known
    by then: a path-valued argument that is not an output)."""
    names = _option_names(sig)

    def check(arguments: dict) -> None:
        outputs, folders, inputs = {}, {}, []
        for pname, value in arguments.items():
            opt, kind = names.get(pname, ("", ""))
            if opt:
                try:
                    check_number(opt, value, command)
                except InputError as exc:
                    from estcal.cli.config import from_config

                    src = from_config(pname, value)
                    if src is None:
                        raise
                    raise InputError(f"{src[0]}: key {src[1]!r}: {exc}") from None
            for v in value if isinstance(value, (list, tuple)) else [value]:
                if kind == "file" and v is not None:
                    outputs[opt] = Path(v)
                elif kind == "folder" and v is not None:
                    folders[opt] = Path(v)
                elif isinstance(v, (str, Path)) and v and str(v) != "-":
                    inputs.append(Path(v))
        check_outputs(outputs, inputs, folders)

    return check
