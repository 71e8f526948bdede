"""The random restarts of the joint-space GP fit (:func:`estcal.discrepancy.residual._restarts`) run only when the
first L-BFGS-B run is suspect — stopped on a bound of the box or not converged — and then still find a better
optimum than a first run trapped on the box. Checked on objectives whose optima are known in closed form."""
from __future__ import annotations

import numpy as np

from estcal.discrepancy.residual import _restarts, _suspect

BOUNDS = [(-3.0, 3.0)] * 3  # na = 1: [log a, log ℓ, log s]
CENTRE = np.array([0.5, 0.4, -0.1])
CURV = np.array([1.0, 30.0, 900.0])
#: fit_joint_gp's default start for a residual RMS of 1 and a joint spread of 1: a = 0.3, ℓ = 1, s = 0.7
X0 = np.r_[np.log(0.3), 0.0, np.log(0.7)]


def _counted(f):
    calls = []

    def g(x):
        calls.append(np.array(x))
        return f(x)
    return g, calls


def _quadratic(x):
    d = x - CENTRE
    return float(0.5 * np.sum(CURV * d * d)), CURV * d


def _run(nll, restarts, maxiter=200, seed=0):
    gen = np.random.default_rng(seed)
    best = _restarts(nll, BOUNDS, restarts, gen, maxiter, X0)
    drawn = not np.array_equal(gen.uniform(size=3), np.random.default_rng(seed).uniform(size=3))
    return best, drawn


def test_an_interior_converged_optimum_is_kept_without_a_restart():
    nll, calls = _counted(_quadratic)
    best, drawn = _run(nll, restarts=3)
    assert best.success and not _suspect(best, BOUNDS)
    np.testing.assert_allclose(best.x, CENTRE, atol=1e-4)
    assert not drawn  # no random start drawn, so no restart run
    # one run only: the evaluations are those of a single L-BFGS-B run from the default start
    nll1, calls1 = _counted(_quadratic)
    _run(nll1, restarts=0)
    assert len(calls) == len(calls1)


def test_a_run_stopped_on_a_bound_restarts_and_the_restart_wins():
    # along x0 a slope pulls a descent from the default start (log 0.3) onto the lower bound −3 (value −0.15 + …);
    # the global minimum is the well at x0 ≈ 2 (value ≈ −1.9), reachable from a random start
    def f(x):
        q, gq = _quadratic(np.r_[CENTRE[0], x[1:]])
        w = np.exp(-(x[0] - 2.0) ** 2)
        return q - 2.0 * w + 0.05 * x[0], np.r_[4.0 * (x[0] - 2.0) * w + 0.05, gq[1:]]
    first = _restarts(f, BOUNDS, 0, np.random.default_rng(0), 200, X0)
    assert first.x[0] == BOUNDS[0][0] and _suspect(first, BOUNDS)
    best, drawn = _run(f, restarts=6)
    assert drawn
    assert abs(best.x[0] - 2.0) < 0.05 and best.fun < first.fun - 1.5


def test_a_run_that_did_not_converge_restarts():
    nll, _ = _counted(_quadratic)
    first = _restarts(nll, BOUNDS, 0, np.random.default_rng(0), 1, X0)
    assert not first.success and _suspect(first, BOUNDS)
    _, drawn = _run(nll, restarts=1, maxiter=1)
    assert drawn
