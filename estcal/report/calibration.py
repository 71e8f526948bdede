"""Report of ``estcal calibrate``: errors before/after, residual structure, parameters,
correlation and (MCMC) the posterior."""
from __future__ import annotations

import numpy as np

from estcal.base.tables import accuracy_table, mcmc_table, parameter_table
from estcal.base.units import joint_display
from estcal.estimate.result import pose_errors
from estcal.plots.errors import pose_error_figure, residual_vs_joints_figure
from estcal.plots.parameters import correlation_figure, parameter_figure

from .html import Report

__all__ = ["calibration_report", "per_pose_errors"]


def per_pose_errors(robot, theta, data):
    """Per-pose position error (mm, RMS over the measured points of the pose) and orientation
    error (mrad, None without orientation data)."""
    pos, rot = pose_errors(robot, theta, data)
    if pos is None:
        return None, None
    return np.sqrt(np.mean(pos ** 2, axis=1)) * 1e3, None if rot is None else rot * 1e3


def calibration_report(folder, res, problem, validation=(), *, unit, label=None, data_path="",
                       validate_paths=(), title="", result_dict=None) -> Report:
    """Write the report of a calibration into ``folder``.

    Parameters
    ----------
    res : :class:`~estcal.estimate.result.CalibrationResult`
    problem : the :class:`~estcal.methods.problem.Problem` whose parameter values are the
        initial guess (``run_calibration``'s third return value).
    validation : validation datasets, in the order of ``res.accuracy['validation']``.
    unit : ``unit(name) -> (unit, factor from SI)``; label : readable regrouping of a name.
    result_dict : the command's JSON (written as ``result.json`` next to ``index.html``).
    """

    rep = Report(folder, title or f"estcal calibrate — {res.method}",
                 subtitle=f"{len(res.names)} parameters, {res.n_iterations} iterations, "
                          f"{'converged' if res.converged else 'NOT converged'}, σ0 = {res.sigma0:.4g} "
                          f"(covariance {res.covariance_source})")
    robot = problem.robot
    before = problem.params.values
    after = np.asarray(res.theta, float)[: robot.n_params]
    data = problem.terms[0].data
    named = [(f"calibration: {data_path or data.where}", data)] + [
        (f"validation: {p}", d) for p, d in zip(list(validate_paths) or [d.where for d in validation], validation)]
    pos_sets, rot_sets, joint_sets = [], [], []
    for lab, d in named:
        pb, rb = per_pose_errors(robot, before, d)
        pa, ra = per_pose_errors(robot, after, d)
        if pa is None:
            continue
        pos_sets.append({"label": lab, "before": pb, "after": pa})
        if ra is not None:
            rot_sets.append({"label": lab, "before": rb, "after": ra})
        q, junits = joint_display(robot, d.readings)
        joint_sets.append({"label": lab, "readings": q, "error": pa})

    rep.heading("Accuracy")
    rep.table(accuracy_table(res, data_path or data.where, list(validate_paths)))
    if pos_sets:
        rep.figure("pose_errors.png", pose_error_figure(pos_sets, "position", "mm"),
                   "Position error of every pose before (initial guess) and after calibration; each validation "
                   "file in its own panel.")
    if rot_sets:
        rep.figure("pose_errors_rotation.png", pose_error_figure(rot_sets, "orientation", "mrad"),
                   "Orientation error of every pose before and after calibration.")
    if joint_sets:
        rep.figure("residual_vs_joints.png",
                   residual_vs_joints_figure(joint_sets, robot.joint_names, junits, "mm"),
                   "Position error after calibration against each joint reading: a trend or a periodic pattern "
                   "is an effect the geometric model lacks (see estcal diagnose).")

    rep.heading("Parameters")
    rep.table(parameter_table(res, unit, label))
    units = [unit(n) for n in res.names]
    rep.figure("parameters.png", parameter_figure(res.names, (res.estimate - res.nominal) * [f for _, f in units],
                                                  res.std * [f for _, f in units], [u for u, _ in units]),
               "Change of every estimated parameter from its initial value, with ±2σ bars (display units).")
    if len(res.names) > 1:
        rep.figure("correlation.png", correlation_figure(res.names, res.covariance),
                   "Correlation matrix of the estimates (from the reported covariance); |ρ| near 1 marks "
                   "parameters the data barely separate.")
    mt = mcmc_table(res, unit)
    if mt is not None:
        rep.heading("Posterior (MCMC)")
        rep.table(mt)
        samples = getattr(res, "samples", None)
        if samples is not None:
            from estcal.plots.posterior import corner_figure

            try:
                # joint-model parameters first: the base frame and markers are registration
                order = sorted(range(len(res.names)), key=lambda i: res.names[i].startswith(("base_", "marker")))
                fac = np.array([f for _, f in units])
                X = (np.asarray(samples) - res.nominal) * fac
                labels = [f"{res.names[i]} − initial ({units[i][0] or '—'})" for i in order]
                fig = corner_figure(X[:, order], labels)
            except ImportError:
                rep.text("corner plot skipped: the optional 'corner' package is not installed "
                         "(pip install estcal[mcmc])")
            else:
                rep.figure("posterior_corner.png", fig,
                           "Posterior corner plot of the change from the initial value (up to 8 "
                           "parameters, joint-model ones before the base frame and markers; display units), "
                           "2.5 / 50 / 97.5 % quantiles dashed.")
    if result_dict is not None:
        rep.json("result.json", result_dict, "result.json — the same numbers as estcal calibrate --json")
    rep.write()
    return rep
