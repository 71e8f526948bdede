"""Kinematics of many parameter vectors at once (SerialRobot.kinematics with θ of shape (W, P)):
every output equals W single-θ evaluations, effects included (docs/probabilistic.md, MCMC walkers)."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.io.robotfile import load_robot
from estcal.kinematics.builder import build_robot

FIELDS = ("q", "R", "p", "points", "J", "J_points", "J_q", "link_R", "link_p", "joint_axis", "joint_origin")


def _check(robot, q, TH, context=None):
    many = robot.kinematics(q, TH, context)
    for w, th in enumerate(TH):
        one = robot.kinematics(q, th, context)
        for f in FIELDS:
            a, b = getattr(many, f)[w], getattr(one, f)
            assert a.shape == b.shape, f
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12, err_msg=f"{robot.name} walker {w}: {f}")
    fk = robot.kinematics(q, TH, context, jacobian=False)
    assert fk.J is None and np.array_equal(fk.p, many.p)


def _thetas(robot, W, rng, scale=0.02):
    return robot.params.values + scale * rng.normal(size=(W, robot.n_params))


@pytest.mark.parametrize("spec,markers", [("puma560", 0), ("puma560", 3), ("stanford", 1), ("5r1p", 0),
                                          ("planar2", 2), ("puma560_fu", 0)])
def test_batched_equals_per_theta_builtin(spec, markers):
    robot = load_robot(spec, n_markers=markers or None)
    rng = np.random.default_rng(1)
    _check(robot, robot.random_readings(7, rng), _thetas(robot, 5, rng))


def test_batched_with_coupling_gains_and_constant_frames():
    rng = np.random.default_rng(2)
    Cj, Cm = np.eye(3) + 0.2 * rng.normal(size=(3, 3)), np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    frames = [{"name": "f0", "type": "fixed", "convention": "khalil", "label": "F0", "theta": 0.3, "r": 0.2}]
    frames += [{"name": f"j{i}", "offset": 0.1 * i, "gain": 1.0 + 0.1 * i, "d": 0.3, "alpha": 0.4} for i in range(3)]
    robot = build_robot("c", frames, coupling=(Cj, Cm), markers=rng.normal(0, 0.1, (2, 3)),
                        base={"xyz": [0.1, 0.2, 0.3], "rpy": [0.1, -0.2, 0.3]})
    _check(robot, robot.random_readings(6, rng), _thetas(robot, 4, rng))


@pytest.mark.parametrize("effects", [["joint_compliance:j2,j3"], ["gear_harmonic:j1", "encoder_gain:j4"],
                                     ["backlash:j2"], ["thermal_expansion"], ["drift"]])
def test_batched_with_effects(effects):
    """Robots as identified by a diagnosis (geometry + effects): joint-space and point corrections."""
    from estcal.simulate import simulate

    sim = simulate("puma560", n_poses=6, measure="points", effects=effects, seed=4, dt=60.0,
                   temperature=(20.0, 30.0), record_approach=True)
    robot, ds = sim.true_robot, sim.dataset
    assert robot.effects
    rng = np.random.default_rng(5)
    TH = robot.params.values + 0.01 * np.abs(robot.params.values).clip(1e-3) * rng.normal(size=(4, robot.n_params))
    _check(robot, ds.readings, TH, ds.context)
