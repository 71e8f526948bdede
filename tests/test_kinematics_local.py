"""The local composition of a chain's segments for one θ, batched over the segments with the same motions
(``SerialRobot._all_segments_local``), gives the kinematics of the segment-by-segment composition bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.kinematics import puma560, tiago
from estcal.kinematics.chain import SerialRobot


@pytest.mark.parametrize("make", [puma560, lambda: tiago(n_markers=2)], ids=["khalil-puma560", "urdf-tiago"])
def test_batched_segments_are_bit_identical(make, monkeypatch, request):
    if make is not puma560:
        request.getfixturevalue("tiago_dir")  # skips without the shared TIAGo URDF
    robot = make()
    rng = np.random.default_rng(1)
    theta = robot.params.values + 1e-3 * rng.normal(size=robot.n_params)
    q = rng.uniform(-1, 1, (20, robot.n_joints))
    batched = robot.kinematics(q, theta)
    assert robot._local_cache[1]  # the batched pass filled the cache
    monkeypatch.setattr(SerialRobot, "_all_segments_local", lambda self, theta, store: None)
    robot.__dict__.pop("_local_cache", None)
    one_by_one = robot.kinematics(q, theta)
    for f in ("R", "p", "points", "J", "J_points"):
        assert np.array_equal(getattr(batched, f), getattr(one_by_one, f)), f


@pytest.mark.parametrize("n", [1, 37, 256, 300])
def test_rotation_of_a_vector_is_the_sum_of_three_products(n):
    """``_rot_vec`` (a matmul up to 16 poses, an einsum beyond) is R[:, 0] v0 + R[:, 1] v1 + R[:, 2] v2 to rounding."""
    from estcal.kinematics.chain import _rot_vec

    rng = np.random.default_rng(n)
    R, v = rng.normal(size=(3, 3, n)), rng.normal(size=3)
    np.testing.assert_allclose(_rot_vec(R, v), R[:, 0] * v[0] + R[:, 1] * v[1] + R[:, 2] * v[2], rtol=0, atol=1e-14)


def test_segment_plan_follows_a_chain_that_grows(tiago_dir):
    """The grouping of the segments is kept across θ and redone when a motion is appended in place (a robot
    being built)."""
    robot = tiago(n_markers=1)
    robot.kinematics(np.zeros((3, robot.n_joints)))
    plan = robot._segment_plan()
    assert robot._segment_plan() is plan
    link = next(lk for lk in robot.links if lk.before)
    link.before.append(link.before[-1])
    try:
        grown = robot._segment_plan()
        assert grown is not plan
        assert sum(len(keys) for _, keys, *_ in grown) == sum(len(keys) for _, keys, *_ in plan)
        assert max(len(kinds) for *_, kinds, _ in grown) == 7
    finally:
        link.before.pop()
    assert robot._segment_plan() is not grown
