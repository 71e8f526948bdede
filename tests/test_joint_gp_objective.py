"""The joint-space residual GP's objective (:func:`estcal.discrepancy.residual.joint_gp_objective`, formed on the
posture blocks with a ≥ b only) against the dense computation: K assembled entry by entry from the kernel of
:class:`JointGP`, ½ YᵀK⁻¹Y + ½ log det K by numpy's solve and slogdet, and its gradient by central differences."""
from __future__ import annotations

import numpy as np

from estcal.discrepancy.residual import JointGP, joint_gp_objective


def _problem(N=9, m=6, seed=3):
    rng = np.random.default_rng(seed)
    joint_of = np.repeat(np.arange(3), 4)  # 3 joints, 4 placement parameters each
    Q = rng.uniform(-1.5, 1.5, (N, 3))
    H = rng.normal(size=(N, m, joint_of.size))
    Y = rng.normal(scale=0.3, size=N * m)
    return Q, H, Y, joint_of


def _dense_nll(Q, H, Y, joint_of, x):
    na = 3
    amp, ls, s = np.exp(x[:na]), np.exp(x[na:2 * na]), float(np.exp(x[-1]))
    gp = JointGP(["a", "b", "c"], [], joint_of, np.ones(joint_of.size), Q, H, Y.reshape(len(Q), -1), amp, ls, s,
                 H.shape[1] // 3)
    K = gp._blocks(Q, H, Q, H) + s * s * np.eye(Y.size)
    return 0.5 * Y @ np.linalg.solve(K, Y) + 0.5 * np.linalg.slogdet(K)[1]


def test_objective_is_the_dense_marginal_likelihood_and_its_gradient():
    Q, H, Y, joint_of = _problem()
    f = joint_gp_objective(Q, H, Y, joint_of, [0, 1, 2], H.shape[1])
    for x in (np.r_[np.log([0.5, 0.2, 1.0]), np.log([0.7, 1.5, 0.4]), np.log(0.3)],
              np.r_[np.log([2.0, 0.05, 0.3]), np.log([3.0, 0.2, 1.0]), np.log(0.05)]):
        val, g = f(x)
        assert abs(val - _dense_nll(Q, H, Y, joint_of, x)) <= 1e-9 * max(1.0, abs(val))
        h = 1e-6
        fd = np.array([(_dense_nll(Q, H, Y, joint_of, x + h * e) - _dense_nll(Q, H, Y, joint_of, x - h * e)) / (2 * h)
                       for e in np.eye(x.size)])
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())
