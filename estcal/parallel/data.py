"""Gough-platform measurements: platform poses and leg readings, their files, synthetic data.

A measurement is a platform pose ``T_base_platform`` (measured in the base frame) and the six
leg-sensor readings ``ρ`` of that pose (SI: m, rad). Files (:func:`load_gough_data`):

* CSV: a header row with ``x,y,z`` (m), the orientation as ``psi,theta,phi`` (ZYX Euler,
  rad, ``R = Rz(ψ) Ry(θ) Rx(φ)``) or ``qw,qx,qy,qz`` (scalar-first, as the serial datasets),
  and the readings ``rho1..rho6`` (or ``leg1..6``, ``q1..6``) in m;
* NPZ: arrays ``T`` (N, 4, 4) and ``rho`` (N, 6), optional scalars ``sigma_rho``, ``sigma_p``,
  ``sigma_r``;
* JSON: the output of :meth:`GoughData.to_dict`.

:meth:`GoughData.to_csv_text` gives the CSV form; writing it to disk is the caller's (the Gough
workflow writes atomically).
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estcal.base.errors import InputError
from estcal.base.textinput import check_input_file, read_csv, read_json
from estcal.kinematics.transforms import quat_to_matrix

from ._rot import euler_zyx_to_matrix, make_T, matrix_to_euler_zyx, so3_exp
from .daney import generate_random_poses
from .gough import N_LEGS, GoughPlatform, split_pose

__all__ = ["GoughData", "load_gough_data", "simulate_gough_data", "CSV_HEADER"]

#: header of the CSV form (m, ZYX Euler rad, m)
CSV_HEADER = "x,y,z,psi,theta,phi," + ",".join(f"rho{k}" for k in range(1, N_LEGS + 1))


@dataclass
class GoughData:
    """Measured platform poses (base frame) and leg readings.

    Attributes
    ----------
    T : (N, 4, 4) measured ``T_base_platform``.
    rho : (N, 6) leg-sensor readings [m].
    sigma_rho, sigma_p, sigma_r : noise standard deviations (m, m, rad) when known, else None.
    source : where the data came from (file path, ``"simulated"``), used in messages.
    """

    T: np.ndarray
    rho: np.ndarray
    sigma_rho: float | None = None
    sigma_p: float | None = None
    sigma_r: float | None = None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        self.T = np.asarray(self.T, float).reshape(-1, 4, 4)
        self.rho = np.asarray(self.rho, float).reshape(-1, N_LEGS)
        if len(self.T) != len(self.rho):
            raise InputError(f"{self.source}: {len(self.T)} poses but {len(self.rho)} rows of leg readings")
        bad = ~np.isfinite(self.T).all(axis=(1, 2)) | ~np.isfinite(self.rho).all(axis=1)
        if bad.any():
            raise InputError(f"{self.source}: non-finite values in rows {np.flatnonzero(bad)[:10].tolist()} "
                             f"(0-based data rows); remove or repair them")

    def __len__(self) -> int:
        return len(self.T)

    @property
    def n(self) -> int:
        """Number of poses (as ``Dataset.n``)."""
        return len(self.T)

    @property
    def path(self) -> str | None:
        """The file the data were read from (None for data made in memory)."""
        return None if self.source in ("<memory>", "simulated") else self.source

    def subset(self, idx) -> "GoughData":
        return GoughData(self.T[idx], self.rho[idx], self.sigma_rho, self.sigma_p, self.sigma_r, self.source)

    def to_dict(self) -> dict:
        """JSON form: position [m], ZYX Euler angles [rad], readings [m]."""
        P, R = split_pose(self.T)
        return {"n_poses": len(self), "position": P.tolist(), "euler_zyx": matrix_to_euler_zyx(R).tolist(),
                "rho": self.rho.tolist(), "sigma_rho": self.sigma_rho, "sigma_p": self.sigma_p,
                "sigma_r": self.sigma_r}

    def to_csv_text(self) -> str:
        """CSV with header :data:`CSV_HEADER` (m, ZYX Euler rad, m), 12 significant digits."""
        P, R = split_pose(self.T)
        buf = io.StringIO()
        np.savetxt(buf, np.c_[P, matrix_to_euler_zyx(R), self.rho], delimiter=",", header=CSV_HEADER,
                   comments="", fmt="%.12g")
        return buf.getvalue()


def _load_npz(p: Path) -> GoughData:
    try:
        z = np.load(p)
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: not a readable NPZ file ({exc})") from None
    for key in ("T", "rho"):
        if key not in z.files:
            raise InputError(f"{p}: NPZ needs arrays 'T' and 'rho' (found {z.files})")
    kw = {k: float(z[k]) for k in ("sigma_rho", "sigma_p", "sigma_r") if k in z.files}
    return GoughData(z["T"], z["rho"], source=str(p), **kw)


def _load_json(p: Path) -> GoughData:
    d = read_json(p, "Gough measurement")
    missing = [k for k in ("position", "euler_zyx", "rho") if not isinstance(d, dict) or k not in d]
    if missing:
        raise InputError(f"{p}: JSON Gough data needs keys position, euler_zyx, rho (missing {missing})")
    T = make_T(np.asarray(d["position"], float), euler_zyx_to_matrix(np.asarray(d["euler_zyx"], float)))
    return GoughData(T, d["rho"], d.get("sigma_rho"), d.get("sigma_p"), d.get("sigma_r"), str(p))


def _numeric(t) -> np.ndarray:
    """The CSV records as floats; a short row or a non-number is named by its line and column."""
    if t.numeric is not None:
        return np.asarray(t.numeric, float)
    for rec, line in zip(t.rows, t.lines):
        if len(rec) != len(t.header):
            raise InputError(f"{t.where}, line {line}: {len(rec)} fields but the header has {len(t.header)} "
                             f"({', '.join(t.header)})")
        for name, v in zip(t.header, rec):
            try:
                float(v)
            except ValueError:
                raise InputError(f"{t.where}, line {line}, column {name!r}: not a number ({v.strip()!r})") from None
    return np.array(t.rows, float).reshape(len(t.rows), len(t.header))


def _load_csv(p: Path) -> GoughData:
    t = read_csv(p, "Gough measurement")
    cols = t.header
    arr = _numeric(t)
    ix = {c: i for i, c in enumerate(cols)}

    def col(names):
        missing = [n for n in names if n not in ix]
        if missing:
            raise InputError(f"{p}: missing column(s) {missing}; header is {cols}")
        return arr[:, [ix[n] for n in names]]

    P = col(["x", "y", "z"])
    if "psi" in ix:
        R = euler_zyx_to_matrix(col(["psi", "theta", "phi"]))
    elif "qw" in ix:
        R = quat_to_matrix(col(["qw", "qx", "qy", "qz"]))
    else:
        raise InputError(f"{p}: orientation columns psi,theta,phi or qw,qx,qy,qz required; header is {cols}")
    for prefix in ("rho", "leg", "q"):
        if all(f"{prefix}{k}" in ix for k in range(1, N_LEGS + 1)):
            rho = col([f"{prefix}{k}" for k in range(1, N_LEGS + 1)])
            break
    else:
        raise InputError(f"{p}: leg readings needed as columns rho1..rho6 (or leg1..leg6, q1..q6) in m; "
                         f"header is {cols}")
    return GoughData(make_T(P, R), rho, source=str(p))


def load_gough_data(path: str | Path) -> GoughData:
    """Read Gough measurements from CSV, NPZ or JSON (module docstring)."""
    p = check_input_file(path, "Gough measurement")
    suf = p.suffix.lower()
    if suf == ".npz":
        return _load_npz(p)
    if suf == ".json":
        return _load_json(p)
    return _load_csv(p)


def simulate_gough_data(
    robot: GoughPlatform,
    n_poses: int,
    rng: np.random.Generator | int = 0,
    sigma_rho: float = 0.0,
    sigma_p: float = 0.0,
    sigma_r: float = 0.0,
    T: np.ndarray | None = None,
) -> GoughData:
    """Synthetic measurements of ``robot`` (the *true* robot): random workspace poses (or ``T``),
    exact readings, Gaussian noise on the readings (σ_ρ), on each position component (σ_p) and
    as a base-frame rotation vector (σ_r). The noise levels are stored as known (None when 0)."""
    rng = np.random.default_rng(rng)
    T = generate_random_poses(robot, n_poses, rng) if T is None else np.asarray(T, float).reshape(-1, 4, 4)
    rho = robot.leg_lengths(T) + rng.normal(0, sigma_rho, (len(T), N_LEGS))
    P, R = split_pose(T)
    Tm = make_T(P + rng.normal(0, sigma_p, P.shape), so3_exp(rng.normal(0, sigma_r, P.shape)) @ R)
    return GoughData(Tm, rho, sigma_rho or None, sigma_p or None, sigma_r or None, "simulated")
