"""Pose sets from the textbook observation strategies S1–S4 (Mooring–Roth–Driels §4.6, digest §5.2).

All four draw joint readings within the joint limits, optionally shrunk by a
``margin`` (fraction of each range kept free at both ends):

* **S1** — all joints stepped *together* along one curve: pose i has every
  joint at the same fraction ``s_i`` of its range, ``s_i = (i + ½)/N``. A
  single space curve — the textbook's worst strategy (ranked last).
* **S2** — one joint at a time: the poses are split into n blocks; in block j
  joint j sweeps its range evenly while every other joint stays at its home
  value (mid-range, or ``home``).
* **S3** — one joint held while the others move, the complement of S2: in
  block j joint j is held at its home value (mid-range, or ``home``) while
  every *other* joint steps together across its range, pose i of the block
  at fraction ``(i + ½)/m_j`` of each range (S1's curve with joint j held).
* **S4** — every joint an independent uniform draw (the best in Table 4.6).

The textbook ranking for identification accuracy is S4 > S3 > S2 ≫ S1.

S1–S3 are deterministic (no ``rng`` use); only S4 is random. The digest only
says "S3 holds one joint while the others move". We read S1/S2/S3 as one
family of stepping strategies (Driels & Pathre 1990), S3 being S2's
complement, for two reasons: (i) the book's κ for S3 *grows* with m (364,
396, 420, 434 at m = 36…360) like the deterministic S1, whereas a random
strategy's κ falls with m (S4: 539 → 189); (ii) an earlier random reading
(held joint drawn once per block, the other joints independent uniform draws)
was statistically indistinguishable from S4 (δrms angle 0.000581° vs
0.000590° at m = 36, 150 repetitions) and so could not reproduce the book's
separation S4 > S3.
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
    rng : seed or Generator (used by S4 only; S1–S3 are deterministic).
    margin : fraction of every joint range excluded at each end (0 ≤ margin < 0.5).
    home : (n,) home readings for S2 (the resting joints) and S3 (the held joint);
        default mid-range.
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
    h = (lo + hi) / 2 if home is None else np.asarray(home, float)
    if h.shape != (n,) or np.any(h < lo) or np.any(h > hi):
        raise ValueError(f"home must be {n} readings within the (margin-shrunk) limits")
    out = np.tile(h, (N, 1))
    start = 0
    for j, m in enumerate(block_sizes(N, n)):
        if m:
            frac = (np.arange(m) + 0.5) / m
            if s == "S2":  # joint j sweeps, the others rest at home
                out[start:start + m, j] = lo[j] + frac * (hi[j] - lo[j])
            else:  # S3: joint j rests at home, the others sweep together
                others = np.arange(n) != j
                out[start:start + m, others] = lo[others] + frac[:, None] * (hi[others] - lo[others])
        start += m
    return out
