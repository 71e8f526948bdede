"""estcal import-bag: ROS 1 and ROS 2 bags written here with rosbags itself (estcal.io.bags)."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")

from estcal.io.bags import BagError, import_bag  # noqa: E402

NAMES = ["j1", "j2", "j3"]
PLATEAUS = np.array([[0.1, -0.5, 0.3], [0.6, -0.2, 0.9], [-0.4, 0.3, 0.2], [0.2, 0.8, -0.6]])
POSES = np.array([[0.5, 0.1, 0.3], [0.4, 0.3, 0.5], [0.2, -0.2, 0.6], [0.6, 0.0, 0.2]])
HOLD, MOVE = 3.0, 2.0
OFFSET = 1234.567  # the measurement PC's clock minus the robot's
T0 = 1_700_000_000.0


def _profile(t, values):
    """Piecewise: hold each value HOLD s, move linearly MOVE s to the next."""
    period = HOLD + MOVE
    i = np.clip((t // period).astype(int), 0, len(values) - 1)
    f = np.clip((t - i * period - HOLD) / MOVE, 0, 1)[:, None]
    nxt = values[np.minimum(i + 1, len(values) - 1)]
    return values[i] * (1 - f) + nxt * f


def _quat(a):
    """Rotation about z by angle a: (w, x, y, z)."""
    return np.c_[np.cos(a / 2), 0 * a, 0 * a, np.sin(a / 2)]


def _write(path, version, pose_kind="pose"):
    from rosbags.typesys import Stores, get_typestore

    ros1 = version == 1
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    ns = "msg/"  # rosbags names ROS 1 types the ROS 2 way too
    JointState, Header = T[f"sensor_msgs/{ns}JointState"], T[f"std_msgs/{ns}Header"]
    Time = T["builtin_interfaces/msg/Time"]
    PoseStamped, Pose = T[f"geometry_msgs/{ns}PoseStamped"], T[f"geometry_msgs/{ns}Pose"]
    Point, Quaternion = T[f"geometry_msgs/{ns}Point"], T[f"geometry_msgs/{ns}Quaternion"]
    rng = np.random.default_rng(0)
    dur = len(PLATEAUS) * (HOLD + MOVE) - MOVE
    tj = np.arange(0, dur, 1 / 100.0)  # joints at 100 Hz
    tp = np.arange(0.013, dur, 1 / 120.0)  # poses at 120 Hz, another phase
    Q = _profile(tj, PLATEAUS) + rng.normal(0, 1e-5, (tj.size, 3))
    P = _profile(tp, POSES) + rng.normal(0, 1e-4, (tp.size, 3))
    ang = _profile(tp, np.array([[0.1], [0.5], [-0.3], [1.0]]))[:, 0] + rng.normal(0, 1e-4, tp.size)
    q = _quat(ang)

    def stamp(t, frame=""):
        sec = int(np.floor(t))
        kw = dict(sec=sec, nanosec=int(round((t - sec) * 1e9)))
        h = dict(stamp=Time(**kw), frame_id=frame)
        if ros1:
            h["seq"] = 0
        return Header(**h)

    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        ser = ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=9)
        ser = ts.serialize_cdr
    with writer:
        cj = writer.add_connection("/joint_states", JointState.__msgtype__, typestore=ts)
        cp = writer.add_connection("/mocap/pose", PoseStamped.__msgtype__, typestore=ts)
        events = [(T0 + t, 0, i) for i, t in enumerate(tj)] + [(T0 + t + 0.004, 1, i) for i, t in enumerate(tp)]
        for tlog, which, i in sorted(events):
            if which == 0:
                msg = JointState(header=stamp(T0 + tj[i]), name=NAMES, position=Q[i], velocity=np.zeros(0),
                                 effort=np.zeros(0))
                writer.write(cj, int(tlog * 1e9), ser(msg, JointState.__msgtype__))
            else:
                pose = Pose(position=Point(x=P[i, 0], y=P[i, 1], z=P[i, 2]),
                            orientation=Quaternion(w=q[i, 0], x=q[i, 1], y=q[i, 2], z=q[i, 3]))
                msg = PoseStamped(header=stamp(T0 + OFFSET + tp[i], "mocap"), pose=pose)
                writer.write(cp, int(tlog * 1e9), ser(msg, PoseStamped.__msgtype__))
    return path


@pytest.mark.parametrize("version", [1, 2])
def test_four_plateaus_become_four_rows(tmp_path, version):
    bag = _write(tmp_path / ("b.bag" if version == 1 else "b2"), version)
    out = import_bag(bag, "/joint_states", "/mocap/pose")
    assert out.n == 4
    assert abs(out.offset_s["/mocap/pose"] - OFFSET) < 0.05
    Q = np.c_[tuple(out.columns[n] for n in NAMES)]
    assert np.abs(Q - PLATEAUS).max() < 2e-5  # noise 1e-5 rad, averaged over ~260 samples
    P = np.c_[out.columns["x"], out.columns["y"], out.columns["z"]]
    assert np.abs(P - POSES).max() < 5e-5  # noise 0.1 mm, averaged over ~310 samples
    ang = 2 * np.arctan2(out.columns["qz"], out.columns["qw"])
    assert np.abs(ang - [0.1, 0.5, -0.3, 1.0]).max() < 5e-5
    assert np.all(out.columns["marker_std_mm"] < 0.2) and np.all(out.columns["marker_std_mm"] > 0.05)
    t0, t1 = out.columns["t_start_robot"], out.columns["t_end_robot"]
    assert np.all(t1 - t0 > 2.0) and np.all(t1 - t0 < HOLD)
    # each window lies inside its hold (robot clock): [i·5 s, i·5 s + 3 s] shrunk by the 0.25 s half
    # window of the static test and the 0.2 s margin (the recording starts and ends holding)
    starts = np.arange(4) * (HOLD + MOVE)
    assert np.all(t0[1:] - T0 >= starts[1:] + 0.44) and np.all(t0[1:] - T0 <= starts[1:] + 0.5)
    ends = starts[:3] + HOLD
    assert np.all(t1[:3] - T0 <= ends - 0.44) and np.all(t1[:3] - T0 >= ends - 0.5)
    # written as a dataset that estcal loads (t from the window, like the TIAGo files)
    from estcal.io.dataset import load_dataset

    out.write_csv(tmp_path / "rows.csv")
    ds = load_dataset(tmp_path / "rows.csv", joint_names=NAMES)
    assert ds.kind == "pose" and ds.n == 4 and "t" in ds.context


def test_missing_topic_is_named(tmp_path):
    bag = _write(tmp_path / "b.bag", 1)
    with pytest.raises(BagError, match=r"no topic '/tf'; the bag has /joint_states \(sensor_msgs/msg/JointState\)"):
        import_bag(bag, "/joint_states", "/tf")
