"""Cartesian effects reach every kind of measurement.

Thermal expansion (both scopes) moves the tool origin as well as the markers, so
tool positions, full poses, point/frame links, planes and distances all see it.
Checked per measurement kind against central finite differences of the stacked
residuals (the α column exactly; the other columns to the documented O(αΔT)
for ``scope="links"``), and against the closed form of a scaled robot.
"""
from __future__ import annotations

import numpy as np
import pytest

from estcal.effects import make_effect
from estcal.kinematics.robots import puma560, stanford
from estcal.methods import Problem
from estcal.methods.generate import distance_data, link_data, measurement_data, plane_data

KINDS = ("position", "location", "point-link", "frame-link", "plane-unknown", "distance")


def _data(robot, kind, n=16, seed=1):
    if kind in ("point-link", "frame-link"):
        return link_data(robot, n // 2, 2, kind.split("-")[0], seed)
    if kind == "plane-unknown":
        return plane_data(robot, n, None, seed)
    if kind == "distance":
        return distance_data(robot, n // 2, seed)
    return measurement_data(robot, n, kind, seed)


def _method(kind):
    return {"location": "pose"}.get(kind, kind)


@pytest.mark.parametrize("scope", ["arm", "links"])
@pytest.mark.parametrize("kind", KINDS)
def test_thermal_reaches_every_measurement_kind(kind, scope):
    base = stanford()
    robot = base.add_effect(make_effect("thermal_expansion", base, scope=scope))
    ds = _data(base, kind)
    ds.context["temperature"] = np.random.default_rng(4).uniform(25.0, 45.0, ds.n)
    prob = Problem(robot, [(_method(kind), ds)])
    theta = prob.params.values.copy()
    ia = prob.params.index(robot.effects[-1].param_names[0])  # thermal_alpha, or thermal_alpha_links
    theta[ia] = 2e-4  # large, so the O(αΔT) terms would show
    rows = prob.evaluate(theta)
    h = 1e-7
    fd = np.empty_like(rows.H)
    for k in range(theta.size):
        step = h * max(1.0, abs(theta[k])) if k != ia else 1e-7
        tp, tm = theta.copy(), theta.copy()
        tp[k] += step
        tm[k] -= step
        fd[:, k] = -(prob.evaluate(tp, jacobian=False).e - prob.evaluate(tm, jacobian=False).e) / (2 * step)
    # the effect reaches this kind of measurement: a non-zero, exact α column
    assert np.abs(fd[:, ia]).max() > 1e-3 * 20.0 * 0.1
    np.testing.assert_allclose(rows.H[:, ia], fd[:, ia], rtol=1e-6, atol=1e-9 * np.abs(fd[:, ia]).max())
    scale = np.abs(fd).max()
    # arm: every column exact (correct_jacobian); links: O(αΔT) ≈ 5e-3 relative on the other columns
    tol = 1e-6 if scope == "arm" else 2e-2
    np.testing.assert_allclose(rows.H, fd, rtol=0, atol=tol * scale)


def test_thermal_scopes_closed_form():
    """arm: tool position = scaled robot (every length × (1 + αΔT)); links: the flange moves like
    the scaled robot's flange and the tool offset keeps its size. Orientation is unchanged."""
    base = puma560()
    base.params["tool_tz"] = 0.15
    base.params["tool_tx"] = 0.05
    rng = np.random.default_rng(2)
    q = base.random_readings(8, rng)
    temp = rng.uniform(10, 40, 8)
    alpha = 1.2e-5
    rigid = base.kinematics(q, jacobian=False)
    for scope in ("arm", "links"):
        robot = base.add_effect(make_effect("thermal_expansion", base, scope=scope))
        robot.params[robot.effects[-1].param_names[0]] = alpha
        k = robot.kinematics(q, context={"temperature": temp}, jacobian=False)
        np.testing.assert_allclose(k.R, rigid.R, atol=1e-15)
        for i in range(8):
            s = 1 + alpha * (temp[i] - 20.0)
            scaled = base.copy()
            for n in base.params.names:
                if n.split("_")[0] in ("d", "a") or (scope == "arm" and n in ("tool_tx", "tool_ty", "tool_tz")):
                    scaled.params[n] = base.params[n] * s
            np.testing.assert_allclose(k.p[i], scaled.kinematics(q[i:i + 1], jacobian=False).p[0], atol=1e-15)
    with pytest.raises(ValueError, match="scope must be one of"):
        make_effect("thermal_expansion", base, scope="tool")
