"""LM with Gauss–Newton steps first and the step-left stopping rule reaches the least-squares minimum.

The minimum is found independently: scipy's MINPACK LM (``least_squares``, analytic Jacobian — itself
checked against finite differences in the kinematics tests) at tolerances 1e-15, polished by plain
Gauss–Newton steps with ``numpy.linalg.lstsq``. estcal's LM, Gauss–Newton and iterated LS must stop within
about 1e-6 standard deviation of it (docs/benchmarks.md, "Everyday commands"): on TIAGo's real data
(large residuals: Gauss–Newton converges linearly, ×0.1 per iteration) and on simulated PUMA data.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from estcal.estimate import calibrate_lsq
from estcal.estimate._common import resolve_free
from estcal.estimate.lsq import _clearly_identifiable, _factor
from estcal.identify.select import UnidentifiableError, check_identifiable
from estcal.io import load_dataset
from estcal.kinematics import puma560, tiago
from estcal.methods import NoiseModel, Problem
from estcal.simulate import simulate
from estcal.workflows.calibrate import run_calibration

from conftest import TIAGO_DIR


def independent_minimum(problem, free):
    """The free parameters at the minimum of Σ (e/σ)², by scipy + Gauss–Newton polishing."""
    p, fidx, _ = resolve_free(problem, free)
    th0 = p.params.values.copy()

    def at(x):
        th = th0.copy()
        th[fidx] = x
        return th

    def fun(x):
        r = p.evaluate(at(x), jacobian=False)
        return r.e / r.sigma

    def jac(x):
        r = p.evaluate(at(x))
        return -r.H[:, fidx] / r.sigma[:, None]

    x = least_squares(fun, th0[fidx], jac=jac, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                      max_nfev=5000).x
    for _ in range(40):  # Gauss–Newton polish: linear convergence at large residuals, so many steps
        x = x + np.linalg.lstsq(jac(x), -fun(x), rcond=None)[0]
    return x


@pytest.fixture(scope="module")
def tiago_problem():
    if not (TIAGO_DIR / "tiago_48_schunk.urdf").exists():
        pytest.skip(f"TIAGo data not found at {TIAGO_DIR}")
    robot = tiago(n_markers=1)
    train = load_dataset(TIAGO_DIR / "qualisys_2021-11-30_static_postures.csv", robot, points=1)
    noise = NoiseModel(position=1e-3)
    _, sel, _ = run_calibration(robot, train, level="full", noise=noise)
    # the start of benchmarks/bench_calibration.py (FIGAROH comparison): the registration-level fit
    start = Problem(robot.with_values(np.asarray(sel.theta, float)), [(None, train, noise)])
    return start, sel.identifiable


@pytest.mark.parametrize("method", ["lm", "gauss-newton", "iterated-lls"])
def test_tiago_full_level_stops_at_the_minimum(tiago_problem, method):
    problem, free = tiago_problem
    ref = independent_minimum(problem, free)
    res = calibrate_lsq(problem, method, free=free)
    assert res.converged
    assert np.max(np.abs(res.estimate - ref) / res.std) < 2e-6
    # the figures reported at the minimum: χ² to 1e-12 relative
    r = resolve_free(problem, free)
    th = r[0].params.values.copy()
    th[r[1]] = ref
    rows = problem.evaluate(th, jacobian=False)
    assert res.chi2 == pytest.approx(float(np.sum((rows.e / rows.sigma) ** 2)), rel=1e-12)


@pytest.mark.parametrize("measure, noise", [("position", 1e-3), ("pose", 5e-5)])
def test_simulated_puma_stops_at_the_minimum(measure, noise):
    sim = simulate(puma560(), 40, measure=measure, errors="random", noise={"position": noise, "orientation": noise},
                   seed=4)
    nm = NoiseModel(position=noise, orientation=noise)
    sel = run_calibration(puma560(), sim.dataset, level="full", noise=nm)[1]
    problem, free = Problem(puma560().with_values(np.asarray(sel.theta, float)), [(None, sim.dataset, nm)]), sel.identifiable
    ref = independent_minimum(problem, free)
    for method in ("lm", "gauss-newton"):
        res = calibrate_lsq(problem, method, free=free)
        assert res.converged
        assert np.max(np.abs(res.estimate - ref) / res.std) < 2e-6, method


def test_clear_identifiability_agrees_with_the_scan():
    """The factorisation's shortcut says "identifiable" only where the full scan passes, and the scan
    still refuses (naming the parameters) where it does not."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 6)) * np.logspace(-3, 1, 6)
    b = rng.normal(size=50)
    names = [f"p{i}" for i in range(6)]
    assert _clearly_identifiable(_factor(A, b))
    check_identifiable(A, names)  # passes
    dep = A.copy()
    dep[:, 4] = 2 * A[:, 1] - 0.5 * A[:, 3]
    assert not _clearly_identifiable(_factor(dep, b))
    with pytest.raises(UnidentifiableError, match="p4"):
        check_identifiable(dep, names)
    zero = A.copy()
    zero[:, 2] = 0.0
    assert not _clearly_identifiable(_factor(zero, b))
    with pytest.raises(UnidentifiableError, match="p2"):
        check_identifiable(zero, names)
    # nearly dependent (|R_jj| ~ 1e-9, above the structural tolerance, inside the margin): the shortcut
    # defers to the scan, which accepts it
    near = A.copy()
    u = rng.normal(size=50)
    near[:, 5] = A[:, 0] + 1e-9 * np.linalg.norm(A[:, 0]) * u / np.linalg.norm(u)
    assert not _clearly_identifiable(_factor(near, b))
    check_identifiable(near, names)


def test_calibrate_refuses_dependent_parameters_as_before(tiago_problem):
    problem, free = tiago_problem
    with pytest.raises(UnidentifiableError):
        calibrate_lsq(problem, "lm", free=list(free) + ["offset_arm_1_joint", "rz_arm_1_joint"])
