"""The joint-space residual GP's objective (:func:`estcal.discrepancy.residual.joint_gp_objective`, formed on the
posture blocks with a ≥ b only) against the dense computation: K assembled entry by entry from the kernel of
:class:`JointGP`, ½ YᵀK⁻¹Y + ½ log det K by numpy's solve and slogdet, and its gradient by central differences."""
from __future__ import annotations

import numpy as np

from estcal.discrepancy.residual import JointGP, _joint_gp_blocks_objective, joint_gp_objective


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


def test_rigid_body_designs_are_reduced_to_their_signal_range_exactly():
    """Several points of one rigid body (the markers of a tool): every joint parameter moves them by a twist,
    so each posture's m = 3k coordinates carry signal in 6 directions only (5 for two points) and the
    objective factorises the rotated problem (N·r rows) plus the noise-only remainder. Value and gradient
    must still be the dense likelihood of all N·m rows and its central differences."""
    rng = np.random.default_rng(5)
    for k, rank in ((4, 6), (2, 5)):
        N, m = 8, 3 * k
        pts = rng.normal(scale=0.2, size=(N, k, 3))
        joint_of = np.repeat(np.arange(3), 4)
        # d(point)/d(twist) = [I, −[x]×] for each point, times a random twist per parameter
        skew = lambda v: np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])  # noqa: E731
        Gtw = np.stack([np.vstack([np.hstack([np.eye(3), -skew(x)]) for x in pts[a]]) for a in range(N)])  # (N, m, 6)
        H = Gtw @ rng.normal(size=(N, 6, joint_of.size))
        assert np.linalg.matrix_rank(H[0]) == rank < m
        Q = rng.uniform(-1.5, 1.5, (N, 3))
        Y = rng.normal(scale=0.3, size=N * m)
        f = joint_gp_objective(Q, H, Y, joint_of, [0, 1, 2], m)
        unreduced = _joint_gp_blocks_objective(Q, H, Y, joint_of, [0, 1, 2], m)
        for x in (np.r_[np.log([0.5, 0.2, 1.0]), np.log([0.7, 1.5, 0.4]), np.log(0.3)],
                  np.r_[np.log([2.0, 0.05, 0.3]), np.log([3.0, 0.2, 1.0]), np.log(0.05)]):
            val, g = f(x)
            assert abs(val - _dense_nll(Q, H, Y, joint_of, x)) <= 1e-9 * max(1.0, abs(val))
            v0, g0 = unreduced(x)
            assert abs(val - v0) <= 1e-10 * max(1.0, abs(val))
            np.testing.assert_allclose(g, g0, rtol=1e-7, atol=1e-9 * np.abs(g0).max())
            # the dense likelihood's rounding (noise 0.05 under a rank-6 signal) needs the wider step
            h = 1e-4
            fd = np.array([(_dense_nll(Q, H, Y, joint_of, x + h * e) - _dense_nll(Q, H, Y, joint_of, x - h * e))
                           / (2 * h) for e in np.eye(x.size)])
            np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
