"""``--config FILE.toml``: a command's options kept in a file (docs/conventions.md, "One vocabulary").

The keys are the command's option names without the dashes (``robot``, ``noise-pos-mm``,
``json`` …; ``noise_pos_mm`` is read the same) and its arguments' names (``data``); a table
named after a command holds the options of that command only, so that one file can serve
several commands::

    robot = "puma560"
    noise-pos-mm = 0.05

    [calibrate]
    data = ["train.csv"]
    validate = ["valid.csv"]
    known-noise = true

The file gives defaults: an option given on the command line wins. A key that is not an
option of the command (a misspelling, an option of another command) is refused, naming the
key and the file. Paths in the file are read from the current folder, as on the command line.
"""
from __future__ import annotations

from pathlib import Path

import typer

__all__ = ["apply_config", "read_config"]


def _key(text: str) -> str:
    return text.lstrip("-").replace("_", "-")


def read_config(path: Path, command: str, params, commands=()) -> dict:
    """``{parameter name: value}`` of ``command`` from the TOML file ``path``; ``params`` are the
    command's click parameters, ``commands`` the names of every command (their tables are skipped).
    Raises ``typer.BadParameter`` naming the file (and the key)."""
    import tomllib

    from estcal.base.textinput import read_text

    try:
        text = read_text(path, "TOML configuration", ValueError)
        doc = tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise typer.BadParameter(f"{path}: {exc}") from None
    by_key = {}
    for p in params:
        if p.name == "config":
            continue
        names = [o for o in getattr(p, "opts", []) + getattr(p, "secondary_opts", []) if o.startswith("--")]
        if getattr(p, "hidden", False):
            continue  # deprecated spellings stay on the command line
        for n in names or [p.name]:
            by_key[_key(n)] = p
        by_key[_key(p.name)] = p  # the argument's / parameter's own name
    commands = set(commands) | {command}
    values = {}
    for key, value in doc.items():
        if isinstance(value, dict) and key in commands:
            if key != command:
                continue  # another command's table
            items = value.items()
        else:
            items = [(key, value)]
        for k, v in items:
            p = by_key.get(_key(k))
            if p is None:
                raise typer.BadParameter(f"{path}: unknown key {k!r} — not an option of `estcal {command}` "
                                         f"(see `estcal {command} --help`)")
            if isinstance(v, dict):
                raise typer.BadParameter(f"{path}: key {k!r} holds a table; give the option's value")
            if _key(k) in {_key(o) for o in getattr(p, "secondary_opts", [])}:  # --no-x, --keep-all: the off switch
                v = not v
            values[p.name] = [str(x) if isinstance(x, Path) else x for x in v] if isinstance(v, list) else v
    return values


def apply_config(ctx: typer.Context, value: Path | None):
    """Eager callback of ``--config``: the file's values become the command's defaults."""
    if value is None or ctx.resilient_parsing:
        return value
    group = ctx.parent.command if ctx.parent is not None else None
    names = getattr(group, "commands", {}) or {}
    values = read_config(Path(value), ctx.info_name or "", ctx.command.params, names)
    ctx.default_map = {**(ctx.default_map or {}), **values}
    return value
