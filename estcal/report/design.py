"""Reports of ``estcal design`` (a measurement plan) and ``estcal next-pose``."""
from __future__ import annotations

import numpy as np

from estcal.base.tables import Table
from estcal.base.units import joint_display
from estcal.design.sequential import model_for_state
from estcal.plots.design import accuracy_map_figure, baseline_figure

from .html import Report

__all__ = ["design_report", "next_pose_report", "readings_table"]


def readings_table(key, title, robot, Q) -> Table:
    """Joint readings of each pose (revolute in degrees, prismatic in mm)."""
    D, units = joint_display(robot, Q)
    return Table(key, title, ["pose"] + [f"{n} ({u})" for n, u in zip(robot.joint_names, units)],
                 [[i + 1] + [float(v) for v in row] for i, row in enumerate(D)])


def _dump(result_dict, rep, command):
    if result_dict is not None:
        rep.json("result.json", result_dict, f"result.json — the same numbers as estcal {command} --json")


def design_report(folder, model, plan, criteria, baseline, accuracy_map=None, rho_mm=None, q_test=None, *,
                  larger_is_better: bool, unit, title: str = "estcal design", result_dict=None) -> Report:
    """Write the report of an optimised plan into ``folder``.

    Parameters
    ----------
    model : :class:`~estcal.design.model.DesignModel`; plan : :class:`~estcal.design.plans.Plan`.
    criteria : :class:`~estcal.design.criteria.PlanCriteria` of the plan.
    baseline : :class:`~estcal.design.plans.BaselineStats` (with ``values`` for the histogram).
    accuracy_map : :class:`~estcal.design.criteria.AccuracyMap` of the plan's covariance.
    rho_mm : predicted RMS position error (mm) at the test poses ``q_test``.
    """
    rb = model.robot
    rep = Report(folder, title, subtitle=f"{rb.name}, method {model.method}, {model.p} free parameters, "
                                         f"plan of m = {plan.m} poses ({plan.method}), criterion {plan.criterion}")
    rep.heading("Plan")
    rep.table(readings_table("plan", "joint readings of the plan", rb, plan.readings))
    cd = criteria.to_dict()
    rep.table(Table("criteria", "criteria of the plan", ["criterion", "value"],
                    [[k, v] for k, v in cd.items() if not isinstance(v, (dict, list)) and v is not None]))
    std = cd.get("param_std") or {}
    rep.table(Table("param_std", "predicted parameter std (display units)", ["parameter", "std", "unit"],
                    [[n, float(s * unit(n)[1]), unit(n)[0]] for n, s in std.items()]))
    if rho_mm is not None:
        D, _ = joint_display(rb, q_test)
        rep.table(Table("test_pose", "predicted RMS position error at the test pose(s)",
                        ["test pose"] + list(rb.joint_names) + ["error (mm)"],
                        [[i + 1] + [float(v) for v in D[i]] + [float(r)] for i, r in enumerate(rho_mm)]))
    rep.heading("Against random plans")
    bd = baseline.to_dict()
    rep.table(Table("baseline", f"criterion {bd['criterion']} over {bd['n_plans']} random plans of m = {bd['m']}",
                    ["statistic", "value"],
                    [["optimised plan", float(plan.value)], ["min", bd["min"]], ["mean", bd["mean"]],
                     ["max", bd["max"]]] + [[f"percentile {k}", v] for k, v in bd["percentiles"].items()]))
    if baseline.values is not None:
        rep.figure("baseline.png", baseline_figure(baseline.values, plan.value, plan.criterion, larger_is_better),
                   "Distribution of the criterion over random plans of the same size; red: the optimised plan.")
    if accuracy_map is not None:
        rep.heading("Predicted accuracy over the workspace")
        s = accuracy_map.summary()
        rep.table(Table("accuracy_map", "predicted position error std after calibration with the plan (mm)",
                        ["poses", "mean", "median", "min", "max"],
                        [[s["n"], s["mean_m"] * 1e3, s["median_m"] * 1e3, s["min_m"] * 1e3, s["max_m"] * 1e3]]))
        marks = [("plan poses", model.positions(plan.readings) * 1e3)]
        if q_test is not None:
            marks.append(("test pose(s)", model.positions(np.atleast_2d(q_test)) * 1e3))
        rep.figure("accuracy_map.png",
                   accuracy_map_figure([("after the plan", accuracy_map.xyz * 1e3, accuracy_map.std * 1e3)], marks),
                   "Predicted position-error std √trace(J C Jᵀ) at random reachable poses within the joint "
                   "limits (nominal tool positions, three projections); crosses: the plan's poses.")
    _dump(result_dict, rep, "design")
    rep.write()
    return rep


def next_pose_report(folder, model, nxt, state, maps, *, unit, title: str = "estcal next-pose",
                     result_dict=None) -> Report:
    """Write the report of a next-pose proposal into ``folder``.

    ``maps``: ``(before, after)`` :class:`~estcal.design.criteria.AccuracyMap` on the same
    poses, with the state's covariance and with the covariance after measuring ``nxt``.
    """
    rb = model.robot
    rep = Report(folder, title, subtitle=f"{rb.name}, method {model.method}, {len(state.parameters)} parameters "
                                         f"in the state, criterion {nxt.criterion}")
    rep.heading("Proposed pose")
    rep.table(readings_table("next", "next pose", rb, nxt.readings))
    rep.table(Table("criterion", f"criterion {nxt.criterion}", ["before", "after", "reduction"],
                    [[float(nxt.value_before), float(nxt.value_after), float(nxt.reduction)]]))
    sd0 = state.std
    rep.table(Table("param_std", "parameter std before / after measuring the pose (display units)",
                    ["parameter", "std before", "std after", "unit"],
                    [[n, float(sd0[i] * unit(n)[1]), float(nxt.predicted_std[n] * unit(n)[1]), unit(n)[0]]
                     for i, n in enumerate(state.parameters)]))
    before, after = maps
    rep.heading("Predicted accuracy over the workspace")
    rows = []
    for lab, m in (("now", before), ("after the next pose", after)):
        s = m.summary()
        rows.append([lab, s["n"], s["mean_m"] * 1e3, s["median_m"] * 1e3, s["min_m"] * 1e3, s["max_m"] * 1e3])
    rep.table(Table("accuracy_map", "predicted position error std (mm)", ["covariance", "poses", "mean", "median",
                                                                          "min", "max"], rows))
    rep.figure("accuracy_map.png",
               accuracy_map_figure([("now", before.xyz * 1e3, before.std * 1e3),
                                    ("after the next pose", after.xyz * 1e3, after.std * 1e3)],
                                   [("next pose", _next_position(model, state, nxt) * 1e3)]),
               "Predicted position-error std at random reachable poses with the current covariance (top) and "
               "after measuring the proposed pose (bottom, same colour scale); cross: the proposed pose.")
    _dump(result_dict, rep, "next-pose")
    rep.write()
    return rep


def _next_position(model, state, nxt):
    return model_for_state(model, state).positions(np.atleast_2d(nxt.readings))
