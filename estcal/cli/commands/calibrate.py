"""``estcal calibrate``: batch estimation of a robot's parameters from a measurement file.

The command is a thin shell around :func:`estcal.estimate.levels.run_calibration`
(reused by the experiments); it goes through five steps:

1. **Robot** — :func:`estcal.io.robotfile.load_robot` (built-in name, robot
   file, URDF with ``--root/--tip``), with as many unknown markers as measured
   points. A Gough-platform robot file is handed to
   :func:`estcal.workflows.gough.calibrate_gough`.
2. **Measurement** — from the columns (``x,y,z`` → position of the tool origin;
   ``x1..zk`` → k points with unknown coordinates in the tool frame, ``--points N``
   keeps the first N; ``x,y,z,qw..qz`` → location), or a method named by
   ``--measure``/``--method`` (``position``, ``location``, ``point-link`` …).
3. **Initial guess** — data in an unknown frame (points / poses) are first
   registered: the base transform is set by Kabsch/Horn
   (:func:`estcal.estimate.register_base`).
4. **Free set** — ``--free`` (names or shell patterns) or ``--level``:

   * ``registration``: base (6) + markers (or the tool frame when no markers);
   * ``joint_offset``: + joint offsets;
   * ``full``: + geometric and tool parameters.

   Every level is reduced to an identifiable set on the calibration data only
   (never the validation files) by :func:`estcal.estimate.levels.select_free`
   (QR in GECARO priority order; ``--selection aic|bic`` adds greedy pruning).
5. **Estimation** — any estimator of :mod:`estcal.estimate.registry`
   (``lm``, ``gauss-newton``, ``iterated-lls``, ``scipy-lm``, ``gtsam``, ``kalman``,
   ``mcmc`` …), then a report: parameter table (estimate ± std, regrouped
   names), RMSE/mean/max position (mm) and orientation (mrad) before/after on
   the calibration file and on each ``--validate`` file in order.

JSON (``--json PATH``): :meth:`CalibrationResult.to_dict` — ``parameters``
({name: {estimate, std, nominal}}), ``rmse_mm`` ({train, train_before,
validation: [..]}), ``n_iterations``, ``converged``, ``accuracy`` … — plus
``selection`` (level, criterion, identifiable, no_effect, regrouped,
condition_number), ``robot``, ``data``, ``validate``, ``measure``, ``estimator``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from estcal.cli.common import (check_held_out, check_input_files, count_point_columns, fail, robot_for_data,
                               save_model_or_fail, warn, warn_datasets, write_json)
from estcal.cli.units import deprecated_option, noise_pos_option, noise_rot_option
from estcal.base.units import display_unit as _unit  # printed unit and factor from SI of a parameter
from estcal.estimate.levels import LEVELS, Selection, level_candidates, run_calibration, select_free

__all__ = ["register", "Selection", "select_free", "level_candidates", "run_calibration",
           "count_point_columns", "LEVELS"]

# --------------------------------------------------------------------------- helpers


def _fmt(v, nd=3):
    return "—" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{nd}f}"


def _print_report(console, res, sel, robot, data_path, validate_paths, measure_name, estimator):
    from rich.table import Table

    title = (f"estcal calibrate — {robot.name}, {measure_name}, estimator {estimator}: "
             f"{len(res.names)} parameters, {res.n_iterations} iterations, "
             f"{'converged' if res.converged else 'NOT converged'}, σ0 = {res.sigma0:.3g} "
             f"(covariance {res.covariance_source})")
    t = Table(title=title, title_justify="left")
    for c, j in (("parameter", "left"), ("initial", "right"), ("estimate", "right"), ("± std", "right"),
                 ("unit", "left")):
        t.add_column(c, justify=j)
    for n, v, e, s in zip(res.names, res.nominal, res.estimate, res.std):
        u, f = _unit(n, robot)
        label = sel.regroup_label(n) if sel is not None else n
        t.add_row(label, f"{v * f:.5g}", f"{e * f:.5g}", f"{s * f:.3g}", u)
    console.print(t)
    if sel is not None:
        msg = f"selection: level {sel.level}, criterion {sel.criterion}, condition number {sel.condition_number:.3g}"
        if sel.no_effect:
            msg += f"\n  no effect on these data: {', '.join(sel.no_effect)}"
        if sel.regrouped:
            msg += f"\n  regrouped (absorbed by the kept parameters shown in brackets): {', '.join(sel.regrouped)}"
        if sel.rejected:
            msg += f"\n  identifiable but not supported by AIC (kept nominal): {', '.join(sel.rejected)}"
        console.print(msg)
    elif (res.extra.get("selection") or {}).get("source"):
        s = res.extra["selection"]
        console.print(f"selection: level {s['level']}, criterion {s['criterion']}: {s['source']} "
                      f"({len(s['identifiable'])} parameters, as identified at the design geometry)")
    reg = res.extra.get("regularization")
    prior = res.extra.get("prior")
    if prior:
        taus = sorted(set(prior["std"].values()))
        line = (f"prior (MAP): std {', '.join(f'{t * 1e3:.3g}' for t in taus)} mm / mrad on {len(prior['std'])} "
                f"parameters, effective number of parameters {prior['effective_parameters']:.1f}")
        if reg:
            line += (f"\n  width chosen by leave-one-pose-out CV on the calibration file: RMSE "
                     f"{reg['loo_rmse_mm']:.3f} mm (unregularised {reg['loo_rmse_unregularised_mm']:.3f} mm)")
        console.print(line)
    elif reg:
        console.print(f"regularization: leave-one-pose-out CV prefers no prior (unregularised "
                      f"{reg['loo_rmse_unregularised_mm']:.3f} mm)")
    acc = res.accuracy or {}
    a = Table(title="accuracy (position mm, orientation mrad)", title_justify="left")
    for c in ("data", "poses", "RMSE before", "RMSE after", "mean after", "max after", "rot RMSE before",
              "rot RMSE after", "rot max after"):
        a.add_column(c, justify="left" if c == "data" else "right")
    rows = []
    if "train" in acc:
        rows.append((f"calibration: {data_path}", acc["train"]))
    for p, v in zip(validate_paths, acc.get("validation", [])):
        rows.append((f"validation: {p}", v))
    for label, d in rows:
        b, af = d.get("before", {}), d.get("after", {})
        a.add_row(label, str(af.get("n_poses", "")), _fmt(b.get("rmse_mm")), _fmt(af.get("rmse_mm")),
                  _fmt(af.get("mean_mm")), _fmt(af.get("max_mm")), _fmt(b.get("rmse_mrad")),
                  _fmt(af.get("rmse_mrad")), _fmt(af.get("max_mrad")))
    console.print(a)
    console.print("'before' = initial guess: " + res.extra.get("initial_guess", "nominal"))
    from estcal.report.tables import mcmc_table, rich_table

    mt = mcmc_table(res, lambda n: _unit(n, robot))  # MCMC: credible intervals, ESS and τ per parameter
    if mt is not None:
        console.print(rich_table(mt))
        console.print(mt.note)
    if isinstance(res.extra.get("robust_report"), dict):
        from estcal.estimate.robust import format_report

        console.print(format_report(res.extra["robust_report"]), soft_wrap=True)
    for w in (res.extra.get("reliability") or {}).get("warnings", []):
        console.print(f"warning: {w}", soft_wrap=True)


def _regularize(value):
    """``--regularize`` value: None, 'loo', or a positive prior std in milli-units (``2mm`` or
    ``2mrad``: 0.002 m / rad); a bare number is the deprecated SI form (warned)."""
    if value is None or value == "loo":
        return value
    text = str(value).strip()
    scale = 1e-3 if text.endswith(("mm", "mrad")) else 1.0
    try:
        tau = float(text.removesuffix("mrad").removesuffix("mm")) * scale
    except ValueError:
        _fail(f"--regularize must be 'loo' or a prior std with its unit (e.g. 2mm; mm for lengths, mrad for "
              f"angles), got {value!r}")
    if scale == 1.0:
        typer.echo(f"warning: --regularize {value} without a unit is read as SI (m / rad), deprecated; "
                   f"write --regularize {tau * 1e3:g}mm", err=True)
    if not tau > 0:
        _fail(f"--regularize: the prior std must be > 0, got {value}")
    return tau


def _parse_options(items) -> dict:
    """``KEY=VALUE`` strings -> dict; values parsed as YAML scalars (numbers, booleans, strings)."""
    import yaml

    out = {}
    for item in items:
        if "=" not in item:
            _fail(f"--option {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        val = yaml.safe_load(v)
        if isinstance(val, str):  # YAML 1.1 reads 1e-7 (no dot) as a string: a number is meant
            try:
                val = float(val)
            except ValueError:
                pass
        out[k.strip()] = val
    return out


_fail = fail


# --------------------------------------------------------------------------- command
def register(app: typer.Typer) -> None:
    @app.command("calibrate")
    def calibrate(
        data: list[Path] = typer.Argument(..., help="Calibration dataset (CSV: joint columns + x,y,z / x1..zk / "
                                                    "pose); several files are several sessions, fitted with one "
                                                    "parameter set (per-session deviations: estcal sessions)."),
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF."),
        root: Optional[str] = typer.Option(None, help="URDF root link."),
        tip: Optional[str] = typer.Option(None, help="URDF tip link."),
        method: Optional[str] = typer.Option(
            None, "--method", "-m",
            help="A measurement method (position, location, point-link, …) or an estimator (lm, gauss-newton, "
                 "iterated-lls, scipy-lm, gtsam, isam2, kalman, ukf, mcmc); dispatched by name."),
        estimator: Optional[str] = typer.Option(None, "--estimator", help="Estimator name (default lm)."),
        measure: Optional[str] = typer.Option(None, "--measure", help="Measurement method name (default: "
                                                                      "from the columns)."),
        free: Optional[str] = typer.Option(None, "--free", help="Comma-separated parameter names or patterns "
                                                                "to estimate (e.g. 'base_*,marker1_*,offset_*')."),
        level: Optional[str] = typer.Option(None, "--level", help="registration | joint_offset | full "
                                                                  "(default full when --free is not given)."),
        selection: Optional[str] = typer.Option(None, "--selection",
                                                help="structural (default: every identifiable parameter, QR) | "
                                                     "aic | bic (greedy pruning by an information criterion)."),
        regularize: Optional[str] = typer.Option(
            None, "--regularize", help="Gaussian prior toward the nominal joint-model parameters (MAP): "
                                       "'loo' (width chosen by leave-one-pose-out CV on the calibration file) "
                                       "or a prior std with its unit, e.g. 2mm (mm for lengths, mrad for angles, 10⁻³ "
                                       "for gains). Base frame and points stay free."),
        validate: list[Path] = typer.Option([], "--validate", help="Validation dataset; repeat the option for several, scored in order."),
        points: Optional[int] = typer.Option(None, "--points", help="Use the first N measured points (x1..zN)."),
        noise_pos_mm: float = noise_pos_option(0.1),
        noise_rot_mrad: float = noise_rot_option(1.0),
        old_noise_pos: Optional[float] = deprecated_option("--noise-pos"),
        old_noise_rot: Optional[float] = deprecated_option("--noise-rot"),
        known_noise: bool = typer.Option(False, "--known-noise", help="Trust the noise values (covariance not "
                                                                      "rescaled by σ0²)."),
        noise_leg_mm: Optional[float] = typer.Option(None, "--noise-leg-mm", help="Gough platforms: leg-length "
                                                                                  "noise std (mm)."),
        old_noise_leg: Optional[float] = deprecated_option("--noise-leg"),
        residual: str = typer.Option("ik", "--residual", help="Gough platforms: ik (leg lengths from the "
                                                              "measured pose) or fk (pose from the legs)."),
        gough_model: int = typer.Option(42, "--model", help="Gough platforms: 42 (attachment points + leg "
                                                            "offsets) or 36 (offsets known)."),
        robust: Optional[str] = typer.Option(None, "--robust", help="Robust kernel huber | cauchy (thresholds "
                                             "1.345 / 2.385 σ, --option robust_k=K): lm, gauss-newton, iterated-lls, "
                                             "scipy-lm (IRLS), gtsam, isam2, gtsam-timevarying, kalman; the "
                                             "down-weighted rows are named."),
        option: list[str] = typer.Option([], "--option", help="Estimator option KEY=VALUE (repeatable; values "
                                         "in SI units, parsed as YAML scalars), e.g. --option max_iter=50, "
                                         "--option q=1e-5 (kalman), --option optimizer=dogleg (gtsam). The keys "
                                         "of every estimator: `estcal estimators`; docs/calibration.md."),
        allow_ill: bool = typer.Option(False, "--allow-ill-conditioned",
                                       help="Report non-convergence, a condition number above the documented "
                                            "threshold (docs/reliability.md) or a rank loss of the data as "
                                            "warnings instead of refusing (exit 3)."),
        chain: Optional[Path] = typer.Option(None, "--chain", help="MCMC: keep the chain in this HDF5 file; "
                                             "run again with the same file, data and options to extend it."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON."),
        report: Optional[Path] = typer.Option(None, "--report", help="Folder for a report: PNG figures (errors "
                                              "before/after, residual vs joints, parameters ±2σ, correlation, "
                                              "MCMC corner plot) and index.html with the tables."),
        save_model: Optional[Path] = typer.Option(
            None, "--save-model", help="Write the calibrated robot as a robot file (.yaml) with a "
                                       "'calibration:' block (provenance, covariance); reload it with --robot."),
    ) -> None:
        """Estimate robot parameters from measurements (batch least squares or any registered estimator)."""
        from rich.console import Console

        from estcal.estimate.chainfile import ChainFileError
        from estcal.base.errors import NumericalRefusal
        from estcal.estimate.lsq import UnidentifiableError
        from estcal.estimate.registry import estimator_names
        from estcal.io import load_dataset
        from estcal.io.dataset import DatasetError
        from estcal.kinematics.parameters import ParameterError
        from estcal.methods import METHODS, NoiseModel, get_method

        from estcal.base.units import MILLI
        from estcal.cli.units import resolve

        noise_pos = resolve(noise_pos_mm, MILLI, old_noise_pos, "--noise-pos", "--noise-pos-mm", "m", 1.0, 0.1)
        noise_rot = resolve(noise_rot_mrad, MILLI, old_noise_rot, "--noise-rot", "--noise-rot-mrad", "rad", 1.0, 1.0)
        noise_leg = None if noise_leg_mm is None and old_noise_leg is None else \
            resolve(noise_leg_mm or 0.0, MILLI, old_noise_leg, "--noise-leg", "--noise-leg-mm", "m", 1.0, 0.0)
        console = Console(width=160)
        # --method dispatch: estimator names and measurement-method names are disjoint
        try:
            get_method("position")  # imports the optional method modules so METHODS is complete
        except ValueError:
            pass
        if method is not None:
            if method in estimator_names():
                if estimator and estimator != method:
                    _fail(f"--method {method} names an estimator but --estimator {estimator} was also given")
                estimator = method
            elif method in METHODS:
                if measure and measure != method:
                    _fail(f"--method {method} names a measurement method but --measure {measure} was also given")
                measure = method
            else:
                _fail(f"unknown --method {method!r}: neither a measurement method ({', '.join(sorted(METHODS))}) "
                      f"nor an estimator ({', '.join(estimator_names())})")
        estimator = estimator or "lm"
        if estimator not in estimator_names():
            _fail(f"unknown estimator {estimator!r}; choose one of {estimator_names()}")
        if measure is not None and measure not in METHODS:
            _fail(f"unknown measurement method {measure!r}; choose one of {sorted(METHODS)}")
        if free is not None and level is not None:
            _fail("give either --free or --level, not both")
        if level is not None and level not in LEVELS:
            _fail(f"unknown --level {level!r}; choose one of {', '.join(LEVELS)}")
        session_paths = list(data)
        data = session_paths[0]
        data_label = " + ".join(str(p) for p in session_paths)
        check_input_files(session_paths + list(validate))

        # Gough platforms have their own calibration entry point
        try:
            from estcal.parallel import is_gough_file
        except ImportError:  # pragma: no cover
            is_gough_file = None
        if is_gough_file is not None and is_gough_file(robot):
            from estcal.workflows.gough import calibrate_gough

            if len(session_paths) > 1:
                _fail("several data files are not supported for Gough platforms: give one file")
            free_list = [s.strip() for s in free.split(",") if s.strip()] if free else None
            try:
                gres = calibrate_gough(robot, data, estimator=estimator, free=free_list, residual=residual,
                                       model=gough_model, sigma_p=noise_pos, sigma_r=noise_rot,
                                       sigma_rho=noise_leg)
            except (ValueError, KeyError) as exc:
                _fail(str(exc))
            console.print(str(gres))
            if save_model:
                gres.save_model(save_model)
                console.print(f"wrote {save_model}")
            if validate:
                warn("--validate is not supported for Gough platforms (ignored)")
            if report is not None:
                warn("--report is not supported for Gough platforms (ignored)")
            if json_path:
                out = gres.to_dict()
                out.update(robot=robot, data=str(data), estimator=estimator)
                write_json(json_path, out)
                console.print(f"wrote {json_path}")
            return

        rob, n_markers = robot_for_data(robot, data, root=root, tip=tip, points=points)
        try:
            parts = [load_dataset(p, rob, points=n_markers) for p in session_paths]
            vals = [load_dataset(v, rob, points=n_markers) for v in validate]
        except (DatasetError, FileNotFoundError) as exc:
            _fail(str(exc))

        check_held_out(parts, [], "session")
        check_held_out(parts, vals)
        if len(parts) > 1:
            from estcal.sessions.data import stack_sessions

            try:
                ds = stack_sessions(parts)
            except ValueError as exc:
                _fail(str(exc))
        else:
            ds = parts[0]
        warn_datasets(parts + vals)
        noise = NoiseModel(position=noise_pos, orientation=noise_rot, scalar=noise_pos, known=known_noise)
        free_list = None
        if free is not None:
            free_list = [s.strip() for s in free.split(",") if s.strip()]
            if not free_list:
                _fail("--free is empty")
        options = _parse_options(option)
        if chain is not None:
            if estimator != "mcmc":
                _fail(f"--chain stores an MCMC chain: it needs --method mcmc, not {estimator!r}")
            options["chain"] = str(chain)
        if options.get("chain") is not None:  # read to continue, rewritten every block: an output path
            from estcal.cli.checks import check_outputs

            check_outputs({"--chain" if chain is not None else "--option chain": Path(str(options["chain"]))},
                          session_paths + list(validate) + ([Path(robot)] if Path(robot).is_file() else []))
        reg_value = _regularize(regularize)
        if robust is not None:
            if robust not in ("huber", "cauchy"):
                _fail(f"--robust must be huber or cauchy, got {robust!r}")
            if estimator == "ukf":
                _fail("--robust: the UKF has no robust update here — use --estimator kalman (EKF with a "
                      "robust innovation weight) or a least-squares / factor-graph estimator")
            if estimator == "mcmc":
                _fail("--robust: MCMC samples the Gaussian likelihood and has no robust likelihood — use "
                      "--estimator lm --robust … to name the outliers, remove them, then sample")
            if reg_value is not None:
                _fail("--robust with --regularize is not supported: choose one")
            options["robust"] = robust
        try:
            res, sel, problem = run_calibration(rob, ds, measure=measure, estimator=estimator, free=free_list,
                                                level=level or "full", selection=selection, validate=vals,
                                                noise=noise, options=options, regularize=reg_value,
                                                checks=True, allow_ill_conditioned=allow_ill)
        except NumericalRefusal as exc:
            _fail(f"numerical refusal: {exc}", code=3)
        except ChainFileError as exc:
            _fail(f"--chain: {exc}")
        except ParameterError as exc:
            _fail(f"--free: {exc}")
        except UnidentifiableError as exc:
            _fail(f"{exc}\n  (try `estcal identifiable --robot {robot}` or `--level full` to let estcal choose "
                  f"an identifiable set)")
        except ValueError as exc:
            _fail(str(exc))
        except (RuntimeError, np.linalg.LinAlgError) as exc:  # e.g. a backend's numerical failure
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            if "Indeterminate" in str(exc):
                near = " ".join(str(exc).split()).split("(Symbol:")[-1].split(")")[0].strip() \
                    if "(Symbol:" in str(exc) else "?"
                _fail(f"numerical refusal: estimator {estimator!r}: gtsam found the linear system indeterminate "
                      f"near variable {near} — some parameter combinations are not determined by the data "
                      f"(for gtsam-timevarying: a batch whose poses, after robust down-weighting, leave "
                      f"directions fixed only by an extremely tight process noise; raise --option q=… or "
                      f"--option batch_size=…)", code=3)
            _fail(f"estimator {estimator!r} failed: {first} — try another estimator (e.g. --estimator lm) "
                  f"or check the free set with `estcal identifiable`")
        measure_name = problem.terms[0].method.name
        _print_report(console, res, sel, rob, data_label, [str(v) for v in validate], measure_name, estimator)
        res.extra.update(robot=robot, data=data_label, validate=[str(v) for v in validate],
                         measure=measure_name, estimator=estimator, noise=noise.to_dict(), points=n_markers)
        if json_path:
            res.to_json(json_path)
            console.print(f"wrote {json_path}")
        if report is not None:
            from estcal.report.calibration import calibration_report

            rep = calibration_report(report, res, problem, vals, unit=lambda n: _unit(n, rob),
                                     label=sel.regroup_label if sel is not None else None, data_path=data_label,
                                     validate_paths=[str(v) for v in validate], result_dict=res.to_dict(),
                                     title=f"estcal calibrate — {rob.name}, {measure_name}, {estimator}")
            console.print(f"report: {report}/index.html ({len(rep.files)} figures)")
        if save_model:
            console.print(save_model_or_fail(res, save_model, robot, root, tip))
