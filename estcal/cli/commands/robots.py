"""``estcal robots``: the robots ``--robot`` accepts by name."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import json_option

__all__ = ["robots"]


@command("robots")
def robots(json_path: Optional[Path] = json_option("Write the list as JSON.")) -> None:
    """List the built-in robots (name, joints, convention, parameters, source); any of them is a --robot."""
    from estcal.workflows.robots import builtin_robots

    rows = builtin_robots()
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        if r["available"]:
            typer.echo(f"{r['name']:<{width}}  {r['kind']:<8}  {r['joints']} joints ({r['joint_types']}), "
                       f"{r['convention']}" + (f", {r['parameters']} parameters" if "parameters" in r else "")
                       + (f" — {r['source']}" if r.get("source") else ""))
        else:
            typer.echo(f"{r['name']:<{width}}  {r['kind']:<8}  not available here: {r['reason']}")
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, rows)
        typer.echo(f"wrote {json_path}")
