"""Pose sets from the textbook observation strategies S1–S4 (Mooring–Roth–Driels §4.6, digest §5.2).

All four draw joint readings within the joint limits, optionally shrunk by a
``margin`` (fraction of each range kept free at both ends):

* **S1** — all joints stepped *together* along one curve: pose i has every
  joint at the same fraction ``s_i`` of its range, ``s_i = (i + ½)/N``. A
  single space curve — the textbook's worst strategy (ranked last).
* **S2** — one joint at a time: the poses are split into n blocks; in block j
  joint j sweeps its range evenly while every other joint stays at its home
  value (mid-range, or ``home``).
* **S3** — one joint held while the others move: in block j joint j is held
  at one value (drawn uniformly once per block) and the other joints are
  independent uniform draws.
* **S4** — every joint an independent uniform draw (the best in Table 4.6).

The textbook ranking for identification accuracy is S4 > S3 > S2 ≫ S1.
"""
from __future__ import annotations

import numpy as np

__all__ = ["STRATEGIES", "generate_poses", "block_sizes"]

STRATEGIES = ("S1", "S2", "S3", "S4")


def block_sizes(N: int, n: int) -> np.ndarray:
    """Split N poses into n nearly equal consecutive blocks (the first N mod n get one more)."""
    sizes = np.full(n, N // n)
    sizes[: N % n] += 1
    return sizes


def generate_poses(robot, n_poses: int, strategy: str = "S4", rng=None, margin: float = 0.0,
                   home=None) -> np.ndarray:
    """Joint readings (N, n) for ``strategy`` within ``robot.limits``.

    Parameters
    ----------
    robot : SerialRobot (only ``limits`` and ``joint_names`` are used).
    n_poses : number of poses N.
    strategy : ``"S1"``, ``"S2"``, ``"S3"`` or ``"S4"`` (see module docstring).
    rng : seed or Generator.
    margin : fraction of every joint range excluded at each end (0 ≤ margin < 0.5).
    home : (n,) home readings for S2 (default mid-range).
    """
    s = str(strategy).upper()
    if s not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; choose one of {', '.join(STRATEGIES)} "
                         f"(S1 together, S2 one at a time, S3 one held, S4 uniform random)")
    if not 0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin}")
    N = int(n_poses)
    if N < 1:
        raise ValueError(f"n_poses must be >= 1, got {n_poses}")
    rng = np.random.default_rng(rng)
    lim = np.asarray(robot.limits, float)
    span = lim[:, 1] - lim[:, 0]
    lo, hi = lim[:, 0] + margin * span, lim[:, 1] - margin * span
    n = lo.size
    if s == "S4":
        return rng.uniform(lo, hi, size=(N, n))
    if s == "S1":
        frac = (np.arange(N) + 0.5) / N
        return lo + frac[:, None] * (hi - lo)
    if s == "S2":
        h = (lo + hi) / 2 if home is None else np.asarray(home, float)
        if h.shape != (n,) or np.any(h < lo) or np.any(h > hi):
            raise ValueError(f"home must be {n} readings within the (margin-shrunk) limits")
        out = np.tile(h, (N, 1))
        start = 0
        for j, m in enumerate(block_sizes(N, n)):
            if m:
                out[start:start + m, j] = lo[j] + (np.arange(m) + 0.5) / m * (hi[j] - lo[j])
            start += m
        return out
    # S3
    out = rng.uniform(lo, hi, size=(N, n))
    start = 0
    for j, m in enumerate(block_sizes(N, n)):
        out[start:start + m, j] = rng.uniform(lo[j], hi[j])
        start += m
    return out
