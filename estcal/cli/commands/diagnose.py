"""``estcal diagnose``: what the geometric model gets wrong on measured data, and which effect explains it.

Runs :func:`estcal.discrepancy.diagnose` (geometric fit, residual analysis,
forward selection of library effects by BIC / significance test /
cross-validation, identifiability by QR) and prints the named cause(s), the
verdict and the RMSE of the geometric and extended models (train, CV,
validation). Robot and data options are those of ``estcal calibrate``.

JSON (``--json PATH``): ``causes`` (list of {``effect``, ``joints``,
``parameters`` {name: {estimate, std}}, ``delta_bic``, ``explained_fraction``,
``test``, ``p_value``, …}), ``verdict``, ``rmse_mm`` and ``max_mm``
({``geometric``, ``extended``} × {``train``, ``cv``, ``validation``}),
``analysis`` (noise floor, feature R², spectrum), ``steps`` (selection log),
``model`` (the identified robot: every parameter value, effects, gravity — the
input of ``estcal simulate --from-fit``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from estcal.cli.common import (check_distinct_poses, check_held_out, check_input_files, fail, refuse, robot_for_data,
                               save_model_or_fail, warn_datasets)

__all__ = ["register"]


_fail = fail


def register(app: typer.Typer) -> None:
    @app.command("diagnose")
    def diagnose_cmd(
        data: list[Path] = typer.Argument(..., help="Measured dataset(s) (CSV: joint columns + x,y,z / x1..zk / "
                                                    "pose); several files are several sessions, fitted together "
                                                    "(approach and time per session)."),
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF."),
        root: Optional[str] = typer.Option(None, help="URDF root link."),
        tip: Optional[str] = typer.Option(None, help="URDF tip link."),
        points: Optional[int] = typer.Option(None, "--points", help="Use the first N measured points (x1..zN)."),
        validate: list[Path] = typer.Option([], "--validate", help="Validation dataset(s) (scored, never used "
                                                                  "for decisions)."),
        effects: Optional[str] = typer.Option(None, "--effects", help="Comma-separated effect names to try "
                                                                      "(default: every registered effect)."),
        noise_pos_mm: Optional[float] = typer.Option(None, "--noise-pos-mm", help="Known position noise std (mm); "
                                                  "default unknown (F tests, no noise-floor test)."),
        old_noise_pos: Optional[float] = typer.Option(None, "--noise-pos", hidden=True),  # deprecated (m)
        k_folds: int = typer.Option(5, "--folds", help="Cross-validation folds."),
        alpha: float = typer.Option(0.01, "--alpha", help="Family-wise significance level per selection step."),
        max_effects: int = typer.Option(3, "--max-effects", help="Most effects named."),
        urdf_masses: bool = typer.Option(True, "--urdf-chain-masses/--no-urdf-chain-masses",
                                         help="For URDF robots, count the links after the last actuated "
                                              "joint (tool, sensor, gripper) in its mass."),
        geometric: str = typer.Option("full", "--geometric", help="Geometric model: full (every identifiable "
                                      "parameter) | aic (those Akaike's criterion supports) | joint_offset | "
                                      "auto (lowest cross-validated RMSE)."),
        approach_from_order: bool = typer.Option(False, "--approach-from-order",
                                                 help="Infer approach_<joint> columns from the posture order "
                                                      "(backlash by approach direction)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the fold assignment."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the diagnosis as JSON."),
        report: Optional[Path] = typer.Option(None, "--report", help="Folder for a report: residual figures "
                                              "(PNG), diagnosis.json, summary.txt and index.html with the tables."),
        save_model: Optional[Path] = typer.Option(
            None, "--save-model", help="Write the identified robot (geometry + named effects) as a robot file "
                                       "(.yaml) with a 'calibration:' block; reload it with --robot."),
    ) -> None:
        """Name the non-geometric cause of the residual of a geometric calibration and measure the gain."""
        from estcal.discrepancy import diagnose
        from estcal.estimate.lsq import UnidentifiableError
        from estcal.io import load_dataset
        from estcal.io.dataset import DatasetError

        from estcal.base.units import MILLI
        from estcal.cli.units import resolve

        noise_pos = None if noise_pos_mm is None and old_noise_pos is None else \
            resolve(noise_pos_mm or 0.0, MILLI, old_noise_pos, "--noise-pos", "--noise-pos-mm", "m", 1.0, 0.0)
        check_input_files(list(data) + list(validate))
        rob, n_markers = robot_for_data(robot, data[0], root=root, tip=tip, points=points)
        if urdf_masses and rob.meta.get("urdf"):
            from estcal.discrepancy.masses import with_urdf_masses

            rob = with_urdf_masses(rob)
        try:
            sessions = [load_dataset(d, rob, points=n_markers) for d in data]
            vals = [load_dataset(v, rob, points=n_markers) for v in validate]
        except (DatasetError, FileNotFoundError) as exc:
            _fail(str(exc))
        warn_datasets(sessions + vals)
        cands = None
        if effects:
            from estcal.effects import EFFECTS

            cands = [e.strip() for e in effects.split(",") if e.strip()]
            bad = [e for e in cands if e not in EFFECTS]
            if bad:
                _fail(f"--effects: unknown effect(s) {bad}; registered: {', '.join(sorted(EFFECTS))}")
        for d in sessions:
            check_distinct_poses(d)  # after the option checks: usage errors first
        check_held_out(sessions, [], "session")
        check_held_out(sessions, vals)
        ds = sessions[0] if len(sessions) == 1 else sessions
        n_poses = sum(d.n for d in sessions)
        where = ", ".join(str(d) for d in data)
        spec = robot if not (root or tip) else None
        try:
            res = diagnose(rob, ds, validate=vals, candidates=cands, k_folds=k_folds, noise=noise_pos, alpha=alpha,
                           max_effects=max_effects, report=report, rng=seed, robot_spec=spec, geometric=geometric,
                           approach_from_order=approach_from_order)
        except UnidentifiableError as exc:
            refuse(f"{where}: {exc} (the geometric fit on {n_poses} poses, and each cross-validation fold of "
                   f"--folds {k_folds}, needs more equations than parameters)")
        except ValueError as exc:
            _fail(str(exc))
        res.model["robot_spec"] = robot
        res.model["root"], res.model["tip"] = root, tip
        res.model["urdf_chain_masses"] = bool(urdf_masses and rob.meta.get("urdf"))
        typer.echo(str(res))
        if report is not None:
            from estcal.report.diagnose import diagnose_report

            res.to_json(Path(report) / "diagnosis.json")
            diagnose_report(report, res, title=f"estcal diagnose — {rob.name}, {where}")
            typer.echo(f"report: {report}/index.html ({', '.join(res.report_files)})")
        if json_path:
            res.to_json(json_path)
            typer.echo(f"wrote {json_path}")
        if save_model:
            typer.echo(save_model_or_fail(res, save_model, robot, root, tip))
