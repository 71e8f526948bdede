"""``estcal calibrate``: batch estimation of a robot's parameters from a measurement file.

Parses the options, runs :func:`estcal.workflows.calibrate.calibrate` (or, for a Gough-platform
robot file, :func:`estcal.workflows.calibrate.calibrate_gough`) and prints the report: parameter
table (estimate ± std, regrouped names), RMSE/mean/max position (mm) and orientation (mrad)
before/after on the calibration file and on each ``--validate`` file in order. The five steps
(robot, measurement, initial guess, free set, estimation) are those of the workflow; options in
docs/calibration.md.

JSON (``--json PATH``): :meth:`CalibrationResult.to_dict` — ``parameters``
({name: {estimate, std, nominal}}, SI), ``rmse_mm`` ({train, train_before, validation: [..]}),
``n_iterations``, ``converged``, ``accuracy`` … — plus ``selection`` (level, criterion,
identifiable, no_effect, regrouped, condition_number), ``robot``, ``data``, ``validate``,
``measure``, ``estimator``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from estcal.base.errors import InputError
from estcal.cli.app import command
from estcal.cli.options import (deprecated_option, estimator_option, free_option, json_option, known_noise_option,
                                level_option, measure_option, method_option, noise_pos_option, noise_rot_option,
                                row_sigma_option, with_row_sigma,
                                points_option, posture_tol, posture_tol_mm_option, posture_tol_mrad_option,
                                report_option, robot_option, root_option, save_model_option, tip_option,
                                validate_option, map_option, drop_flagged_option)

__all__ = ["calibrate"]

# --------------------------------------------------------------------------- printing


def _fmt(v, nd=3):
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def _print_report(console, cal) -> None:
    from rich.table import Table

    from estcal.base.tables import parameter_table
    from estcal.base.units import display_unit as _unit  # printed unit and factor from SI of a parameter
    from estcal.report.tables import rich_table

    res, sel, robot = cal.result, cal.selection, cal.robot
    if res.extra.get("left_out"):  # answer first: what was left out and what it changed
        from estcal.workflows.left_out import format_left_out

        console.print(format_left_out(res.extra["left_out"]), soft_wrap=True, highlight=False)
    title = (f"estcal calibrate — {robot.name}, {cal.measure}, estimator {cal.estimator}: "
             f"{len(res.names)} parameters, {res.n_iterations} iterations, "
             f"{'converged' if res.converged else 'NOT converged'}, σ0 = {res.sigma0:.3g} "
             f"(covariance {res.covariance_source})")
    t = parameter_table(res, lambda n: _unit(n, robot), title=title)
    if sel is not None:  # the regrouping in the name's cell: `a_2 [+β·d_3]`
        for row in t.rows:
            row[0] = sel.regroup_label(row[0])
    t.fmt = lambda i, j, v, digits: f"{v:.3g}" if j == 3 else f"{v:.5g}"  # σ to 3 digits
    console.print(rich_table(t))
    if sel is not None:
        msg = f"selection: level {sel.level}, criterion {sel.criterion}, condition number {sel.condition_number:.3g}"
        if sel.no_effect:
            msg += f"\n  no effect on these data: {', '.join(sel.no_effect)}"
        if sel.regrouped:
            msg += f"\n  regrouped (absorbed by the kept parameters shown in brackets): {', '.join(sel.regrouped)}"
        if sel.rejected:
            msg += f"\n  identifiable but not supported by AIC (kept nominal): {', '.join(sel.rejected)}"
        console.print(msg)
    elif res.extra.get("default_model"):
        dm = res.extra["default_model"]
        console.print(f"selection: {dm['reason']} — so the default is the relevance-prior model: {len(dm['kept'])} of "
                      f"{len(dm['considered'])} identifiable geometric parameters kept by the evidence, each under its "
                      f"own prior (MAP; docs/calibration.md, 'When the full level is refused')")
    elif (res.extra.get("selection") or {}).get("source"):
        s = res.extra["selection"]
        console.print(f"selection: level {s['level']}, criterion {s['criterion']}: {s['source']} "
                      f"({len(s['identifiable'])} parameters, as identified at the design geometry)")
    if res.extra.get("measurement_noise"):
        from estcal.discrepancy.noise import noise_lines

        console.print("\n".join(noise_lines(res.extra["measurement_noise"])))
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
        rows.append((f"calibration: {cal.data_label}", acc["train"]))
    for p, v in zip(cal.validate_labels, acc.get("validation", [])):
        rows.append((f"validation: {p}", v))
        for part in ("seen", "new"):  # the same file split by posture (seen in calibration / new)
            if v.get(part, {}).get("n_rows"):
                rows.append((f"  at {part} postures", {"after": {"n_poses": v[part]["n_rows"],
                                                                  "rmse_mm": v[part]["rmse_mm"]}}))
    for label, d in rows:
        b, af = d.get("before", {}), d.get("after", {})
        a.add_row(label, str(af.get("n_poses", "")), _fmt(b.get("rmse_mm")), _fmt(af.get("rmse_mm")),
                  _fmt(af.get("mean_mm")), _fmt(af.get("max_mm")), _fmt(b.get("rmse_mrad")),
                  _fmt(af.get("rmse_mrad")), _fmt(af.get("max_mrad")))
    console.print(a)
    console.print("'before' = initial guess: " + res.extra.get("initial_guess", "nominal"))
    from estcal.base.tables import mcmc_table
    from estcal.report.tables import rich_table

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
    import warnings

    from estcal.base.errors import EstcalWarning

    text = str(value).strip()
    scale = 1e-3 if text.endswith(("mm", "mrad")) else 1.0
    try:
        tau = float(text.removesuffix("mrad").removesuffix("mm")) * scale
    except ValueError:
        raise InputError(f"--regularize must be 'loo' or a prior std with its unit (e.g. 2mm; mm for lengths, mrad "
                         f"for angles), got {value!r}") from None
    if scale == 1.0:
        warnings.warn(f"--regularize {value} without a unit is read as SI (m / rad), deprecated; write "
                      f"--regularize {tau * 1e3:g}mm", EstcalWarning, stacklevel=2)
    if not tau > 0:
        raise InputError(f"--regularize: the prior std must be > 0, got {value}")
    return tau


def _parse_options(items) -> dict:
    """``KEY=VALUE`` strings -> dict; values parsed as YAML scalars (numbers, booleans, strings)."""
    import yaml

    out = {}
    for item in items:
        if "=" not in item:
            raise InputError(f"--option {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        val = yaml.safe_load(v)
        if isinstance(val, str):  # YAML 1.1 reads 1e-7 (no dot) as a string: a number is meant
            try:
                val = float(val)
            except ValueError:
                pass
        out[k.strip()] = val
    return out


# --------------------------------------------------------------------------- command
@command("calibrate")
def calibrate(
    data: list[Path] = typer.Argument(..., help="Calibration dataset (CSV: joint columns + x,y,z / x1..zk / "
                                                "pose); several files are several sessions, fitted with one "
                                                "parameter set (per-session deviations: estcal sessions)."),
    robot: str = robot_option(),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    estimator: Optional[str] = estimator_option(None),
    measure: Optional[str] = measure_option(),
    method: Optional[str] = method_option(),
    free: Optional[str] = free_option(),
    level: Optional[str] = level_option(None),
    selection: Optional[str] = typer.Option(None, "--selection",
                                            help="structural (default: every identifiable parameter, QR) | "
                                                 "aic | bic (greedy pruning by an information criterion)."),
    regularize: Optional[str] = typer.Option(
        None, "--regularize", help="Gaussian prior toward the nominal joint-model parameters (MAP): "
                                   "'loo' (width chosen by leave-one-posture-out CV on the calibration file) "
                                   "or a prior std with its unit, e.g. 2mm (mm for lengths, mrad for angles, 10⁻³ "
                                   "for gains). Base frame and points stay free."),
    validate: list[Path] = validate_option(),
    posture_tol_mrad: float = posture_tol_mrad_option(),
    posture_tol_mm: float = posture_tol_mm_option(),
    points: Optional[int] = points_option(),
    column_map: Optional[Path] = map_option(),
    drop_flagged: bool = drop_flagged_option(True),
    noise_pos_mm: float = noise_pos_option(0.1),
    noise_rot_mrad: float = noise_rot_option(1.0),
    old_noise_pos: Optional[float] = deprecated_option("--noise-pos"),
    old_noise_rot: Optional[float] = deprecated_option("--noise-rot"),
    known_noise: bool = known_noise_option(),
    row_sigma_mm: Optional[str] = row_sigma_option(),
    noise_leg_mm: Optional[float] = typer.Option(None, "--noise-leg-mm", help="Gough platforms: leg-length "
                                                                              "noise std (mm)."),
    old_noise_leg: Optional[float] = deprecated_option("--noise-leg"),
    residual: str = typer.Option("ik", "--residual", help="Gough platforms: ik (leg lengths from the "
                                                          "measured pose) or fk (pose from the legs)."),
    gough_model: int = typer.Option(42, "--model", help="Gough platforms: 42 (attachment points + leg "
                                                        "offsets) or 36 (offsets known)."),
    robust: Optional[str] = typer.Option(None, "--robust", help="Robust kernel huber | cauchy (thresholds "
                                         "1.345 / 2.385 σ, --option robust_k=K) on the rows fitted (every row "
                                         "with --keep-all): lm, gauss-newton, iterated-lls, scipy-lm (IRLS), gtsam, "
                                         "isam2, gtsam-timevarying, kalman; the down-weighted rows are named."),
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
    json_path: Optional[Path] = json_option(),
    report: Optional[Path] = report_option("Folder for a report: PNG figures (errors before/after, residual vs "
                                           "joints, parameters ±2σ, correlation, MCMC corner plot) and "
                                           "index.html with the tables."),
    save_model: Optional[Path] = save_model_option(),
) -> None:
    """Estimate robot parameters from measurements (batch least squares or any registered estimator)."""
    from estcal.cli.options import estimator_and_measure
    from estcal.base.units import MILLI
    from estcal.cli.units import resolve
    from estcal.workflows import calibrate as wf

    estimator, measure = estimator_and_measure(method, estimator, measure)
    estimator = estimator or "lm"
    noise_pos = resolve(noise_pos_mm, MILLI, old_noise_pos, "--noise-pos", "--noise-pos-mm", "m", 1.0, 0.1)
    noise_rot = resolve(noise_rot_mrad, MILLI, old_noise_rot, "--noise-rot", "--noise-rot-mrad", "rad", 1.0, 1.0)
    if wf.is_gough(robot):
        if row_sigma_mm:
            raise typer.BadParameter("--row-sigma-mm weights serial-robot measurements; a Gough platform's noise is "
                                     "--noise-pos-mm / --noise-rot-mrad / --noise-leg-mm")
        noise_leg = None if noise_leg_mm is None and old_noise_leg is None else \
            resolve(noise_leg_mm or 0.0, MILLI, old_noise_leg, "--noise-leg", "--noise-leg-mm", "m", 1.0, 0.0)
        gres = wf.calibrate_gough(robot, data, estimator=estimator, free=free, residual=residual, model=gough_model,
                                  noise_pos=noise_pos, noise_rot=noise_rot, noise_leg=noise_leg,
                                  options=_parse_options(option))
        _gough_outputs(gres, robot, data, estimator, validate, report, save_model, json_path)
        return
    from estcal.methods import NoiseModel

    options = _parse_options(option)
    if chain is not None:
        options["chain"] = str(chain)
    if options.get("chain") is not None:  # read to continue, rewritten every block: an output path
        from estcal.cli.checks import check_outputs

        check_outputs({"--chain" if chain is not None else "--option chain": Path(str(options["chain"]))},
                      list(data) + list(validate) + ([Path(robot)] if Path(robot).is_file() else []))
    noise = with_row_sigma(NoiseModel(position=noise_pos, orientation=noise_rot, scalar=noise_pos,
                                      known=known_noise), row_sigma_mm)
    import warnings

    from estcal.workflows.left_out import LeftOutWarning

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=LeftOutWarning)  # the report prints the rows left out first
        cal = wf.calibrate(robot, list(data), estimator=estimator, measure=measure, free=free, level=level,
                           selection=selection, validate=list(validate), noise=noise,
                           regularize=_regularize(regularize), robust=robust, options=options, points=points,
                           root=root, tip=tip, checks=True, allow_ill_conditioned=allow_ill,
                           posture_tol=posture_tol(posture_tol_mrad, posture_tol_mm), column_map=column_map,
                           drop_flagged=drop_flagged)
    _outputs(cal, robot, root, tip, json_path, report, save_model)


def _outputs(cal, robot, root, tip, json_path, report, save_model) -> None:
    """Print the report and write what was asked (JSON, report folder, saved model)."""
    from rich.console import Console

    from estcal.base.units import display_unit

    console = Console(width=160)
    _print_report(console, cal)
    res = cal.result
    if json_path:
        res.to_json(json_path)
        console.print(f"wrote {json_path}")
    if report is not None:
        from estcal.report.calibration import calibration_report

        sel = cal.selection
        rep = calibration_report(report, res, cal.problem, cal.validation, unit=lambda n: display_unit(n, cal.robot),
                                 label=sel.regroup_label if sel is not None else None, data_path=cal.data_label,
                                 validate_paths=cal.validate_labels, result_dict=res.to_dict(),
                                 title=f"estcal calibrate — {cal.robot.name}, {cal.measure}, {cal.estimator}")
        console.print(f"report: {report}/index.html ({len(rep.files)} figures)")
    if save_model:
        from estcal.workflows.inputs import save_model as save

        save(res, save_model, robot, root, tip)
        console.print(f"wrote {save_model} (load it with --robot {save_model})")


def _gough_outputs(gres, robot, data, estimator, validate, report, save_model, json_path) -> None:
    import warnings

    from estcal.base.errors import EstcalWarning

    typer.echo(str(gres))
    if save_model:
        gres.save_model(save_model)
        typer.echo(f"wrote {save_model}")
    if validate:
        warnings.warn("--validate is not supported for Gough platforms (ignored)", EstcalWarning, stacklevel=2)
    if report is not None:
        warnings.warn("--report is not supported for Gough platforms (ignored)", EstcalWarning, stacklevel=2)
    if json_path:
        from estcal.base.jsonio import write_json

        out = gres.to_dict()
        out.update(robot=robot, data=str(data[0]), estimator=estimator)
        write_json(json_path, out)
        typer.echo(f"wrote {json_path}")
