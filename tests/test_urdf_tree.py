"""The fixed subtree of a URDF link (estcal.kinematics.urdf.fixed_subtree), used to find the measured
tool frame (estcal frames) and the tip of an exported model: checked against transforms composed by hand."""
from types import SimpleNamespace as J

import numpy as np

from estcal.kinematics.transforms import make_transform, rot_axis
from estcal.kinematics.urdf import fixed_subtree


def test_fixed_subtree_composes_fixed_joints_only():
    A = make_transform(rot_axis([0, 0, 1], 0.3), [0.1, 0.0, 0.2])
    B = make_transform(rot_axis([1, 0, 0], -0.7), [0.0, 0.05, 0.0])
    C = make_transform(rot_axis([0, 1, 0], 1.1), [0.3, 0.0, 0.0])
    joints = [J(parent="flange", child="tool", type="fixed", origin=A),
              J(parent="tool", child="tcp", type="fixed", origin=B),
              J(parent="flange", child="camera", type="fixed", origin=None),
              J(parent="tool", child="finger", type="prismatic", origin=C),  # moving: not in the subtree
              J(parent="finger", child="pad", type="fixed", origin=C)]
    got = dict(fixed_subtree(joints, "flange"))
    assert list(dict(fixed_subtree(joints, "flange"))) == ["flange", "camera", "tool", "tcp"]  # name order
    np.testing.assert_allclose(got["flange"], np.eye(4))
    np.testing.assert_allclose(got["camera"], np.eye(4))
    np.testing.assert_allclose(got["tool"], A)
    np.testing.assert_allclose(got["tcp"], A @ B, atol=1e-15)
    assert [n for n, _ in fixed_subtree(joints, "finger")] == ["finger", "pad"]
