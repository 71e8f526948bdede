"""Simulation feedback: simulate the robot *as identified* (geometric + named effects).

Closing the loop "what does our simulation get wrong": a diagnosis fit (the
JSON of :meth:`DiagnosisResult.to_dict`, or the result itself) describes the
identified robot — every parameter value, the named effects with their
options, gravity in the measurement frame and whether masses were lumped.
:func:`identified_robot` rebuilds it; :func:`simulate_from_fit` simulates a
dataset with it (at given poses, e.g. the measured ones, with the noise the
fit left); :func:`residual_comparison` fits the geometric model to measured
and simulated data alike and puts their residual statistics side by side. If
the named effects are the whole story, the simulated geometric residual looks
like the measured one (same RMSE, same structure); what remains different is
what the simulation still gets wrong.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from estcal.base.textinput import read_json
from estcal.effects import make_effect
from estcal.io.prepare import with_effect_context
from estcal.io.robotfile import load_robot
from estcal.kinematics.chain import SerialRobot
from estcal.simulate import NoiseModel, simulate
from estcal.simulate.core import simulation_noise

from .analysis import partial_joint_residuals
from .diagnose import _scores
from .geometric import fit_geometric, gravity_ready

__all__ = ["load_fit", "identified_robot", "simulate_from_fit", "simulate_like", "residual_comparison"]


def load_fit(fit) -> dict:
    """The fit as a dict: from a :class:`DiagnosisResult`, a dict, or a JSON file path."""
    if hasattr(fit, "to_dict"):
        return fit.to_dict()
    if isinstance(fit, dict):
        return fit

    path = Path(fit)
    d = read_json(path, "diagnosis fit", ValueError)
    if not isinstance(d, dict) or not isinstance(d.get("model"), dict) or "theta" not in d["model"]:
        raise ValueError(f"{path}: not a diagnosis fit (needs the 'model' written by `estcal diagnose --json`)")
    return d


def identified_robot(fit, robot=None, geometric_only: bool = False):
    """The identified robot of a diagnosis fit.

    Parameters
    ----------
    fit : DiagnosisResult, dict or JSON path.
    robot : the nominal robot (SerialRobot or spec); default the fit's ``robot_spec``
        (or ``robot`` name) resolved by :func:`estcal.io.robotfile.load_robot`.
    geometric_only : without the named effects.

    Returns ``(geometric robot at the identified values, effect specs)`` where the specs are
    ``[{effect, joints, options, params}]`` ready for :func:`estcal.simulate.simulate`.
    """

    d = load_fit(fit)
    m = d["model"]
    base = _nominal(m, robot)
    if m.get("lumped_masses"):
        base, _ = gravity_ready(base)
    base = SerialRobot(base.name, base.links, base.params.copy(), base.joint_names, base.joint_types, base.limits,
                       base.offset_idx, base.gain_idx, base.marker_idx, np.asarray(m["gravity"], float),
                       base.payload_mass, base.payload_com, base.coupling, base.convention, [], base.meta)
    theta = m["theta"]
    vals = base.params.values.copy()
    for i, n in enumerate(base.params.names):
        if n in theta:
            vals[i] = theta[n]
    geo = base.with_values(vals)
    specs = []
    if not geometric_only:
        for e in m.get("effects", []):
            eff = make_effect(e["effect"], geo, joints=e.get("joints") or None, **(e.get("options") or {}))
            missing = [n for n in eff.param_names if n not in theta]
            if missing:
                raise ValueError(f"fit: effect {e['effect']!r} parameters {missing} have no value")
            specs.append({"effect": e["effect"], "joints": e.get("joints") or None,
                          "options": dict(e.get("options") or {}),
                          "params": {n: float(theta[n]) for n in eff.param_names}})
    return geo, specs


def _nominal(m: dict, robot=None):
    """The nominal robot of a fit's ``model`` section (or ``robot`` when given)."""

    if robot is None and m.get("robot_dict"):
        # the fit carries its nominal robot (masses included): no robot file needed
        from estcal.io.robotfile import robot_from_dict

        base = robot_from_dict(m["robot_dict"], source=f"fit model ({m.get('robot')})")
        nm = int(m.get("n_markers") or 0)
        return load_robot(base, n_markers=nm) if nm and base.n_markers != nm else base
    spec = robot if robot is not None else (m.get("robot_spec") or m.get("robot"))
    if spec is None:
        raise ValueError("the fit names no robot; pass robot=")
    nm = int(m.get("n_markers") or 0)
    if isinstance(spec, SerialRobot):
        base = spec
    else:
        base = load_robot(spec, root=m.get("root"), tip=m.get("tip"), n_markers=nm or None)
        if m.get("urdf_chain_masses") and base.meta.get("urdf"):
            from .masses import with_urdf_masses

            base = with_urdf_masses(base)
    if nm and base.n_markers != nm:
        base = load_robot(base, n_markers=nm)
    return base


def simulate_from_fit(fit, robot=None, readings=None, n_poses: int = 50, strategy: str = "S4", measure=None,
                      noise=None, seed: int | None = 0, context=None, geometric_only: bool = False, **kw):
    """Simulate a dataset with the robot as identified by a diagnosis.

    Parameters
    ----------
    fit : DiagnosisResult, dict or JSON path (``estcal diagnose --json``).
    robot : nominal robot (default from the fit).
    readings : (N, n) joint readings to simulate at (e.g. the measured poses);
        otherwise ``n_poses`` from ``strategy``.
    measure : ``points`` / ``position`` / ``pose`` (default: ``points`` when the
        fit has several markers, else ``position``).
    noise : any form of :meth:`estcal.methods.NoiseModel.parse` (a float σ: position σ m, orientation
        σ / 0.1 m rad);
        default the fit's known noise, else the per-coordinate RMS the extended
        model left (``rmse / √3``).
    context : per-pose ``t`` / ``temperature`` / ``payload`` (dict) for the effects.
    **kw : passed to :func:`estcal.simulate.simulate`.

    Returns
    -------
    estcal.simulate.SimulationResult — its ``true_robot`` is the identified robot.
    """

    d = load_fit(fit)
    geo, specs = identified_robot(d, robot, geometric_only)
    if measure is None:
        measure = "points" if geo.n_markers > 1 else "position"
    if noise is None:
        nz = d.get("noise") or d["model"].get("noise") or {}
        if nz.get("known"):
            s = float(nz["position"])
        else:
            s = float(d["model"]["residual"]["rmse_mm"]) * 1e-3 / np.sqrt(3.0)
        noise = NoiseModel(position=s, orientation=float(nz.get("orientation", s)) if nz.get("known") else s)
    else:
        noise = simulation_noise(noise)
    ctx = dict(context or {})
    if d["model"].get("approach_from_order") and any(sp["effect"] == "backlash" for sp in specs):
        # the backlash was identified against the approach direction: keep that meaning
        # (directions drawn at random; see simulate_like for the recorded ones)
        kw["record_approach"] = True
    return simulate(geo, n_poses=n_poses, strategy=strategy, measure=measure, errors=None, effects=specs,
                    noise=noise, seed=seed, readings=readings, t=ctx.get("t"),
                    temperature=ctx.get("temperature"), payload=ctx.get("payload"), **kw)


def simulate_like(fit, data, robot=None, noise=None, seed: int | None = 0):
    """A copy of the measured ``data`` whose measurements are replaced by the identified robot's
    prediction plus Gaussian noise — same poses, same time/approach/payload columns.

    Unlike :func:`simulate_from_fit` (which draws approach directions at random), the
    context of the measurement is kept, so effects driven by recorded columns (backlash by
    approach direction, drift, thermal expansion) act as they did on the real robot.

    ``noise``: position σ (m) of independent noise on every coordinate. Default: the error the diagnosis
    found — when the fit carries its rigid error per posture (``random_effect``: the variances Ψ of a rigid
    motion ``(δt, δφ)`` of the measured body, in the measuring frame, and the within-posture σ), every row's
    body moves by its own draw ``δt + δφ × (x_i − c)`` about its centroid ``c``, plus σ on each coordinate
    (:mod:`estcal.discrepancy.relevance`, "Rows within a posture"); without it, as :func:`simulate_from_fit`.
    Independent noise of the same RMSE carries more information per posture than the rigid error it stands
    for: simulated that way, a fit is more accurate than on the real rows.
    """

    d = load_fit(fit)
    geo, specs = identified_robot(d, robot)
    rob = geo
    for sp in specs:
        rob = rob.add_effect(make_effect(sp["effect"], rob, joints=sp["joints"], **sp["options"]))
        for n, v in sp["params"].items():
            rob.params[n] = v
    rigid = None
    re_ = d.get("random_effect") or {}
    if noise is None and re_.get("psi_si") is not None:
        rigid = np.asarray(re_["psi_si"], float)
        noise = float(re_["sigma_mm"]) * 1e-3
    elif noise is None:
        nz = d.get("noise") or {}
        noise = float(nz["position"]) if nz.get("known") else \
            float(d["model"]["residual"]["rmse_mm"]) * 1e-3 / np.sqrt(3.0)
    m = d["model"]
    if m.get("approach_from_order"):
        from estcal.io.prepare import derive_approach

        data = derive_approach(data)
    data_c = with_effect_context(rob, data)
    if m.get("session_time") and "t" in data_c.context:
        t = data_c.context["t"]
        data_c.context["t"] = t - (t.mean() if m["session_time"] == "centred" else t.min())
    kin = rob.kinematics(data_c.readings, context=data_c.context, jacobian=False)
    rng = np.random.default_rng(seed)
    out = data.subset(slice(None))
    # the rigid error of every row's body (zero without one): drawn first, so a seed gives the same noise on top
    dt, dphi = (np.zeros((data.n, 3)),) * 2 if rigid is None else \
        np.split(rng.normal(0.0, 1.0, (data.n, 6)) * np.sqrt(np.maximum(rigid, 0.0)), 2, axis=1)
    if data.kind == "pose":
        from estcal.kinematics.transforms import so3_exp

        out.p = kin.p + dt + rng.normal(0, noise, kin.p.shape)
        out.R = so3_exp(dphi) @ so3_exp(rng.normal(0, noise, (data.n, 3))) @ kin.R
    else:
        k = data.n_points
        pred = kin.points[:, :k] if rob.n_markers >= k else kin.p[:, None, :]
        arm = pred - pred.mean(axis=1, keepdims=True)  # one point: no lever arm, its translation only
        out.points = pred + dt[:, None, :] + np.cross(dphi[:, None, :], arm) + rng.normal(0, noise, pred.shape)
    out.path = f"simulated from fit ({data.where})"
    return out


def residual_comparison(fit, measured, simulated, robot=None, noise=None) -> dict:
    """Geometric-model residual statistics on measured vs simulated data.

    Both datasets get the same geometric fit (:func:`estcal.discrepancy.geometric.fit_geometric`
    from the nominal robot); returned per dataset: RMSE / max (mm), χ²/dof and the RMS of the
    partial joint residual of every joint (mrad or mm). Similar rows mean the simulation
    reproduces what the geometric model misses on the real robot.
    """

    d = load_fit(fit)
    nominal = _nominal(d["model"], robot)
    nm = noise or NoiseModel(**{k: v for k, v in (d.get("noise") or {}).items()
                                if k in ("position", "orientation", "scalar", "known")})
    out = {}
    for label, data in (("measured", measured), ("simulated", simulated)):
        # the diagnosis's relevance-prior geometry ("sparse") has no unpenalised twin: the full level for both
        level = d["model"].get("geometric_level", "full")
        problem, res, free, _ = fit_geometric(nominal, data, nm, level="full" if level == "sparse" else level)
        dq, _ = partial_joint_residuals(problem, res.theta)
        r, mx = _scores(problem.robot, res.theta, [data])
        out[label] = {"rmse_mm": r, "max_mm": mx, "chi2_per_dof": float(res.chi2 / max(res.dof, 1)),
                      "partial_rms": {n: float(np.sqrt(np.mean(dq[:, j] ** 2)) * 1e3)
                                      for j, n in enumerate(problem.robot.joint_names)}}
    return out
