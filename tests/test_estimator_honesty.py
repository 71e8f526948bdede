"""Honest estimators (docs/probabilistic.md): ``converged`` is the estimator's own convergence test,
and on real data every registered estimator agrees with LM within 0.05 σ or says it did not converge.

Real data of ../shared/data (skipped when absent): the UR10 camera poses (23 full poses,
../shared/data/ur10/README.md) and the TALOS left arm, session 02-10 (62 positions of one marker,
../shared/data/talos/README.md), read as published through their column maps (docs/maps).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import estcal
from estcal.estimate.registry import estimator_names
from estcal.kinematics.robots import shared_dir

DATA = shared_dir() / "data"
MAPS = Path(__file__).resolve().parents[1] / "docs" / "maps"
TOL_SIGMA = 0.05

CASES = {
    # data, map, robot, chain, markers, free set: the base frame and the joint offsets the data
    # determine (TALOS: not the wrist offsets 5 and 6, which do not move the marker at its initial
    # position, the tool origin)
    "ur10": ("ur10/calibration.csv", "ur10.yaml", "ur10/ur10_robot.urdf", "base_link", "wrist_3_link", None, None),
    "talos": ("talos/talos_feb_arm_02_10_contact.csv", "talos.yaml", "talos/talos_reduced.urdf", "base_link",
              "arm_left_7_link", 1, "base_*,offset_torso_2_joint,offset_arm_left_[1-4]_joint,marker1_*"),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def case(request):
    csv, cmap, urdf, root, tip, markers, free = CASES[request.param]
    if not (DATA / csv).exists():
        pytest.skip(f"{DATA / csv} absent (the shared real data)")
    robot = estcal.load_robot(DATA / urdf, root=root, tip=tip, n_markers=markers)
    data = estcal.load_dataset(DATA / csv, robot, column_map=MAPS / cmap)
    kw = dict(checks=False)  # the robot object carries the marker
    lm = estcal.calibrate(robot, data, "lm", **(dict(free=free.split(",")) if free else dict(level="joint_offset")),
                          **kw)
    assert lm.converged and len(lm.names) >= 14
    return request.param, robot, data, kw, lm


def _run(case, name, **options):
    _, robot, data, kw, lm = case
    res = estcal.calibrate(robot, data, name, free=lm.names, **kw, **options)
    dz = np.abs(res.estimate[[res.names.index(n) for n in lm.names]] - lm.estimate) / lm.std
    return res, float(dz.max())


OPTIONS = {"gtsam-timevarying": {"q": 1e-9}}  # a time-varying model with (almost) no variation


@pytest.mark.parametrize("name", [n for n in estimator_names() if n not in ("lm", "mcmc")])
def test_every_estimator_agrees_with_lm_or_says_it_did_not_converge(case, name):
    res, dz = _run(case, name, **OPTIONS.get(name, {}))
    assert dz <= TOL_SIGMA or not res.converged, f"{case[0]}, {name}: {dz:.3g} σ from LM with converged=True"


def test_kalman_and_ukf_iterate_to_convergence_and_a_single_pass_says_so(case):
    """The default Kalman estimators pass their convergence test (a pass moving the estimate by
    < 10⁻³ σ) within 0.05 σ of LM; one pass — 2 to 50 σ from LM on these data — reports
    converged=False, since a single pass has no convergence test."""
    for name in ("kalman", "ukf"):
        res, dz = _run(case, name)
        assert res.converged and dz < 0.01 and res.extra["last_change_sigma"] < 1e-3, (name, dz)
        assert 2 <= res.n_iterations < 20
        one, dz1 = _run(case, name, passes=1)
        assert not one.converged and dz1 > 1.0, (name, dz1)


def test_mcmc_converged_is_its_own_test(case):
    """MCMC estimates the posterior *mean*, not the mode: its convergence test is the chain's (every
    parameter's ESS ≥ target, the chain longer than 50 τ). On the UR10 its mean is up to 0.16 σ from
    LM's mode on one parameter — 10 times its Monte Carlo error, and the same for a second chain —
    so the gap is the posterior's (a skewed posterior at 15× the nominal noise), not a chain that
    has not converged. The TALOS chain mixes slowly (≈ 100 s) and is left out of the suite (its
    mean is 0.9 σ from the mode, its median alike: a non-Gaussian posterior at 70× the noise)."""
    if case[0] != "ur10":
        pytest.skip("TALOS: a 100 s chain (see the docstring)")
    lm = case[-1]
    runs = []
    for seed in (1, 2):
        res, _ = _run(case, "mcmc", seed=seed)
        ex = res.extra
        assert res.converged == bool(np.min(ex["ess"]) >= 1000 and ex["n_steps"] > 50 * np.max(ex["tau"]))
        idx = [res.names.index(n) for n in lm.names]
        runs.append((res.estimate[idx], res.std[idx] / np.sqrt(np.asarray(ex["ess"])[idx])))
    (m1, e1), (m2, e2) = runs
    assert np.all(np.abs(m1 - m2) <= 4 * np.hypot(e1, e2))  # the mean is the posterior's, to its MC error
    assert np.all(np.abs(m1 - lm.estimate) <= 0.25 * lm.std)


@pytest.mark.parametrize("options", [dict(relinearize_sigma=1e9, final_sigma=1e9),
                                     dict(linear=False, relinearize_threshold=1e9)],
                         ids=["containers-never-relinearised", "customfactor-never-relinearised"])
def test_isam2_stopped_far_from_the_minimum_says_it_did_not_converge(case, options):
    """iSAM2 kept from relinearising (the linear containers with the relinearisation and end-of-stream
    thresholds at 1e9 σ; the CustomFactor graph with gtsam's relinearisation threshold at 1e9) stops
    at the minimum of the model linearised at the nominal parameters: 10 σ (UR10) and 3 σ (TALOS)
    from LM. ``converged`` is the test at the returned estimate — every measurement and the prior
    linearised there, the Gauss–Newton step ≤ 1e-3 of its marginal σ — not the end of the stream."""
    from estcal.estimate.factorgraph import CONVERGED_STEP_SIGMA

    res, dz = _run(case, "isam2", **options)
    assert dz > 1.0, dz  # the perturbation does stop it far from the minimum
    assert not res.converged and res.extra["final_step_sigma"] > 100 * CONVERGED_STEP_SIGMA


@pytest.mark.parametrize("options", [{}, dict(linear=False), dict(relinearize_sigma=1e9)],
                         ids=["containers", "customfactor", "containers-finished-at-the-end"])
def test_isam2_reaches_lm_on_real_data(case, options):
    """Both iSAM2 paths converge to LM's minimum (within 0.05 σ: the wide prior's pull is below 1e-3 σ).
    On TALOS undamped steps while few poses have arrived used to wander by whole turns of the base
    yaw and joint offsets, to a 2π-equivalent minimum 394 σ (containers) / 646 σ (CustomFactor) from
    LM's; steps are now accepted only when they lower the cost (Levenberg–Marquardt otherwise;
    Powell's dogleg inside iSAM2 for the CustomFactor graph). A stream that never relinearises is
    finished at the end by Gauss–Newton on the whole model."""
    from estcal.estimate.factorgraph import CONVERGED_STEP_SIGMA

    res, dz = _run(case, "isam2", **options)
    assert res.converged and dz < TOL_SIGMA and res.extra["final_step_sigma"] <= CONVERGED_STEP_SIGMA, dz
