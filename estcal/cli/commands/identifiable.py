"""``estcal identifiable``: identifiable (base) parameters of a robot for a measurement.

Runs :func:`estcal.workflows.identifiable.identifiable` (GECARO App. III) on random admissible
configurations (``--n-poses``, ``--seed``) or on a dataset (``--data``, which also checks its
excitation against random configurations). Prints a table (parameter, status, priority,
``|R_jj|``, regrouping relation) and writes JSON with ``--json``:
``n_parameters``, ``n_identifiable``, ``identifiable``, ``no_effect``,
``regrouped`` ([{parameter, relation: {base: coefficient}, formula}]),
``relations`` ({base: "base + c*other …"}), ``excluded``, ``condition_number``,
``tau``, ``rank_gap``, ``qr``, ``priorities``, ``priorities_out`` (GECARO's output
priority matrix: non-identifiable set to 0), ``excitation`` (with ``--data``), and
``robot``, ``method`` (the measurement), ``source``, ``n_poses``, ``rules``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import (json_option, map_option, measure_option, method_option, points_option, root_option,
                                tip_option)

__all__ = ["identifiable"]

MEASURE_HELP = ("position, pose, point-link, frame-link, plane-known, plane-unknown, plane-normal-known, "
                "plane-normal-unknown, distance (default with --data: from the columns)")


def _print(console, res) -> None:
    from rich.markup import escape
    from rich.table import Table

    if isinstance(res, dict):  # Gough platform
        console.print(f"[bold]{res.get('robot')}[/bold]: {res['n_identifiable']} of {res['n_parameters']} "
                      f"identifiable, condition number {res['condition_number']:.4g}")
        console.print("no effect: " + (", ".join(res["no_effect"]) or "—"))
        for r in res["regrouped"]:
            console.print(f"regrouped: {r['parameter']} = " + " + ".join(f"{v:.6g}*{k}"
                                                                          for k, v in r["combination"].items()))
        return
    m = res.meta
    t = Table(title=f"{m.get('robot')} — {m.get('method')}: {res.n_identifiable} of {res.n_parameters} "
                    f"parameters identifiable")
    for col in ("parameter", "status", "priority", "|R_jj| (scaled)", "base parameter estimates / absorbed by"):
        t.add_column(col, justify="right" if col.startswith(("priority", "|R")) else "left")
    regr = {r["parameter"]: r for r in res.regrouped}
    label = {"": "[green]identifiable[/green]", "0": "[red]no effect (0)[/red]", "n": "[yellow]regrouped (n)[/yellow]",
             "x": "[dim]excluded (priority 0)[/dim]"}
    for name in res.names + res.excluded:
        st = res.status(name)
        if st == "":
            rel = res.relations.get(name, name)
            rel = "" if rel == name else rel
        elif st == "n":
            rel = ", ".join(f"{k} ({v:+.6g})" for k, v in regr[name]["relation"].items())
        else:
            rel = ""
        rd = res.r_diag.get(name)
        t.add_row(name, label[st], str(res.priorities.get(name, "")), "" if rd is None else f"{rd:.3g}", rel)
    console.print(t)
    lo, hi = res.rank_gap
    n, nd = m.get("n_poses"), m.get("n_distinct", m.get("n_poses"))
    configs = f"{n} configurations" if nd == n else f"{n} poses, {nd} distinct configuration{'s' if nd != 1 else ''}"
    console.print(f"rows {res.n_rows}, source: {m.get('source')} ({configs}"
                  f"{', seed ' + str(m['seed']) if 'seed' in m else ''}), priority rules: {m.get('rules')}")
    console.print(f"QR: {res.qr}; τ = {res.tau:.3g}; gap: smallest kept |R_jj| {lo:.3g}, largest rejected {hi:.3g}")
    console.print(f"condition number of the column-scaled W_b: {res.condition_number:.4g}")
    for note in m.get("notes", []):
        console.print(f"[dim]note: {note}[/dim]")
    lines = res.excitation_lines()
    if lines:
        colr = "green" if res.excitation["same_set"] else "red"
        console.print(f"[{colr}]{escape(lines[0])}[/{colr}]")
        for line in lines[1:]:
            console.print(escape(line))


@command("identifiable")
def identifiable(
    robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml), URDF, or Gough file."),
    measure: Optional[str] = measure_option(None, MEASURE_HELP),
    method: Optional[str] = method_option(),
    data: Optional[Path] = typer.Option(None, "--data", help="Dataset CSV: analyse its configurations and "
                                                             "check its excitation."),
    column_map: Optional[Path] = map_option(),
    n_poses: int = typer.Option(60, "--n-poses", help="Random admissible configurations (raised when too few)."),
    seed: int = typer.Option(0, "--seed"),
    priority: Optional[Path] = typer.Option(None, "--priority", help="YAML {name or pattern: priority} or "
                                                                     "{matrix: [[α,d,θ,r,β,K], …]}; 0 = do "
                                                                     "not identify."),
    free: Optional[str] = typer.Option(None, "--free", help="Comma-separated names/patterns to analyse "
                                                            "(default: all free parameters)."),
    rules: str = typer.Option("gecaro", "--rules", help="Default priorities: gecaro (GECARO §1.5) or order "
                                                        "(parameter-vector order)."),
    pivoting: bool = typer.Option(False, "--pivoting", help="QR with column pivoting (ignores priorities)."),
    plane: Optional[str] = typer.Option(None, "--plane", help="a,b,c of a x + b y + c z + 1 = 0 in 1/m (x, y, z in "
                                                              "metres as in the dataset; SI like the files) "
                                                              "(plane-known, plane-normal-known)."),
    points: Optional[int] = points_option("Use the first N measured points."),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    tau_floor: float = typer.Option(1e-10, "--tau-floor", help="Floor of the numerical zero on unit-norm "
                                                               "columns (0: GECARO eq. 34 only)."),
    json_path: Optional[Path] = json_option(),
) -> None:
    """Identifiable, no-effect and regrouped parameters (GECARO App. III) for a measurement."""
    from rich.console import Console

    from estcal.cli.common import warn
    from estcal.cli.options import estimator_and_measure
    from estcal.workflows.identifiable import identifiable as run

    measure = estimator_and_measure(method, None, measure, means="measure")[1]
    console = Console()
    res = run(robot, measure, data, n_poses, seed, priority, free, rules, pivoting, plane, points, root, tip, tau_floor,
              column_map=column_map)
    nd = None if isinstance(res, dict) else res.meta.get("n_distinct")
    if data is not None and nd is not None and nd < res.meta.get("n_poses", 0):
        warn(f"{data}: {res.meta['n_poses']} poses but only {nd} distinct joint configuration{'s' if nd != 1 else ''}"
             f" — a repeated pose adds no information: the analysis is that of {nd} configuration"
             f"{'s' if nd != 1 else ''}")
    if data is not None and not isinstance(res, dict) and res.n_rows < res.n_parameters:
        warn(f"{data}: {res.n_rows} equations ({res.meta.get('n_poses')} poses) for {res.n_parameters} "
             f"parameters — at most {res.n_rows} can be identifiable from these data, whatever the robot; "
             f"without --data the structural analysis uses random configurations (--n-poses)")
    _print(console, res)
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, res if isinstance(res, dict) else res.to_dict())
        console.print(f"wrote {json_path}")
