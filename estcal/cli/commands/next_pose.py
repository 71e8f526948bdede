"""``estcal next-pose``: the measurement pose that most reduces a criterion of the covariance.

The state file is JSON with keys ``parameters`` (free parameter names),
``estimate`` (SI values) and ``covariance`` (p × p), e.g. written by any
estimator; a :class:`~estcal.estimate.result.CalibrationResult` JSON
(``estcal calibrate --json``) is accepted too. The predicted covariance after
measuring a candidate pose is the Kalman / MAP update
``C⁺ = C − C Hᵀ (H C Hᵀ + R)⁻¹ H C``, evaluated for all candidates at once.

JSON keys: ``robot``, ``method``, ``criterion``, ``next`` (:meth:`NextPose.to_dict`:
``readings_rad``, ``readings_deg``, ``value_before``, ``value_after``, ``reduction``,
``predicted_std``), ``test_poses_rad``; with ``--report DIR``: ``accuracy_map`` (``before``, ``after``:
predicted position-error std on the same ``--map N`` random poses, see :mod:`estcal.report.design`).
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from estcal.cli.units import deprecated_option, noise_pos_option, noise_rot_option
from estcal.base.jsonio import write_json


def register(app: typer.Typer) -> None:
    @app.command("next-pose")
    def next_pose_cmd(
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF."),
        state: Path = typer.Option(..., "--state", help="JSON with parameters, estimate, covariance."),
        criterion: Optional[str] = typer.Option(
            None, "--criterion", "-c", help="D, A, E, G, O1..O5, cond, test-pose (default: test-pose when "
                                            "--test-pose is given, else D)."),
        method: str = typer.Option("position", "--method", help="position, pose or points."),
        test_pose: Optional[List[str]] = typer.Option(
            None, "--test-pose", help="Test pose 'q1,q2,...' (revolute in deg, prismatic in mm); repeatable."),
        candidates: Optional[Path] = typer.Option(None, "--candidates", help="CSV of candidate readings (rad/m)."),
        degrees: bool = typer.Option(False, "--degrees", help="Candidate CSV revolute columns are in degrees."),
        n_candidates: int = typer.Option(2000, "--n-candidates", help="Random candidate poses when no CSV is "
                                                                      "given."),
        sigma_mm: float = noise_pos_option(0.1),
        sigma_rot_mrad: float = noise_rot_option(1.0, ", pose method"),
        old_sigma: Optional[float] = deprecated_option("--sigma"),
        old_sigma_rot: Optional[float] = deprecated_option("--sigma-rot"),
        refine: bool = typer.Option(True, "--refine/--no-refine", help="Polish the best candidate locally."),
        seed: int = typer.Option(0, "--seed"),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the proposal as JSON."),
        report: Optional[Path] = typer.Option(None, "--report", help="Folder for a report: the pose, parameter "
                                              "std before/after, predicted error over the workspace before/after "
                                              "(PNG) and index.html; adds 'accuracy_map' to the JSON."),
        map_n: int = typer.Option(500, "--map", help="Poses sampled within the joint limits for the report's "
                                  "accuracy map."),
    ) -> None:
        """Propose the next measurement pose from the current estimate and covariance."""
        import numpy as np
        from rich.console import Console

        from estcal.design._cli import default_test_pose, format_readings, parse_poses
        from estcal.design.criteria import CRITERIA, normalise_criterion
        from estcal.design.model import DesignModel, resolve_robot
        from estcal.design.plans import load_candidates
        from estcal.design.sequential import CalibrationState, propose_next_pose

        from estcal.cli.units import resolve

        sigma_mm = resolve(sigma_mm, 1.0, old_sigma, "--sigma", "--noise-pos-mm", "mm", 1.0, 0.1)
        sigma_rot_mrad = resolve(sigma_rot_mrad, 1.0, old_sigma_rot, "--sigma-rot", "--noise-rot-mrad", "mrad", 1.0,
                                 1.0)
        console = Console()
        try:
            rb = resolve_robot(robot)
            st = CalibrationState.from_json(state)
            st.check_robot(rb, str(state))
            if st.robot is not None and st.robot not in (robot, rb.name):
                from estcal.cli.common import warn

                warn(f"{state}: the state was computed for robot {st.robot!r}, not {robot!r} — its covariance "
                     f"describes that robot's parameters")
            q_test = parse_poses(test_pose, rb)
            crit = normalise_criterion(criterion or ("test-pose" if q_test is not None else "D"))
            if q_test is None and CRITERIA[crit][1]:
                q_test = default_test_pose(rb)
            model = DesignModel(rb, method, list(st.parameters), sigma=sigma_mm * 1e-3,
                                sigma_rot=sigma_rot_mrad * 1e-3 if method == "pose" else None)
            cand = None if candidates is None else load_candidates(candidates, rb, degrees)
            nxt = propose_next_pose(model, st, crit, q_test=q_test, candidates=cand, n_candidates=n_candidates,
                                    rng=seed, refine=refine)
        except (ValueError, KeyError, FileNotFoundError, np.linalg.LinAlgError) as exc:
            from estcal.cli.common import fail, message

            fail(message(exc))
        console.print(f"robot {rb.name}, method {method}, {len(st.parameters)} parameters in the state")
        console.print("next pose (" + ", ".join(rb.joint_names) + "):")
        console.print("  " + format_readings(nxt.readings, rb)[0])
        console.print(f"{crit}: {nxt.value_before:.6g} -> {nxt.value_after:.6g} "
                      f"({100 * nxt.reduction:.2f} % better, {nxt.n_candidates} candidates"
                      f"{', refined' if nxt.refined else ''})")
        out = {"robot": rb.name, "method": method, "criterion": crit, "next": nxt.to_dict(),
               "test_poses_rad": None if q_test is None else q_test.tolist()}
        maps = None
        if report is not None:
            from estcal.design.sequential import covariance_after, model_for_state

            mdl = model_for_state(model, st)
            Cp = covariance_after(mdl, st, nxt.readings)
            maps = (mdl.accuracy_map(st.covariance, n=map_n, rng=seed + 2),
                    mdl.accuracy_map(Cp, n=map_n, rng=seed + 2))  # same poses: same seed
            out["accuracy_map"] = {"before": maps[0].to_dict(), "after": maps[1].to_dict()}
        if json_path is not None:
            write_json(json_path, out)
            console.print(f"wrote {json_path}")
        if report is not None:
            from estcal.report.design import next_pose_report
            from estcal.base.units import display_unit

            next_pose_report(report, model, nxt, st, maps, unit=lambda nm: display_unit(nm, rb),
                             title=f"estcal next-pose — {rb.name}", result_dict=out)
            console.print(f"report: {report}/index.html")
