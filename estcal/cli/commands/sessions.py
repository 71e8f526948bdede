"""``estcal sessions``: calibration over several sessions with a repeatability model.

Each DATA file is one session (or one file with a ``session`` column holds them
all). The population parameters are shared; the parameters given by ``--vary``
(or chosen by the REML likelihood-ratio test with ``--vary auto``) get one
deviation per session, ``u_s ~ N(0, Q)``, whose variance components Q are
estimated by REML (:mod:`estcal.sessions`, docs/repeatability.md). Prints the
between-session std of every varying parameter (mm / mrad), each session's
deviation, and scores ``--validate`` sessions against the new-session 95 %
prediction ellipsoids (θ covariance + Q).

JSON (``--json PATH``): ``parameters`` {name: {estimate, std}} (SI), ``vary``,
``variance_components`` [{parameter, std, std_err, unit}] (mm / mrad),
``session_deviations``, ``q`` (SI²), ``s2``, ``vary_selection`` (with ``--vary
auto``), ``validation`` {file: {rmse_mm, rmse_mm_per_point, coverage,
coverage_per_point, band}}, ``recalibration`` (with ``--recalibrate K``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.common import check_held_out, check_input_files, fail, refuse, robot_for_data, warn, warn_datasets

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    @app.command("sessions")
    def sessions_cmd(
        data: list[Path] = typer.Argument(..., help="One CSV per session (or one CSV with a 'session' column)."),
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF."),
        root: Optional[str] = typer.Option(None, help="URDF root link."),
        tip: Optional[str] = typer.Option(None, help="URDF tip link."),
        points: Optional[int] = typer.Option(None, "--points", help="Use the first N measured points (x1..zN)."),
        level: str = typer.Option("joint_offset", "--level", help="Free set: registration, joint_offset or full "
                                                                 "(identifiable by QR on the stacked sessions)."),
        free: Optional[str] = typer.Option(None, "--free", help="Explicit free set (names or patterns, "
                                                              "comma-separated) instead of --level."),
        vary: str = typer.Option("auto", "--vary", help="Parameters that vary between sessions (comma-separated "
                                                        "names, or patterns matched among the free parameters), "
                                                        "'auto' (REML likelihood-ratio selection among the free "
                                                        "offsets and base) or 'none'."),
        formulation: str = typer.Option("gls", "--formulation", help="gls, gtsam (factor graph) or kalman "
                                                                     "(filterpy); they agree."),
        noise_pos_mm: float = typer.Option(0.1, "--noise-pos-mm", help="Position noise std per coordinate (mm)."),
        noise_rot_mrad: float = typer.Option(1.0, "--noise-rot-mrad", help="Orientation noise std (mrad)."),
        known_noise: bool = typer.Option(False, "--known-noise", help="Trust the noise values (else a variance "
                                                                      "factor is estimated with Q by REML)."),
        validate: list[Path] = typer.Option([], "--validate", help="New session(s): scored, never used for a "
                                                                  "decision."),
        recalibrate: int = typer.Option(0, "--recalibrate", help="With --validate: error on the rest of each "
                                                                 "new session after re-measuring k = 0…K poses "
                                                                 "(number of poses)."),
        alpha: float = typer.Option(0.01, "--alpha", help="Significance level of the --vary auto selection."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the fit as JSON (SI units)."),
    ) -> None:
        """Calibrate several sessions at once, with per-session deviations (repeatability as process noise)."""
        import numpy as np

        from estcal.estimate.levels import LEVELS, select_free
        from estcal.io import load_dataset
        from estcal.io.dataset import DatasetError
        from estcal.cli.checks import check_outputs
        from estcal.base.jsonio import write_json
        from estcal.methods import NoiseModel, Problem
        from estcal.sessions import choose_vary, fit_sessions, predict_session, recalibration_curve
        from estcal.sessions.data import session_name, split_sessions

        if formulation not in ("gls", "gtsam", "kalman"):
            fail(f"--formulation must be gls, gtsam or kalman, got {formulation!r}")
        if level not in LEVELS:
            fail(f"--level must be one of {', '.join(LEVELS)}, got {level!r}")
        if not noise_pos_mm > 0 or not noise_rot_mrad > 0:
            fail("--noise-pos-mm and --noise-rot-mrad must be > 0")
        if recalibrate < 0:
            fail("--recalibrate must be ≥ 0")
        check_outputs({"--json": json_path}, list(data) + list(validate))
        check_input_files(list(data) + list(validate))
        rob, n_markers = robot_for_data(robot, data[0], root=root, tip=tip, points=points)
        try:
            loaded = [load_dataset(d, rob, points=n_markers) for d in data]
            vals = [load_dataset(v, rob, points=n_markers) for v in validate]
        except (DatasetError, FileNotFoundError) as exc:
            fail(str(exc))
        try:
            sessions = [s for d in loaded for s in split_sessions(d)]
        except ValueError as exc:
            fail(str(exc))
        warn_datasets(loaded + vals)
        check_held_out(loaded, [], "session")
        check_held_out(loaded, vals)
        names = [session_name(s, i) for i, s in enumerate(sessions)]
        if len(set(names)) < len(names):
            names = [f"{n}#{i + 1}" for i, n in enumerate(names)]
        noise = NoiseModel(position=noise_pos_mm * 1e-3, orientation=noise_rot_mrad * 1e-3,
                           scalar=noise_pos_mm * 1e-3, known=known_noise)
        prob = Problem(rob, [(None, s, noise) for s in sessions], noise)
        try:
            if free:
                free_names = prob.with_free([f.strip() for f in free.split(",") if f.strip()]).params.free_names
                theta0 = prob.params.values
            else:
                sel = select_free(prob, level)
                free_names, theta0 = sel.identifiable, sel.theta
        except (ValueError, KeyError) as exc:
            fail(f"--free/--level: {exc.args[0] if exc.args else exc}")
        typer.echo(f"estcal sessions: {len(sessions)} sessions ({', '.join(f'{n}: {s.n}' for n, s in zip(names, sessions))}"
                   f" poses), {len(free_names)} free parameters")
        selection = None
        try:
            if vary == "auto":
                if len(sessions) < 2:
                    warn("one session: no between-session information, --vary auto selects nothing")
                cands = [n for n, k in zip(prob.params.names, prob.params.kinds)
                         if n in free_names and k in ("offset", "base")]
                selection = choose_vary(rob, sessions, free_names, cands, noise=noise, alpha=alpha, theta=theta0)
                vary_names = selection["vary"]
            elif vary == "none":
                vary_names = []
            else:
                import fnmatch

                pats = [v.strip() for v in vary.split(",") if v.strip()]
                try:
                    prob.with_free(pats)  # ParameterError naming an unknown name / pattern
                except (ValueError, KeyError) as exc:
                    fail(f"--vary: {exc.args[0] if exc.args else exc}")
                # a pattern selects among the estimated parameters; a name must be one of them
                wild = [p for p in pats if any(ch in p for ch in "*?[")]
                bad = [p for p in pats if p not in wild and p not in free_names]
                empty = [p for p in wild if not any(fnmatch.fnmatchcase(n, p) for n in free_names)]
                if bad or empty:
                    what = f"{bad} are not free parameters" if bad else f"{empty} match no free parameter"
                    fail(f"--vary: {what} (a varying parameter must be estimated); the free set is "
                         f"{', '.join(free_names)}")
                vary_names = [n for n in free_names if n in pats or any(fnmatch.fnmatchcase(n, p) for p in wild)]
            fit = fit_sessions(rob, sessions, free_names, vary_names, noise=noise, formulation=formulation,
                               theta=theta0, session_names=names)
        except ValueError as exc:
            refuse(str(exc))
        if not fit.converged:
            warn(f"the session fit did not converge in {fit.n_iterations} iterations")
        typer.echo(f"{formulation}: {fit.n_iterations} iterations, converged={fit.converged}, "
                   f"variance factor s² = {fit.s2:.3g}{' (known noise)' if known_noise else ''}")
        if fit.vary:
            typer.echo("between-session variation (REML):")
            for v in fit.variance_components():
                err = f" ± {v['std_err']:.3g}" if np.isfinite(v["std_err"]) else ""
                typer.echo(f"  {v['parameter']:<24} std {v['std']:.4g}{err} {v['unit']}")
            typer.echo("session deviations:")
            for s, u in zip(fit.sessions, fit.u):
                cells = []
                for n, x in zip(fit.vary, u):
                    unit = next(v["unit"] for v in fit.variance_components() if v["parameter"] == n)
                    cells.append(f"{n} {x * 1e3:+.3f} {unit}")
                typer.echo(f"  {s}: " + ", ".join(cells))
        else:
            typer.echo("no parameter varies between sessions" + (" (LR test)" if vary == "auto" else ""))
        out = fit.to_dict()
        if selection is not None:
            out["vary_selection"] = [{"accepted": st["accepted"], "alpha_per_test": st["alpha_per_test"],
                                      "table": [{k: v for k, v in e.items() if k != "std"} for e in st["table"]]}
                                     for st in selection["steps"]]
        out["validation"], out["recalibration"] = {}, {}
        for v, d in zip(validate, vals):
            try:
                sc = predict_session(fit, d)
            except ValueError as exc:
                fail(f"{v}: {exc}")
            sc.pop("d2")
            out["validation"][v.name] = sc
            typer.echo(f"validate {v.name}: RMSE {sc['rmse_mm']:.3f} mm, 95 % coverage {sc['coverage']:.2f} "
                       f"(binomial band {sc['band'][0]:.2f}–{sc['band'][1]:.2f})")
            if recalibrate:
                rc = recalibration_curve(fit, d, range(0, min(recalibrate, d.n - 1) + 1))
                out["recalibration"][v.name] = rc
                typer.echo("  re-measuring k poses (covariance rule): " +
                           ", ".join(f"k={k} {e:.3f} mm" for k, e in zip(rc["k"], rc["rmse_mm"])))
        if json_path:
            write_json(json_path, out)
            typer.echo(f"wrote {json_path}")
