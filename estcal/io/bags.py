"""ROS bags to a calibration dataset (``estcal import-bag``), read with the ``rosbags`` library.

A static-posture campaign records the robot's joint states and the instrument's measurement
(a pose, or points) continuously while the robot stops at each posture. This module turns that
into one dataset row per stop, as the published TIAGo files were made:

1. **plateaus** — from the joint stream alone: a sample is static when every joint's range over a
   sliding window of ``window_s`` is below ``tol`` (rad, or m for a prismatic joint); runs of
   static samples lasting at least ``min_duration_s`` are the plateaus, each shrunk by
   ``margin_s`` at both ends (the arm settles, the instrument's filter lags);
2. **clock offset** — the measurement stream may be stamped by another clock (a motion-capture
   PC): its own static intervals (position range over the window below ``tol_m``) are matched to
   the joint plateaus by the lag that maximises their overlap (cross-correlation of the two
   static indicators on a common grid, ``grid_s``); ``offset_s`` can also be given;
3. **averages** — joints averaged over each plateau, the measurement over the same interval in
   its own clock: positions by the mean, orientations by the normalised mean of sign-aligned
   quaternions (the chordal L2 mean, exact to O(spread²)).

Each row carries its window and spread like the TIAGo files: ``t_start_robot``, ``t_end_robot``
(joint clock, s), ``marker_std_mm`` (largest per-coordinate std of the measured positions over the
window) and ``joint_std_mrad`` (largest joint std). ROS 1 and ROS 2 bags are read alike
(``rosbags.highlevel.AnyReader``); no ROS installation is needed.

Messages: joints ``sensor_msgs/JointState``; ``--pose`` ``geometry_msgs/PoseStamped``,
``PoseWithCovarianceStamped``, ``TransformStamped`` (or unstamped ``Pose``/``Transform``,
timed by the bag); ``--point`` ``geometry_msgs/PointStamped`` (or ``Point``), one topic per point.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.errors import InputError

__all__ = ["BagError", "BagImport", "import_bag", "static_runs", "estimate_offset"]


class BagError(InputError):
    """A bag that cannot be imported; the message names the bag and topic."""


@dataclass
class BagImport:
    """Rows of :func:`import_bag`: ``columns`` {name: (rows,) array} in file order, and what was found."""

    columns: dict
    plateaus: list
    offset_s: dict
    skipped: list = field(default_factory=list)
    joint_names: list = field(default_factory=list)

    @property
    def n(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def write_csv(self, path) -> Path:
        from estcal.base.atomic import atomic_write

        names = list(self.columns)
        M = np.column_stack([np.asarray(self.columns[c], float) for c in names]) if names else np.zeros((0, 0))
        with atomic_write(Path(path)) as fh:
            np.savetxt(fh, M, delimiter=",", header=",".join(names), comments="", fmt="%.17g")
        return Path(path)


def _stamp(msg, log_ns):
    h = getattr(msg, "header", None)
    if h is not None:
        s = h.stamp
        t = float(getattr(s, "sec", 0)) + 1e-9 * float(getattr(s, "nanosec", getattr(s, "nsec", 0)))
        if t > 0:
            return t
    return 1e-9 * log_ns


def _read(bag, topic, kind):
    """(times (n,), values) of ``topic``: joints → (names, (n, J)); pose → (n, 7) p + q(wxyz);
    point → (n, 3)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    paths = [Path(bag)]
    if not paths[0].exists():
        raise BagError(f"{bag}: bag not found")
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # rosbags raises its own reader errors for non-bags  # noqa: BLE001
        raise BagError(f"{bag}: not a readable ROS 1 or ROS 2 bag ({' '.join(str(exc).split())})") from None
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            have = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
            raise BagError(f"{bag}: no topic {topic!r}; the bag has {', '.join(have)}")
        ts, vals, names = [], [], None
        for conn, log_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            ts.append(_stamp(msg, log_ns))
            if kind == "joints":
                if not hasattr(msg, "position") or not hasattr(msg, "name"):
                    raise BagError(f"{bag}: topic {topic!r} is {conn.msgtype}, not sensor_msgs/JointState")
                if names is None:
                    names = list(msg.name)
                idx = {n: i for i, n in enumerate(msg.name)}
                if any(n not in idx for n in names):
                    raise BagError(f"{bag}: topic {topic!r}: a message at {ts[-1]:.3f} s lacks joints "
                                   f"{[n for n in names if n not in idx]}")
                vals.append(np.asarray(msg.position, float)[[idx[n] for n in names]])
            else:
                vals.append(_geometry(msg, kind, bag, topic, conn.msgtype))
    finally:
        reader.close()
    t = np.asarray(ts, float)
    order = np.argsort(t, kind="stable")
    V = np.asarray(vals, float)[order]
    return t[order], (names, V) if kind == "joints" else V


def _geometry(msg, kind, bag, topic, msgtype):
    obj = msg
    for attr in ("pose", "pose", "transform"):  # PoseWithCovarianceStamped has pose.pose
        if hasattr(obj, attr) and not hasattr(obj, "position") and not hasattr(obj, "translation"):
            obj = getattr(obj, attr)
    if kind == "point":
        p = getattr(msg, "point", None) or getattr(obj, "position", None) or getattr(obj, "translation", None) or obj
        if not all(hasattr(p, c) for c in "xyz"):
            raise BagError(f"{bag}: topic {topic!r} is {msgtype}, not a point (geometry_msgs/PointStamped)")
        return [p.x, p.y, p.z]
    pos = getattr(obj, "position", None) or getattr(obj, "translation", None)
    rot = getattr(obj, "orientation", None) or getattr(obj, "rotation", None)
    if pos is None or rot is None:
        raise BagError(f"{bag}: topic {topic!r} is {msgtype}, not a pose (geometry_msgs/PoseStamped, "
                       f"TransformStamped)")
    return [pos.x, pos.y, pos.z, rot.w, rot.x, rot.y, rot.z]


def static_runs(t, X, tol, window_s: float, min_duration_s: float):
    """Intervals ``[(t0, t1)]`` where every column of ``X`` (n, m) stays within ``tol`` (scalar or
    (m,)) over a sliding window of ``window_s`` and that last at least ``min_duration_s``."""
    t = np.asarray(t, float)
    X = np.asarray(X, float).reshape(len(t), -1)
    n = len(t)
    if n < 3:
        return []
    lo = np.searchsorted(t, t - window_s / 2, "left")
    hi = np.searchsorted(t, t + window_s / 2, "right")
    width = int(np.max(hi - lo))
    # range of each column over [lo_i, hi_i): padded sliding windows of the widest span
    pad = np.concatenate([X, np.repeat(X[-1:], width, axis=0)])
    idx = lo[:, None] + np.arange(width)[None, :]
    valid = idx < hi[:, None]
    W = pad[np.minimum(idx, len(pad) - 1)]  # (n, width, m)
    big = np.where(valid[..., None], W, np.nan)
    rng = np.nanmax(big, axis=1) - np.nanmin(big, axis=1)
    static = np.all(rng <= np.asarray(tol, float), axis=1)
    runs, start = [], None
    for i, s in enumerate(np.r_[static, False]):
        if s and start is None:
            start = i
        elif not s and start is not None:
            if t[i - 1] - t[start] >= min_duration_s:
                runs.append((float(t[start]), float(t[i - 1])))
            start = None
    return runs


def _indicator(runs, grid):
    ind = np.zeros(grid.size)
    for a, b in runs:
        ind[(grid >= a) & (grid <= b)] = 1.0
    return ind


def estimate_offset(joint_runs, meas_runs, grid_s: float = 0.01) -> float:
    """Clock offset ``o`` (s) such that measurement time − o is joint time: the lag maximising the
    overlap of the two static indicators (zero outside the recording, so a lag by one plateau
    spacing overlaps one plateau fewer than the true lag)."""
    if not joint_runs or not meas_runs:
        raise BagError("no static interval in one of the streams: cannot match the clocks (give --offset)")
    j0 = min(r[0] for r in joint_runs)
    m0 = min(r[0] for r in meas_runs)
    # work relative to each stream's first plateau: the clocks may be years apart
    jr = [(a - j0, b - j0) for a, b in joint_runs]
    mr = [(a - m0, b - m0) for a, b in meas_runs]
    span = max(max(b for _, b in jr), max(b for _, b in mr)) + grid_s
    grid = np.arange(-span, 2 * span, grid_s)
    J = _indicator(jr, grid)
    M = _indicator(mr, grid)
    c = np.correlate(M, J, mode="full")  # c[k] = Σ M[i + k - (n-1)] J[i]
    lag = (int(np.argmax(c)) - (grid.size - 1)) * grid_s
    return float(m0 - j0 + lag)


def _mean_quat(q):
    q = np.asarray(q, float)
    q = q * np.where(q @ q[0] < 0, -1.0, 1.0)[:, None]
    m = q.mean(axis=0)
    return m / np.linalg.norm(m)


def import_bag(bag, joints_topic: str, pose_topic: str | None = None, point_topics=(), *, tol: float = 1e-3,
               tol_m: float = 1e-3, window_s: float = 0.5, min_duration_s: float = 1.0, margin_s: float = 0.2,
               offset_s: float | None = None) -> BagImport:
    """One dataset row per static plateau of ``bag`` (module docstring).

    Parameters
    ----------
    bag : ROS 1 ``.bag`` file or ROS 2 bag folder.
    joints_topic : ``sensor_msgs/JointState`` topic.
    pose_topic : pose topic (columns x,y,z,qw,qx,qy,qz), or
    point_topics : point topics (columns x1,y1,z1,… in the given order; ``x,y,z`` for one).
    tol, tol_m : static joint range (rad; m for prismatic — the bag does not say, so one value is used
        for both unless ``tol_m`` differs) and static measurement range (m) over ``window_s``.
    min_duration_s, margin_s : shortest plateau kept; time dropped at each end of a plateau.
    offset_s : measurement clock − joint clock (s); default: estimated per topic.
    """
    if (pose_topic is None) == (not point_topics):
        raise BagError("give either a pose topic (--pose) or one or more point topics (--point)")
    tq, (names, Q) = _read(bag, joints_topic, "joints")
    runs = static_runs(tq, Q, tol, window_s, min_duration_s)
    if not runs:
        raise BagError(f"{bag}: topic {joints_topic!r}: no static plateau of at least {min_duration_s:g} s (joint "
                       f"range ≤ {tol:g} over {window_s:g} s) — lower --min-duration or raise --tol")
    topics = [(pose_topic, "pose")] if pose_topic is not None else [(p, "point") for p in point_topics]
    streams = {}
    offsets = {}
    for topic, kind in topics:
        tm, V = _read(bag, topic, kind)
        if offset_s is None:
            mruns = static_runs(tm, V[:, :3], tol_m, window_s, min_duration_s * 0.5)
            offsets[topic] = estimate_offset(runs, mruns)
        else:
            offsets[topic] = float(offset_s)
        streams[topic] = (tm - offsets[topic], V, kind)
    cols: dict[str, list] = {n: [] for n in names}
    k = len(topics)
    if pose_topic is not None:
        meas_names = ["x", "y", "z", "qw", "qx", "qy", "qz"]
    else:
        meas_names = ["x", "y", "z"] if k == 1 else [f"{c}{i + 1}" for i in range(k) for c in "xyz"]
    for c in meas_names + ["t_start_robot", "t_end_robot", "marker_std_mm", "joint_std_mrad"]:
        cols[c] = []
    plateaus, skipped = [], []
    for a, b in runs:
        a2, b2 = a + margin_s, b - margin_s
        if b2 <= a2:
            skipped.append((a, b, "shorter than the two margins"))
            continue
        sel = (tq >= a2) & (tq <= b2)
        meas, stds = [], []
        for topic, kind in topics:
            tm, V, _ = streams[topic]
            m = (tm >= a2) & (tm <= b2)
            if not m.any():
                meas = None
                break
            P = V[m, :3]
            stds.append(P.std(axis=0).max() if m.sum() > 1 else 0.0)
            meas.append(np.r_[P.mean(axis=0), _mean_quat(V[m, 3:])] if kind == "pose" else P.mean(axis=0))
        if meas is None or not sel.any():
            skipped.append((a, b, "no measurement in the window"))
            continue
        qm = Q[sel].mean(axis=0)
        for n, v in zip(names, qm):
            cols[n].append(v)
        for c, v in zip(meas_names, np.concatenate(meas)):
            cols[c].append(v)
        cols["t_start_robot"].append(a2)
        cols["t_end_robot"].append(b2)
        cols["marker_std_mm"].append(1e3 * max(stds))
        cols["joint_std_mrad"].append(1e3 * float(Q[sel].std(axis=0).max()) if sel.sum() > 1 else 0.0)
        plateaus.append((a2, b2, int(sel.sum())))
    return BagImport({c: np.asarray(v, float) for c, v in cols.items()}, plateaus, offsets, skipped, list(names))
