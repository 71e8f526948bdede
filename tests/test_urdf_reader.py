"""estcal's URDF reader (estcal.kinematics.urdf.load_urdf, the standard library's ElementTree) against
yourdfpy, the independent reader: every URDF of ../shared/data and of the test suite read both ways
gives the same links, inertials, joints (type, parent, child, origin, axis, limit, mimic) and the same
chains, to the bit (the origin matrices are composed as yourdfpy composes them)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estcal.kinematics.robots import puma560
from estcal.kinematics.urdf import load_urdf, robot_from_tree
from estcal.kinematics.urdf_export import export_urdf

yourdfpy = pytest.importorskip("yourdfpy")

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: (file, root, tip) of the published URDFs, as docs/dataset.md uses them
SHARED = [("tiago/tiago_48_schunk.urdf", None, "wrist_ft_tool_link"),
          ("ur10/ur10_robot.urdf", "world", "camera_color_optical_frame"),
          ("talos/talos_reduced.urdf", "base_link", "arm_left_7_link")]


def _link(name, parent, child, typ="revolute", origin='<origin xyz="0 0 0.1" rpy="0 0 0"/>', axis="0 0 1",
          extra=""):
    return (f'<joint name="{name}" type="{typ}"><parent link="{parent}"/><child link="{child}"/>{origin}'
            f'<axis xyz="{axis}"/><limit lower="-1" upper="1" effort="1" velocity="1"/>{extra}</joint>')


def _urdf(joints, links):
    lk = "".join(f'<link name="{n}"/>' if not isinstance(n, tuple) else
                 f'<link name="{n[0]}"><inertial><origin xyz="{n[2]}" rpy="{n[3]}"/><mass value="{n[1]}"/>'
                 f'</inertial></link>' for n in links)
    return f'<?xml version="1.0"?><robot name="r">{lk}{joints}</robot>'


#: the URDF shapes the test suite writes (test_bad_input, test_integrity, test_fuzz_loaders, test_frames):
#: defaults (no origin, no axis, no rpy), rpy of every sign, prismatic and continuous joints, mimic,
#: inertials with and without origins, fixed tails
SUITE = {
    "two-revolute": _urdf(_link("a", "base", "l1") + _link("b", "l1", "l2"), ["base", "l1", "l2"]),
    "defaults": _urdf('<joint name="a" type="continuous"><parent link="base"/><child link="l1"/></joint>'
                      + _link("b", "l1", "l2", origin='<origin xyz="0.3 0 0"/>', axis="0 1 0"),
                      ["base", "l1", "l2"]),
    "rpy-prismatic": _urdf(_link("a", "base", "l1", origin='<origin xyz="0.01 -0.2 0.3" rpy="-1.5707963 0.3 2.9"/>')
                           + _link("b", "l1", "l2", typ="prismatic", axis="1 0 0",
                                   origin='<origin xyz="0.2 0 0" rpy="0 1.57 0"/>')
                           + _link("t", "l2", "tool", typ="fixed", origin='<origin xyz="0 0 0.05" rpy="3.14159 0 -0.5"/>'),
                           ["base", ("l1", 2.5, "0.1 0 0.02", "0 0 0.1"), ("l2", 1.0, "0 0 0", "0 0 0"), "tool"]),
    "mimic": _urdf(_link("j1", "a", "b", axis="0 0 1")
                   + _link("j2", "b", "c", origin='<origin xyz="0.3 0 0"/>', axis="0 1 0",
                           extra='<mimic joint="j1" multiplier="2" offset="0.1"/>')
                   + _link("j3", "c", "d", extra='<mimic joint="j1"/>'), ["a", "b", "c", "d"]),
    "tilted-axis": _urdf(_link("a", "base", "l1", axis="0.6 0 0.8") + _link("b", "l1", "l2", axis="0 -1 0"),
                         ["base", ("l1", 0.3, "0 0 0.1", "0 0 0"), "l2"]),
}


def _shared(rel):
    path = DATA / rel
    if not path.exists():
        pytest.skip(f"{path} not found (the published data live in ../shared next to the repository)")
    return path


def _same(a, b, what):
    if a is None or b is None:
        assert a is None and b is None, what
    else:
        a, b = np.asarray(a, float), np.asarray(b, float)
        assert a.shape == b.shape and np.array_equal(a, b), f"{what}: {a} != {b}"


def _compare_trees(ours, theirs):
    """Every kinematic field of the two readers' trees, exactly."""
    assert ours.robot.name == theirs.robot.name
    assert [lk.name for lk in ours.robot.links] == [lk.name for lk in theirs.robot.links]
    for a, b in zip(ours.robot.links, theirs.robot.links):
        assert (a.inertial is None) == (b.inertial is None), a.name
        if a.inertial is not None:
            assert a.inertial.mass == b.inertial.mass, a.name
            _same(a.inertial.origin, b.inertial.origin, f"link {a.name} inertial origin")
    assert [j.name for j in ours.robot.joints] == [j.name for j in theirs.robot.joints]
    for a, b in zip(ours.robot.joints, theirs.robot.joints):
        assert (a.type, a.parent, a.child) == (b.type, b.parent, b.child), a.name
        _same(a.origin, b.origin, f"joint {a.name} origin")
        _same(a.axis, b.axis, f"joint {a.name} axis")
        assert (a.limit is None) == (b.limit is None), a.name
        if a.limit is not None:
            for f in ("lower", "upper", "effort", "velocity"):
                assert getattr(a.limit, f) == getattr(b.limit, f), (a.name, f)
        assert (a.mimic is None) == (b.mimic is None), a.name
        if a.mimic is not None:
            assert (a.mimic.joint, a.mimic.multiplier, a.mimic.offset) == (b.mimic.joint, b.mimic.multiplier,
                                                                         b.mimic.offset), a.name


def _compare_chains(path, ours, theirs, root, tip):
    """The chains built from both trees: link constants, axes, limits, masses and the kinematics, exactly."""
    ra = robot_from_tree(ours, path, root, tip)
    rb = robot_from_tree(theirs, path, root, tip)
    assert ra.joint_names == rb.joint_names and ra.joint_types == rb.joint_types
    assert ra.params.names == rb.params.names and np.array_equal(ra.params.values, rb.params.values)
    assert np.array_equal(ra.limits, rb.limits)
    for la, lb in zip(ra.links, rb.links):
        assert np.array_equal(la.const, lb.const) and np.array_equal(la.joint_axis, lb.joint_axis), la.label
        assert la.mass == lb.mass and np.array_equal(la.com, lb.com), la.label
    q = ra.random_readings(20, rng=0)
    ka, kb = ra.kinematics(q), rb.kinematics(q)
    assert np.array_equal(ka.p, kb.p) and np.array_equal(ka.R, kb.R) and np.array_equal(ka.J, kb.J)
    return ra


def _theirs(path):
    return yourdfpy.URDF.load(str(path), build_scene_graph=False, build_collision_scene_graph=False,
                              load_meshes=False, load_collision_meshes=False)


@pytest.mark.parametrize("rel,root,tip", SHARED, ids=[s[0].split("/")[0] for s in SHARED])
def test_published_urdfs_read_as_yourdfpy_reads_them(rel, root, tip):
    path = _shared(rel)
    ours = load_urdf(path)
    _compare_trees(ours, _theirs(path))
    robot = _compare_chains(path, ours, _theirs(path), root, tip)
    assert robot.n_joints >= 6


@pytest.mark.parametrize("case", SUITE)
def test_suite_urdfs_read_as_yourdfpy_reads_them(case, tmp_path):
    path = tmp_path / f"{case}.urdf"
    path.write_text(SUITE[case])
    ours = load_urdf(path)
    _compare_trees(ours, _theirs(path))
    leaves = {lk.name for lk in ours.robot.links} - {j.parent for j in ours.robot.joints}
    if case == "mimic":  # a chain through a mimic joint is refused the same way from both trees
        from estcal.base.errors import RobotFileError

        msgs = []
        for tree in (ours, _theirs(path)):
            with pytest.raises(RobotFileError, match=r"joint 'j2' .* is a <mimic> of 'j1' \(q = 2·q_j1 \+ 0\.1\)") as e:
                robot_from_tree(tree, path, None, "d")
            msgs.append(str(e.value))
        assert msgs[0] == msgs[1]
    _compare_chains(path, ours, _theirs(path), None, "b" if case == "mimic" else sorted(leaves)[0])


def test_exported_urdfs_read_as_yourdfpy_reads_them(tmp_path):
    """The URDFs estcal writes (standalone, and a calibrated copy of the TIAGo file) read both ways."""
    puma = puma560()
    v = puma.params.values.copy()
    v[:6] += np.linspace(1e-3, 6e-3, 6)
    out = tmp_path / "puma.urdf"
    export_urdf(puma.with_values(v), out)
    _compare_trees(load_urdf(out), _theirs(out))
    _compare_chains(out, load_urdf(out), _theirs(out), "world", "tool")
    tiago = _shared("tiago/tiago_48_schunk.urdf")
    from estcal.kinematics.urdf import robot_from_urdf

    rob = robot_from_urdf(tiago, tip="wrist_ft_tool_link")
    w = rob.params.values.copy()
    w[rob.params.indices(["tx_arm_2_joint", "rz_arm_4_joint"])] += [2e-3, 1e-3]
    out2 = tmp_path / "tiago_cal.urdf"
    export_urdf(rob.with_values(w), out2, from_urdf=tiago)
    _compare_trees(load_urdf(out2), _theirs(out2))
    _compare_chains(out2, load_urdf(out2), _theirs(out2), None, "wrist_ft_tool_link")


@pytest.mark.parametrize("bad,pattern", [
    ('<origin xyz="0 0" rpy="0 0 0"/>', r"joint 'a': <origin xyz> needs 3 numbers, got '0 0'"),
    ('<origin xyz="0 0 x" rpy="0 0 0"/>', r"joint 'a': <origin xyz> needs 3 numbers, got '0 0 x'"),
    ('<origin xyz="0 0 nan" rpy="0 0 0"/>', r"joint 'a': <origin xyz> holds a non-finite number"),
    ('<origin xyz="0 0 0" rpy="0 inf 0"/>', r"joint 'a': <origin rpy> holds a non-finite number"),
])
def test_bad_numbers_are_named(bad, pattern, tmp_path):
    from estcal.base.errors import RobotFileError

    path = tmp_path / "n.urdf"
    path.write_text(SUITE["two-revolute"].replace('<origin xyz="0 0 0.1" rpy="0 0 0"/>', bad, 1))
    with pytest.raises(RobotFileError, match=pattern):
        load_urdf(path)
