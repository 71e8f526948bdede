"""``estcal identifiable``: identifiable (base) parameters of a robot for a measurement method.

Builds the observation matrix of the method from random admissible
configurations (``--n-poses``, ``--seed``; inverse geometric model for the link
methods, plane-constrained points for the planar ones) or from a dataset
(``--data``, which also checks its excitation against random configurations),
and runs the priority-ordered QR of GECARO App. III
(:func:`estcal.identify.identify`). Prints a table (parameter, status,
priority, ``|R_jj|``, regrouping relation) and writes JSON with ``--json``:
``n_parameters``, ``n_identifiable``, ``identifiable``, ``no_effect``,
``regrouped`` ([{parameter, relation: {base: coefficient}, formula}]),
``relations`` ({base: "base + c*other …"}), ``excluded``, ``condition_number``,
``tau``, ``rank_gap``, ``qr``, ``priorities``, ``priorities_out`` (GECARO's output
priority matrix: non-identifiable set to 0), ``excitation`` (with ``--data``), and
``robot``, ``method``, ``source``, ``n_poses``, ``rules``.

A Gough-platform robot file (``type: gough``) is dispatched to
:func:`estcal.workflows.gough.identifiable_gough`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from estcal.base.jsonio import write_json

METHOD_HELP = ("position, location, point-link, frame-link, plane-known, plane-unknown, plane-normal-known, "
               "plane-normal-unknown, distance (default with --data: from the columns)")


def _plane(text: Optional[str]):
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--plane expects three numbers a,b,c (a x + b y + c z + 1 = 0, 1/m), got {text!r}") from None
    if len(vals) != 3:
        raise ValueError(f"--plane expects three numbers a,b,c, got {len(vals)}")
    if not all(v == v and abs(v) != float("inf") for v in vals) or not any(vals):
        raise ValueError(f"--plane {text}: a, b, c must be finite and not all zero (a x + b y + c z + 1 = 0, 1/m)")
    return vals


def run_identifiable(robot: str, method: Optional[str] = None, data: Optional[Path] = None, n_poses: int = 60,
                     seed: int = 0, priority: Optional[Path] = None, free: Optional[str] = None,
                     rules: str = "gecaro", pivoting: bool = False, plane: Optional[str] = None,
                     points: Optional[int] = None, root: Optional[str] = None, tip: Optional[str] = None,
                     tau_floor: float = 1e-10):
    """The command without the printing: returns an IdentifiabilityResult (or the Gough dict)."""
    from estcal.identify import identify, load_priorities
    from estcal.io.dataset import load_dataset
    from estcal.io.robotfile import load_robot

    try:
        from estcal.parallel import is_gough_file
    except ImportError:  # pragma: no cover - parallel package optional
        is_gough_file = None
    if is_gough_file is not None and is_gough_file(robot):
        from estcal.workflows.gough import identifiable_gough

        return identifiable_gough(robot, data, n_poses=n_poses, seed=seed,
                                  free=None if free is None else [f.strip() for f in free.split(",")])
    rb = load_robot(robot, root=root, tip=tip)
    ds = None
    if data is not None:
        ds = load_dataset(data, rb)
        k = points if points is not None else (ds.n_points if ds.kind == "points" else None)
        if k and k > 1 and rb.n_markers != k:
            rb = load_robot(robot, root=root, tip=tip, n_markers=k)
        if points is not None:
            ds = ds.with_points(points)
    elif points:
        rb = load_robot(robot, root=root, tip=tip, n_markers=points)
    if method is None and ds is None:
        raise ValueError("give --method (one of " + METHOD_HELP + ") or --data")
    if method == "points" and ds is None:
        raise ValueError("method 'points' needs --data (several measured points); use position/location for "
                         "random configurations")
    options = {}
    pl = _plane(plane)
    if pl is not None:
        if method not in ("plane-known", "plane-normal-known"):
            raise ValueError("--plane applies to plane-known and plane-normal-known")
        options["plane"] = pl
    gen = {"plane": pl} if (pl is not None and ds is None) else None
    prio = load_priorities(priority) if priority is not None else None
    cands = None if free is None else [f.strip() for f in free.split(",") if f.strip()]
    return identify(rb, method, ds, n_poses=n_poses, seed=seed, priorities=prio, rules=rules, candidates=cands,
                    pivoting=pivoting, method_options=options, generator_options=gen, tau_floor=tau_floor)


def _print(console, res) -> None:
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
    console.print(f"rows {res.n_rows}, source: {m.get('source')} ({m.get('n_poses')} configurations"
                  f"{', seed ' + str(m['seed']) if 'seed' in m else ''}), priority rules: {m.get('rules')}")
    console.print(f"QR: {res.qr}; τ = {res.tau:.3g}; gap: smallest kept |R_jj| {lo:.3g}, largest rejected {hi:.3g}")
    console.print(f"condition number of the column-scaled W_b: {res.condition_number:.4g}")
    for note in m.get("notes", []):
        console.print(f"[dim]note: {note}[/dim]")
    if res.excitation:
        ex = res.excitation
        colr = "green" if ex["same_set"] else "red"
        console.print(f"[{colr}]excitation: same identifiable set as random configurations: {ex['same_set']}"
                      f"[/{colr}] (condition number {ex['condition_number']:.4g} vs "
                      f"{ex['random_condition_number']:.4g} with random configurations)")
        if ex["missing"]:
            console.print(f"  not identifiable from these data: {', '.join(ex['missing'])}")
        if ex["extra"]:
            console.print(f"  identifiable only from these data: {', '.join(ex['extra'])}")


def register(app: typer.Typer) -> None:
    @app.command("identifiable")
    def identifiable_cmd(
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml), URDF, or Gough file."),
        method: Optional[str] = typer.Option(None, "--method", "-m", help=METHOD_HELP),
        data: Optional[Path] = typer.Option(None, "--data", help="Dataset CSV: analyse its configurations and "
                                                                 "check its excitation."),
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
        points: Optional[int] = typer.Option(None, "--points", help="Use the first N measured points."),
        root: Optional[str] = typer.Option(None, help="URDF root link."),
        tip: Optional[str] = typer.Option(None, help="URDF tip link."),
        tau_floor: float = typer.Option(1e-10, "--tau-floor", help="Floor of the numerical zero on unit-norm "
                                                                   "columns (0: GECARO eq. 34 only)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON."),
    ) -> None:
        """Identifiable, no-effect and regrouped parameters (GECARO App. III) for a measurement method."""
        from rich.console import Console

        console = Console()
        try:
            res = run_identifiable(robot, method, data, n_poses, seed, priority, free, rules, pivoting, plane,
                                   points, root, tip, tau_floor)
        except (ValueError, KeyError, FileNotFoundError, RuntimeError) as exc:
            msg = exc.args[0] if exc.args and isinstance(exc.args[0], str) else str(exc)
            from estcal.cli.common import fail

            if free is not None and msg.startswith(("unknown parameter", "patterns ")):
                msg = f"--free: {msg}"

            fail(msg)
        if data is not None and not isinstance(res, dict) and res.n_rows < res.n_parameters:
            from estcal.cli.common import warn

            warn(f"{data}: {res.n_rows} equations ({res.meta.get('n_poses')} poses) for {res.n_parameters} "
                 f"parameters — at most {res.n_rows} can be identifiable from these data, whatever the robot; "
                 f"without --data the structural analysis uses random configurations (--n-poses)")
        _print(console, res)
        if json_path is not None:
            d = res if isinstance(res, dict) else res.to_dict()
            write_json(json_path, d)
            console.print(f"wrote {json_path}")
