"""Datasets with hidden effects of a chosen size, for tests and detection-power studies.

The size of an effect is given in units of the measurement noise at the tool:
``magnitude = RMS over poses and measured coordinates of the effect's displacement / σ``,
where σ is the per-coordinate noise std. Effects are linear in their parameters,
so the parameter value giving a magnitude m is ``m σ / d₁`` with ``d₁`` the RMS
displacement per unit parameter (evaluated on the true robot at the simulated
poses, by finite difference of the forward model with a small value).
"""
from __future__ import annotations

import numpy as np

from estcal.effects import make_effect
from estcal.simulate import NoiseModel, simulate

__all__ = ["effect_params_for_magnitude", "simulate_hidden", "cartesian_distortion", "eligible_joints"]


def _measured(robot, readings, context, measure):
    kin = robot.kinematics(readings, context=context, jacobian=False)
    if measure == "pose":
        return kin.p[:, None, :]
    if measure == "position":
        return kin.points[:, :1] if robot.n_markers else kin.p[:, None, :]
    return kin.points


def effect_params_for_magnitude(true_robot, effect, readings, context, magnitude, sigma, measure="points",
                                direction=None):
    """Values of ``effect``'s parameters (a direction in parameter space, default all ones)
    whose displacement has RMS ``magnitude · sigma`` at the measured points."""
    names = list(effect.param_names)
    d = np.ones(len(names)) if direction is None else np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    base = true_robot.params.values.copy()
    idx = true_robot.params.indices(names)
    h = 1e-6
    th = base.copy()
    th[idx] = 0.0
    x0 = _measured(true_robot.with_values(th), readings, context, measure)
    th[idx] = h * d
    x1 = _measured(true_robot.with_values(th), readings, context, measure)
    rms1 = np.sqrt(np.mean((x1 - x0) ** 2)) / h
    if rms1 == 0:
        raise ValueError(f"effect {effect.name} on {effect.joints} has no effect at these poses")
    return dict(zip(names, (magnitude * sigma / rms1) * d))


def eligible_joints(robot, effect_name, readings, context=None, min_torque=1e-3):
    """Joints on which ``effect_name`` is identifiable in principle: gravity-driven effects need
    a torque that varies (compliance) or changes sign (backlash)."""
    out = []
    tau = None
    for j, name in enumerate(robot.joint_names):
        try:
            make_effect(effect_name, robot, joints=[name])
        except (ValueError, TypeError):
            continue
        if effect_name in ("joint_compliance", "backlash"):
            if tau is None:
                tau = robot.gravity_torques(readings, context=context)
            t = tau[:, j]
            if np.abs(t).max() <= 1e-9 * max(np.abs(tau).max(), 1e-300):
                continue  # numerically zero torque (vertical axis): the sign is rounding noise
            if effect_name == "joint_compliance" and np.std(t) < min_torque:
                continue
            if effect_name == "backlash":
                s = np.sign(t)
                if min(np.mean(s > 0), np.mean(s < 0)) < 0.15:
                    continue
        out.append(name)
    return out


def simulate_hidden(robot, hidden, sigma, n_poses=60, measure="points", seed=0, error_std=None, payload=None,
                    markers=None, **sim_kw):
    """Simulate ``robot`` with random geometric errors and hidden effects of given magnitudes.

    Parameters
    ----------
    hidden : list of ``(effect name, joints or None, magnitude in σ units[, options])``.
    sigma : measurement noise std per coordinate (m).

    Returns ``(SimulationResult, truth)`` with ``truth = [{effect, joints, params}]``.
    """
    rng = np.random.default_rng(seed)
    err = error_std or {"angle": 5e-4, "length": 5e-4, "offset": 1e-3}
    specs = [{"effect": h[0], "joints": h[1], "options": dict(h[3]) if len(h) > 3 else {}} for h in hidden]
    kw = dict(n_poses=n_poses, measure=measure, errors="random", error_std=err, seed=seed, payload=payload,
              markers=markers, **sim_kw)
    # first pass: poses, context and the true robot with unit-less zero effects
    sim0 = simulate(robot, effects=[dict(s, params={}) for s in specs],
                    noise=NoiseModel(position=sigma, orientation=sigma), **kw)
    true = sim0.true_robot
    ctx = dict(sim0.dataset.context)
    ctx.update({k: v for k, v in sim0.dataset.columns.items() if k.startswith("approach_")})
    params = {}
    truth = []
    for h, eff in zip(hidden, true.effects):
        m = h[2]
        direction = None
        if eff.name == "gear_harmonic":
            ph = rng.uniform(0, 2 * np.pi)
            direction = np.ravel([[np.cos(ph), np.sin(ph)] for _ in eff.orders])
        tz = true.with_values(np.where(np.isin(np.arange(true.n_params), true.params.indices(
            [n for e in true.effects for n in e.param_names])), 0.0, true.params.values))
        vals = effect_params_for_magnitude(tz, eff, sim0.true_readings, ctx, m, sigma, measure, direction)
        if eff.name == "backlash":
            vals = {k: abs(v) for k, v in vals.items()}
        params.update(vals)
        truth.append({"effect": eff.name, "joints": list(eff.joints), "params": vals, "magnitude": m})
    sim = simulate(robot, effects=specs, effect_params=params, noise=NoiseModel(position=sigma, orientation=sigma),
                   **kw)
    return sim, truth


def cartesian_distortion(data, strength, center=None, rng=None):
    """Copy of ``data`` whose measured points suffer a smooth, non-rigid distortion of the
    measuring system (not a robot effect, hence outside the library):

        δx = s (y' z')/L,  δy = s (x'² − z'²)/(2L),  δz = s (x' y')/L

    with ``x' = x − center`` and L the RMS distance of the points to ``center``, so ``s`` is
    the displacement (m) at distance L. Rigid motions and scalings are absorbed by the
    geometric model; this quadratic field is not.
    """
    out = data.subset(slice(None))
    P = out.points if out.points is not None else out.p[:, None, :]
    c = P.reshape(-1, 3).mean(0) if center is None else np.asarray(center, float)
    X = P - c
    L = np.sqrt(np.mean(np.sum(X ** 2, -1)))
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    d = np.stack([y * z / L, (x ** 2 - z ** 2) / (2 * L), x * y / L], -1) * strength / L
    if out.points is not None:
        out.points = P + d
    else:
        out.p = out.p + d[:, 0]
    return out
