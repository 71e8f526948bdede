"""``estcal demo``: simulate → calibrate → validate on an embedded default
(:func:`estcal.workflows.demo.run_demo`)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import estimator_option, json_option

__all__ = ["demo"]


@command("demo")
def demo(
    robot: str = typer.Option("puma560", "--robot", "-r", help="Built-in robot, robot file or URDF."),
    n: int = typer.Option(50, "--n", help="Poses in the calibration set (and in the validation set)."),
    seed: int = typer.Option(0, "--seed", help="Random seed (errors, poses, noise)."),
    estimator: str = estimator_option("lm"),
    json_path: Optional[Path] = json_option("Write the summary as JSON."),
) -> None:
    """Simulate a robot with unknown geometric errors, calibrate it, validate on new poses."""
    from rich.console import Console
    from rich.table import Table
    from scipy.stats import chi2

    from estcal.base.errors import NumericalRefusal
    from estcal.workflows.demo import run_demo

    try:
        out = run_demo(robot, n, seed, estimator=estimator)
    except NumericalRefusal as exc:
        raise NumericalRefusal(f"--n {n}: {exc} (here: raise --n)") from exc
    res = out.pop("result")
    con = Console()
    con.print(f"[bold]estcal demo[/]: {out['robot']}, {n} simulated poses (full pose, CMM noise "
              f"{out['noise']['position_mm']:.3f} mm / {out['noise']['orientation_mrad']:.2f} mrad), "
              f"{out['n_estimated']} identifiable parameters, {out['n_iterations']} iterations, "
              f"converged={out['converged']}")
    t = Table(title="Position / orientation error (RMSE, max)")
    for c in ("data", "model", "RMSE mm", "max mm", "RMSE mrad", "max mrad"):
        t.add_column(c, justify="right" if c not in ("data", "model") else "left")
    for d in ("train", "validation"):
        for m in ("nominal", "calibrated"):
            a = out[d][m]
            t.add_row(d, m, f"{a['rmse_mm']:.4f}", f"{a['max_mm']:.4f}", f"{a['rmse_mrad']:.4f}",
                      f"{a['max_mrad']:.4f}")
    con.print(t)
    con.print(f"NEES of the estimate against the simulated truth: {out['nees']:.1f} "
              f"(χ² with {out['nees_dof']} dof: mean {out['nees_dof']}, 95% < {chi2.ppf(0.95, out['nees_dof']):.1f})")
    if json_path:
        from estcal.base.jsonio import write_json

        out["parameters"] = res.to_dict()["parameters"]
        write_json(json_path, out)
