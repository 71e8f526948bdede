"""Built-in robots (all in SI units: metres, radians).

===================  ==========================================================
function             source
===================  ==========================================================
:func:`stanford`     GECARO Table 1 (Khalil–Kleinfinger, frames 0…7, verbatim:
                     α1 = 0.1 rad, α7 = 1.3 rad as printed)
:func:`puma560`      Mooring–Roth–Driels Table 6.1 (inches/degrees → SI):
                     DH / Hayati / RPY-tool model of the Ch. 6 case study
:func:`puma560_fu`   Table 5.3 (Fu et al. DH, mm → m) with α4 = −90°, α5 = +90°
                     (the printed 0, 0 is a known misprint)
:func:`robot_5r1p`   Table 4.1, the 5R1P simulation robot (inches → m)
:func:`planar2`      Klimchik's two-link planar arm, l1 = 1 m, l2 = 0.8 m
:func:`tiago`        TIAGo URDF from ``../shared/data/tiago`` (not copied here)
===================  ==========================================================

Joint limits are not part of the printed tables except where noted; the
values below are documented choices (typical ranges for the arm class).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .builder import build_robot
from .chain import SerialRobot
from .transforms import matrix_to_rpy, rot_x, rot_z

__all__ = ["stanford", "puma560", "puma560_fu", "robot_5r1p", "planar2", "tiago", "BUILTIN",
           "get_builtin", "shared_dir", "shared_candidates", "INCH"]

INCH = 0.0254
D = np.pi / 180.0


def stanford() -> SerialRobot:
    """Stanford manipulator (RRP3R) as printed in GECARO Table 1."""
    h = np.pi / 2
    frames = [
        {"name": "frame0", "type": "fixed", "theta": h, "r": 0.5},
        {"name": "j1", "alpha": 0.1, "limits": [-np.pi, np.pi]},
        {"name": "j2", "alpha": -h, "r": 0.2, "limits": [-h, h]},
        {"name": "j3", "type": "prismatic", "alpha": h, "limits": [0.3, 1.0]},
        {"name": "j4", "alpha": 0.0, "limits": [-np.pi, np.pi]},
        {"name": "j5", "alpha": -h, "limits": [-h, h]},
        {"name": "j6", "alpha": h, "limits": [-np.pi, np.pi]},
        {"name": "frame7", "type": "fixed", "alpha": 1.3, "d": 0.2, "theta": h, "r": 0.1},
    ]
    return build_robot("stanford", frames, convention="khalil", meta={"source": "GECARO Table 1"})


def _dh_transform(theta, d, a, alpha):
    T = np.eye(4)
    T[:3, :3] = rot_z(theta) @ rot_x(alpha)
    T[:3, 3] = [a * np.cos(theta), a * np.sin(theta), d]
    return T


def puma560() -> SerialRobot:
    """PUMA 560 of the textbook's Chapter 6 case study (Table 6.1), converted to SI.

    B→0 (type 1, DH with constant θ = 0): r = 32.878 in, l = −15.591 in, α = −90°.
    0→1 … 4→5 carry joints 1–5 (1→2 is Hayati's type 2 for the parallel pair),
    5→6 (type 3) carries joint 6 in its θz = 90° and dz = 2.213 in. The base
    transform is expressed as the 6-parameter base frame; the tool frame is the
    identity (the tool origin lies on axis 6, hence rank 25 with position only).
    """
    Tb = _dh_transform(0.0, 32.878 * INCH, -15.591 * INCH, -90 * D)
    base = {"xyz": Tb[:3, 3].tolist(), "rpy": matrix_to_rpy(Tb[:3, :3]).tolist()}
    frames = [
        {"name": "j1", "convention": "dh", "d": 14.681 * INCH, "a": 0.0, "alpha": -90 * D},
        {"name": "j2", "convention": "dh", "d": 0.0, "a": 17.000 * INCH, "alpha": 0.0},  # Hayati β = 0
        {"name": "j3", "convention": "dh", "d": 5.870 * INCH, "a": -0.800 * INCH, "alpha": 90 * D},
        {"name": "j4", "convention": "dh", "d": 17.050 * INCH, "a": 0.0, "alpha": -90 * D},
        {"name": "j5", "convention": "dh", "d": 0.0, "a": 0.0, "alpha": 90 * D},
        {"name": "j6", "convention": "dh", "theta": 90 * D, "d": 2.213 * INCH, "a": 0.0, "alpha": 0.0},
    ]
    lims = [(-160, 160), (-225, 45), (-45, 225), (-110, 170), (-100, 100), (-266, 266)]
    for f, (lo, hi) in zip(frames, lims):
        f["limits"] = [lo * D, hi * D]
    return build_robot("puma560", frames, base=base, convention="dh",
                       meta={"source": "Mooring-Roth-Driels Table 6.1 (in, deg -> m, rad)"})


def puma560_fu() -> SerialRobot:
    """PUMA 560, Fu et al. standard DH (textbook Table 5.3, mm → m, α4 = −90°, α5 = 90°)."""
    mm = 1e-3
    rows = [(0, 0, -90), (149.09, 431.8, 0), (0, -20.32, 90), (433.07, 0, -90), (0, 0, 90), (56.25, 0, 0)]
    lims = [(-160, 160), (-225, 45), (-45, 225), (-110, 170), (-100, 100), (-266, 266)]
    frames = [{"name": f"j{i + 1}", "d": d * mm, "a": a * mm, "alpha": al * D, "limits": [lo * D, hi * D]}
              for i, ((d, a, al), (lo, hi)) in enumerate(zip(rows, lims))]
    return build_robot("puma560_fu", frames, convention="dh", meta={"source": "Mooring Table 5.3"})


def robot_5r1p(tool_distance_in: float = 10.0) -> SerialRobot:
    """The 5R1P robot of the textbook's Driels–Pathre study (Table 4.1), inches → m.

    Standard DH rows (α, l, r, θ): (−90, 0, 6, θ1), (+90, 0, 12, θ2),
    prismatic (+30, 0, r3, 0), (−90, 0, 0, θ4), (+90, 0, 0, θ5), (0, l6, r6, θ6)
    with l6 = r6 = ``tool_distance_in``. Joint ranges: range "N" of Table 4.7
    (θ1 0–300°, θ2 ±120°, r3 12–48 in) and full-range wrist.
    """
    li = tool_distance_in * INCH
    frames = [
        {"name": "j1", "d": 6 * INCH, "alpha": -90 * D, "limits": [0, 300 * D]},
        {"name": "j2", "d": 12 * INCH, "alpha": 90 * D, "limits": [-120 * D, 120 * D]},
        {"name": "j3", "type": "prismatic", "alpha": 30 * D, "limits": [12 * INCH, 48 * INCH]},
        {"name": "j4", "alpha": -90 * D, "limits": [-np.pi, np.pi]},
        {"name": "j5", "alpha": 90 * D, "limits": [-np.pi, np.pi]},
        {"name": "j6", "a": li, "d": li, "alpha": 0.0, "limits": [-np.pi, np.pi]},
    ]
    return build_robot("5r1p", frames, convention="dh", meta={"source": "Mooring Table 4.1"})


def planar2(l1: float = 1.0, l2: float = 0.8) -> SerialRobot:
    """Klimchik's planar two-link arm: x = l1 cos q1 + l2 cos(q1+q2), y = l1 sin q1 + l2 sin(q1+q2)."""
    frames = [{"name": "q1", "a": l1, "limits": [-np.pi, np.pi]},
              {"name": "q2", "a": l2, "limits": [-np.pi, np.pi]}]
    return build_robot("planar2", frames, convention="dh", meta={"source": "Klimchik 2012, eq. 16"})


def shared_candidates() -> list[Path]:
    """Folders searched for the shared data, in order (see :func:`shared_dir`)."""
    import os

    env = os.environ.get("ESTCAL_SHARED")
    if env:
        return [Path(env).expanduser()]
    here = Path(__file__).resolve()
    # a source checkout keeps shared/ beside the repository; a non-editable install lives
    # in site-packages, where parents[3] is meaningless — so also look from the working folder
    cwd = Path.cwd()
    out = [here.parents[3] / "shared", cwd / "shared", cwd.parent / "shared"]
    return list(dict.fromkeys(out))


def shared_dir() -> Path:
    """The shared data folder (real measurements and reference robots, never copied into the repository).

    Resolution order: the ``ESTCAL_SHARED`` environment variable (used as given); otherwise the first of
    ``<repository>/../shared``, ``./shared`` and ``../shared`` (relative to the working folder) that
    exists. When none exists the first candidate is returned, so error messages name a definite path.
    Documented in docs/dataset.md ("Where the data live").
    """
    cands = shared_candidates()
    for c in cands:
        if c.is_dir():
            return c
    return cands[0]


def tiago(n_markers: int = 1) -> SerialRobot:
    """TIAGo arm chain from ``../shared/data/tiago/tiago_48_schunk.urdf``.

    Chain ``base_footprint`` → ``wrist_ft_tool_link`` (torso lift + 7 arm joints),
    with ``n_markers`` unknown points in the tool frame (initialised at the origin).
    Raises ``FileNotFoundError`` with a clear message when the shared data is absent.
    """
    from .urdf import robot_from_urdf

    path = shared_dir() / "data" / "tiago" / "tiago_48_schunk.urdf"
    if not path.exists():
        tried = ", ".join(str(c) for c in shared_candidates())
        raise FileNotFoundError(f"TIAGo URDF not found at {path}: the built-in 'tiago' reads the shared data "
                                f"folder (searched: {tried}); set ESTCAL_SHARED=/path/to/shared, or load a "
                                f"saved model (estcal calibrate --save-model), which carries its robot")
    return robot_from_urdf(path, root="base_footprint", tip="wrist_ft_tool_link",
                           markers=np.zeros((n_markers, 3)) if n_markers else None, name="tiago")


BUILTIN = {"stanford": stanford, "puma560": puma560, "puma560_fu": puma560_fu, "5r1p": robot_5r1p,
           "planar2": planar2, "tiago": tiago}


def get_builtin(name: str) -> SerialRobot:
    try:
        return BUILTIN[name.lower()]()
    except KeyError:
        raise ValueError(f"unknown built-in robot {name!r}; choose one of {sorted(BUILTIN)} "
                         f"or give a robot file (.yaml) or a URDF (.urdf)") from None
