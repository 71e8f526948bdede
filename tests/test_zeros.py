"""The moved-zero test's algebra (estcal.discrepancy.zeros) against brute force: the grouped deletion formula's
held-out residuals and estimates equal refits without each posture's rows; the joint-zero parameters are found
under both naming schemes."""
from __future__ import annotations

import numpy as np

from estcal.discrepancy.zeros import _groups, _loo, zero_parameters


def test_leave_one_posture_out_matches_refits():
    rng = np.random.default_rng(4)
    # postures of 3, 4 and 6 rows (several block sizes), in a shuffled row order
    sizes = [3] * 5 + [4] * 4 + [6] * 3
    pose = np.repeat(np.arange(len(sizes)), sizes)
    pose = pose[rng.permutation(len(pose))]
    X = rng.normal(size=(len(pose), 5))
    r = X @ rng.normal(size=5) + 0.1 * rng.normal(size=len(pose))
    groups, n = _groups(pose)
    assert n == len(sizes) and sorted(groups) == [3, 4, 6]
    sq, est, coef = _loo(X, r, groups)
    np.testing.assert_allclose(coef, np.linalg.lstsq(X, r, rcond=None)[0], rtol=1e-10)
    order = np.concatenate([idx[:, 0] for idx in groups.values()])  # the posture of each output, via a row
    for k, row in enumerate(order):
        out = pose == pose[row]
        c = np.linalg.lstsq(X[~out], r[~out], rcond=None)[0]
        e = r[out] - X[out] @ c
        np.testing.assert_allclose(sq[k], e @ e, rtol=1e-9)
        np.testing.assert_allclose(est[k], c, rtol=1e-9, atol=1e-12)


def test_zero_parameters_of_both_naming_schemes():
    from estcal.io.robotfile import load_robot
    from estcal.kinematics import tiago

    puma = load_robot("puma560")
    assert zero_parameters(puma) == [(f"j{i}", f"offset_{i}") for i in range(1, 7)]
    t = tiago(n_markers=1)
    assert zero_parameters(t) == [(j, f"offset_{j}") for j in t.joint_names]
