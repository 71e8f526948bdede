#!/usr/bin/env python3
"""Online calibration from a stream of CSV rows — the loop to copy into a cell controller.

Each row (joint readings + the measured tool pose ``x,y,z,qw,qx,qy,qz`` or
position ``x,y,z``, SI units, first line = header, see docs/dataset.md) updates
a Kalman filter over the free parameters as soon as it arrives — filterpy's
EKF through :class:`estcal.estimate.kalman.ParameterFilter`, random-walk model
x_k = x_{k−1} + w_k, Cov(w) = Q (textbook §4.5, eqs 4.104–4.112) — and the
estimate ± σ of the shown parameters is printed. A malformed row (wrong field
count, a value that is not a finite number, a quaternion that is not unit) is
reported on stderr with its line and column and skipped (``--strict``: stop
with exit code 2). At the end: the final table, the innovation tests
(docs/probabilistic.md) and, with ``--json``, the estimate and covariance.

It is the same filter, prior and noise model as ``estcal online``, so both
give the same final estimate on the same rows (tests/test_notebooks.py
checks it).

Examples::

    python online_stream.py puma560 stream.csv --sigma-p 1e-4 --sigma-r 1e-4 --free 'theta_*,d_1,d_4,d_5,d_6'
    measurement_source | python online_stream.py my_robot.yaml - --sigma-p 5e-5 --q 1e-6 --json state.json

Exit codes: 0 done, 2 bad arguments / header / input (or a malformed row with ``--strict``).
"""
from __future__ import annotations

import argparse
import csv
import sys

import numpy as np

import estcal  # top-level API: load_robot, NoiseModel (docs/api.md); the filter pieces from their modules
from estcal.estimate.kalman import ParameterFilter, default_burn_in, process_noise
from estcal.base.atomic import atomic_write_text
from estcal.io.dataset import dataset_from_arrays
from estcal.kinematics.transforms import quat_to_matrix
from estcal.methods.base import method_for_dataset
from estcal.methods.problem import Problem

POSE = ("x", "y", "z", "qw", "qx", "qy", "qz")


class BadRow(ValueError):
    """A row that cannot be used (the message names line and column)."""


def die(msg: str) -> None:
    print(f"online_stream: error: {msg}", file=sys.stderr)
    sys.exit(2)


def parse_row(header: list, fields: list, joints: list, where: str):
    """One CSV row → a one-pose dataset (pose if the header has x..qz, else position x,y,z)."""
    if len(fields) != len(header):
        raise BadRow(f"{where}: {len(fields)} fields, the header has {len(header)}")
    col = dict(zip(header, fields))

    def num(c):
        try:
            v = float(col[c])
        except ValueError:
            raise BadRow(f"{where}, column {c!r}: {col[c]!r} is not a number") from None
        if not np.isfinite(v):
            raise BadRow(f"{where}, column {c!r}: {col[c]!r} is not finite")
        return v

    q = np.array([[num(j) for j in joints]])
    p = np.array([[num(c) for c in "xyz"]])
    if "qw" not in col:
        return dataset_from_arrays(joints, q, points=p, path=where)
    quat = np.array([num(c) for c in POSE[3:]])
    if abs(np.linalg.norm(quat) - 1) > 1e-3:
        raise BadRow(f"{where}, columns qw..qz: quaternion norm {np.linalg.norm(quat):.6f}, expected 1")
    return dataset_from_arrays(joints, q, R=quat_to_matrix(quat[None] / np.linalg.norm(quat)), p=p, path=where)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("robot", help="built-in name (puma560, …), robot file (.yaml) or URDF")
    ap.add_argument("data", nargs="?", default="-", help="CSV file, or '-' (default) for standard input")
    ap.add_argument("--sigma-p", type=float, default=1e-4, help="position noise std per coordinate, m")
    ap.add_argument("--sigma-r", type=float, default=1e-3, help="orientation noise std per axis, rad")
    ap.add_argument("--free", default=None, help="comma-separated names/patterns to estimate (default: the robot's "
                                                 "free mask)")
    ap.add_argument("--q", type=float, default=0.0, help="process-noise std per row (SI; 0 = constant parameters)")
    ap.add_argument("--q-params", default=None, help="apply --q only to these comma-separated names/patterns")
    ap.add_argument("--prior-std", type=float, default=0.1, help="prior std of every free parameter, m or rad")
    ap.add_argument("--show", default=None, help="comma-separated parameters printed on every row (default: 3)")
    ap.add_argument("--strict", action="store_true", help="stop at the first malformed row (exit 2)")
    ap.add_argument("--json", default=None, help="write the final estimate, stds and covariance to this file")
    a = ap.parse_args(argv)
    try:
        robot = estcal.load_robot(a.robot)
        if a.free:
            robot = robot.copy(robot.params.with_free([s.strip() for s in a.free.split(",") if s.strip()]))
    except (ValueError, KeyError, FileNotFoundError) as exc:
        die(str(exc))
    pv = robot.params
    names, fidx = pv.free_names, pv.free_indices
    try:
        Q = process_noise(names, {s.strip(): a.q for s in a.q_params.split(",")} if a.q_params else a.q)
        show = [names.index(s.strip()) for s in a.show.split(",")] if a.show else list(range(min(3, len(names))))
    except ValueError as exc:
        die(f"--q-params / --show: {exc} (free parameters: {', '.join(names)})")
    flt = ParameterFilter(pv.values, fidx, np.eye(len(names)) * a.prior_std ** 2, Q, names=names)
    noise = estcal.NoiseModel(a.sigma_p, a.sigma_r, known=True)
    src = "<stdin>" if a.data == "-" else a.data
    try:
        fh = sys.stdin if a.data == "-" else open(a.data, newline="")
    except OSError as exc:
        die(f"{src}: {exc.strerror}")
    head = fh.readline()
    if not head.strip():
        die(f"{src}: empty input (expected a header line with {', '.join(robot.joint_names)}, x, y, z[, qw..qz])")
    header = [h.strip() for h in next(csv.reader([head]))]
    missing = [c for c in list(robot.joint_names) + list("xyz") if c not in header]
    if missing:
        die(f"{src}, line 1: header lacks column(s) {missing}; it has {header}")
    print(f"online_stream: {robot.name}, {len(names)} free parameters, q = {a.q:g}; reading {src} (units: m, rad)",
          flush=True)
    skipped, line_no = 0, 1
    while True:  # readline, not a for loop: each row is used as soon as it arrives on a pipe
        line = fh.readline()
        if not line:
            break
        line_no += 1
        if not line.strip():
            continue
        try:
            ds = parse_row(header, [f.strip() for f in next(csv.reader([line]))], robot.joint_names,
                           f"{src}, line {line_no}")
            step = flt.step(Problem(robot, [(method_for_dataset(ds, robot), ds, noise)]))
        except BadRow as exc:
            if a.strict:
                die(str(exc))
            skipped += 1
            print(f"online_stream: skipped {exc}", file=sys.stderr, flush=True)
            continue
        x, s = flt.x, flt.std
        par = "  ".join(f"{names[i]} = {x[i]:.7g} ± {s[i]:.2g}" for i in show)
        print(f"row {flt.n_steps:5d}  NIS {step.nis:7.2f}/{step.y.size}  {par}", flush=True)
    if flt.n_steps == 0:
        die(f"{src}: no usable data row ({skipped} skipped)")
    x, s = flt.x, flt.std
    print(f"\nestimate after {flt.n_steps} rows ({skipped} skipped):")
    for i, n in enumerate(names):
        print(f"  {n:<12} {x[i]:>14.8g} ± {s[i]:.3g}   (nominal {pv.values[fidx[i]]:.8g})")
    try:
        tests = flt.monitor.tests(burn_in=default_burn_in(flt.monitor.dims, len(names)))
        print(tests)
        tests = tests.to_dict()
    except ValueError as exc:
        tests = {"error": str(exc)}
        print(f"innovation tests: {exc}")
    if a.json:
        import json

        out = {"robot": robot.name, "input": src, "n_rows": flt.n_steps, "skipped": skipped, "q": a.q,
               "parameters": {n: {"estimate": float(x[i]), "std": float(s[i]), "nominal": float(pv.values[fidx[i]])}
                              for i, n in enumerate(names)},
               "covariance": flt.P.tolist(), "innovation": tests}
        atomic_write_text(a.json, json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
