#!/usr/bin/env python3
"""Online calibration from a stream of CSV rows — the loop to copy into a cell controller.

Each row (joint readings + the measured tool pose ``x,y,z,qw,qx,qy,qz`` or
position ``x,y,z``, SI units, first line = header, see docs/dataset.md; or the
publisher's own columns and units through ``--map FILE.yaml``) updates
:class:`estcal.OnlineCalibrator` — a Kalman filter over the free parameters,
random-walk model x_k = x_{k−1} + w_k, Cov(w) = Q (textbook §4.5, eqs 4.104–4.112) —
as soon as it arrives, and the estimate ± σ of the shown parameters is printed.
Rows are read and checked by :class:`estcal.io.stream.CsvStream` (the
dataset loader's checks); a malformed row is reported on stderr with its line
and column and skipped (``--strict``: stop with exit code 2). At the end: the
final table, the innovation tests (docs/probabilistic.md) and, with ``--json``,
the result (``OnlineCalibrator.result().to_dict()``, the schema of
``estcal online --json``) with the number of skipped rows.

It is the object behind ``estcal online``, with the same prior and noise model,
so both give the same final estimate on the same rows (tests/test_notebooks.py
checks it).

Examples::

    python online_stream.py puma560 stream.csv --noise-pos-mm 0.1 --noise-rot-mrad 0.1 --free 'theta_*,d_1,d_4,d_5,d_6'
    measurement_source | python online_stream.py my_robot.yaml - --noise-pos-mm 0.05 --q-mm 0.001 --json state.json

The options are those of ``estcal online`` (docs/conventions.md, "Units on the command line"):
mm and mrad on the command line, each parameter's milli-unit for ``--q-mm`` and
``--prior-std-mm``; SI in the files and the JSON.

Exit codes: 0 done, 2 bad arguments / header / input (or a malformed row with ``--strict``).
"""
from __future__ import annotations

import argparse
import sys

import estcal  # top-level API: OnlineCalibrator (docs/api.md)
from estcal.io.stream import CsvStream


def die(msg: str) -> None:
    print(f"online_stream: error: {msg}", file=sys.stderr)
    sys.exit(2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("robot", help="built-in name (puma560, …), robot file (.yaml) or URDF")
    ap.add_argument("data", nargs="?", default="-", help="CSV file, or '-' (default) for standard input")
    ap.add_argument("--noise-pos-mm", type=float, default=0.1, help="position noise std per coordinate (mm)")
    ap.add_argument("--noise-rot-mrad", type=float, default=1.0, help="orientation noise std per axis (mrad)")
    ap.add_argument("--free", default=None, help="comma-separated names/patterns to estimate (default: the "
                                                 "identifiable set of the measurement)")
    ap.add_argument("--q-mm", type=float, default=0.0, help="process-noise std per row, in each parameter's "
                                                            "milli-unit (mm, mrad; 0 = constant parameters)")
    ap.add_argument("--q-params", default=None, help="apply --q-mm only to these comma-separated names/patterns")
    ap.add_argument("--prior-std-mm", type=float, default=100.0, help="prior std of every free parameter, in its "
                                                                      "milli-unit (mm, mrad)")
    ap.add_argument("--map", default=None, metavar="FILE.yaml", help="column map of the input (its own column "
                                                                     "names and units; docs/dataset.md)")
    ap.add_argument("--show", default=None, help="comma-separated parameters printed on every row (default: 3)")
    ap.add_argument("--strict", action="store_true", help="stop at the first malformed row (exit 2)")
    ap.add_argument("--json", default=None, help="write the final estimate, stds and covariance to this file")
    a = ap.parse_args(argv)
    milli = 1e-3  # mm / mrad on the command line, SI inside
    q_si = a.q_mm * milli
    q = {s.strip(): q_si for s in a.q_params.split(",") if s.strip()} if a.q_params else q_si
    try:
        cal = estcal.OnlineCalibrator(a.robot, free=a.free, noise=(a.noise_pos_mm * milli, a.noise_rot_mrad * milli),
                                      q=q, prior_std=a.prior_std_mm * milli, column_map=a.map)
    except (ValueError, KeyError, FileNotFoundError) as exc:
        die(str(exc))
    src = "<stdin>" if a.data == "-" else a.data
    wanted = [s.strip() for s in a.show.split(",")] if a.show else []
    if set(wanted) - set(cal.robot.params.names):
        die(f"--show: {', '.join(sorted(set(wanted) - set(cal.robot.params.names)))} are not parameters of "
            f"{cal.robot.name}")
    try:
        rows = CsvStream(a.data, cal.robot, column_map=cal.column_map)  # reads and checks the header
        # without --free: the identifiable set of the measurement the header names (as `estcal online`)
        names = cal.names or cal.start(rows.layout())
    except (ValueError, OSError) as exc:
        die(str(exc))
    show = wanted or names[:3]
    if set(show) - set(names):
        die(f"--show: {', '.join(sorted(set(show) - set(names)))} not among the free parameters ({', '.join(names)})")
    show = [names.index(s) for s in show]
    print(f"online_stream: {cal.robot.name}, {len(names)} free parameters, q = {a.q_mm:g} mm / mrad; reading {src} "
          f"(estimates in m, rad)", flush=True)
    skipped = 0
    try:
        for chunk in rows:  # a pipe's rows are used as they arrive (the stream cuts where no row waits)
            if chunk.data is not None:
                up = cal.update(chunk.data, trace=True)
                for j, k in enumerate(range(up.rows[0], up.rows[1] + 1)):
                    x, s = up.estimate[j], up.std[j]
                    par = "  ".join(f"{names[i]} = {x[i]:.7g} ± {s[i]:.2g}" for i in show)
                    print(f"row {k:5d}  NIS {up.nis[j]:7.2f}/{up.dims[j]}  {par}", flush=True)
            if chunk.error is not None:
                if a.strict:
                    die(str(chunk.error))
                skipped += 1
                print(f"online_stream: skipped {chunk.error}", file=sys.stderr, flush=True)
    except (ValueError, OSError) as exc:  # the header, or input that is not CSV text
        die(str(exc))
    if cal.n_rows == 0:
        die(f"{src}: no usable data row ({skipped} skipped)")
    res = cal.result()
    table = res.table()  # display units: mm, mrad (estcal.base.tables.parameter_table)
    table.title = f"\nestimate after {res.n_rows} rows ({skipped} skipped):"
    print(table)
    if a.json:
        from estcal.base.jsonio import write_json

        write_json(a.json, {**res.to_dict(), "skipped": skipped})
    return 0


if __name__ == "__main__":
    sys.exit(main())
