"""The local composition of a chain's segments for one θ, batched over the segments with the same motions
(``SerialRobot._all_segments_local``), gives the kinematics of the segment-by-segment composition bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.kinematics import puma560, tiago
from estcal.kinematics.chain import SerialRobot


@pytest.mark.parametrize("make", [puma560, lambda: tiago(n_markers=2)], ids=["khalil-puma560", "urdf-tiago"])
def test_batched_segments_are_bit_identical(make, monkeypatch):
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
