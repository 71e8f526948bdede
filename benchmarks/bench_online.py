"""Online calibration at sensor rate: rows per second of CPU, the row-by-row EKF and the segmented one.

A PUMA 560 position stream (noise 0.1 mm, the identifiable free set of the file, 30 parameters)
is simulated once; then, side by side in one run:

* **the Python object** — ``estcal.OnlineCalibrator.update`` on chunks of 1024 rows, CPU time
  (``time.process_time``): ``relinearize=1`` (before: every row linearised at the current estimate,
  filterpy's EKF step by step, one single-pose kinematics per row) and the default (after: rows
  linearised in segments, vectorised kinematics, exact block updates); their estimates compared in
  units of the row-by-row σ on the rows both processed;
* **the command** — ``estcal online FILE --free … --every 1000000`` in a child process, CPU time of
  the child (``resource.getrusage(RUSAGE_CHILDREN)``, user + system), start-up and the whole-file
  checks included: ``--relinearize 1`` (before) and the default (after), and the default with
  ``--state`` (a checkpoint every 100 rows).

The row-by-row path runs on the first ``--before-rows`` rows only (its cost per row does not
depend on the stream's length); rows/s is rows / CPU seconds. Figures: docs/benchmarks.md::

    python benchmarks/bench_online.py                       # N = 100,000 (about 2 minutes)
    python benchmarks/bench_online.py --n 20000 --before-rows 2000 --json out.json
    python benchmarks/bench_online.py --previous OLD_VENV/bin/estcal   # also time another installation
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ESTCAL = str(Path(sys.executable).parent / "estcal")


def child_cpu(args, exe=ESTCAL) -> tuple[float, int]:
    """(user + system CPU seconds, exit code) of ``estcal args`` in a child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([exe, *args], capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode:
        print(p.stderr[-2000:], file=sys.stderr)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), p.returncode


def object_rate(robot, free, ds, rows, **options):
    """(rows/s of CPU, calibrator) of OnlineCalibrator.update over the first ``rows`` rows."""
    import estcal

    cal = estcal.OnlineCalibrator(robot, free=free, noise=(1e-4, 1e-3), **options)
    t = time.process_time()
    for a in range(0, rows, 1024):
        cal.update(ds.subset(slice(a, min(a + 1024, rows))))
    return rows / (time.process_time() - t), cal


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000, help="rows of the stream")
    ap.add_argument("--before-rows", type=int, default=10_000, help="rows given to the row-by-row path")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--previous", type=Path, help="the `estcal` executable of another installation (e.g. the "
                    "commit before the segmented filter) whose `estcal online` is timed on the same rows too")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    import estcal
    from estcal.workflows.online import file_free_set

    work = Path(tempfile.mkdtemp(prefix="bench_online_"))
    data, head = work / "stream.csv", work / "head.csv"
    subprocess.run([ESTCAL, "simulate", "--robot", "puma560", "--n", str(a.n), "--measure", "position",
                    "--noise-pos-mm", "0.1", "--seed", str(a.seed), "-o", str(data)], check=True,
                   capture_output=True)
    nb = min(a.before_rows, a.n)
    lines = data.read_text().splitlines(keepends=True)
    head.write_text("".join(lines[:nb + 1]))
    robot = estcal.load_robot("puma560")
    ds = estcal.load_dataset(data, robot)
    free = file_free_set(robot, ds)
    print(f"PUMA 560 position stream, {a.n} rows, {len(free)} free parameters; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    out = {"n_rows": a.n, "before_rows": nb, "n_free": len(free), "load_average_at_start": os.getloadavg()[0]}
    r_before, slow = object_rate(robot, free, ds, nb, relinearize=1)
    r_after, fast = object_rate(robot, free, ds, a.n)
    _, fast_nb = object_rate(robot, free, ds, nb)
    dz = float(np.max(np.abs(fast_nb.estimate - slow.estimate) / slow.std))
    out["object"] = {"before_rows_per_s": r_before, "after_rows_per_s": r_after, "ratio": r_after / r_before,
                     "max_dz_sigma": dz}
    print(f"OnlineCalibrator.update: {r_before:,.0f} rows/s (row by row) → {r_after:,.0f} rows/s "
          f"(segments): ×{r_after / r_before:.1f}; estimates after {nb} rows differ by ≤ {dz:.1e} σ", flush=True)
    args = ["online", "--robot", "puma560", "--free", ",".join(free), "--every", "1000000"]
    c_before, _ = child_cpu([*args[:1], str(head), *args[1:], "--relinearize", "1"])
    c_after, _ = child_cpu([*args[:1], str(data), *args[1:]])
    c_state, _ = child_cpu([*args[:1], str(data), *args[1:], "--state", str(work / "state.json")])
    out["command"] = {"before_rows_per_s": nb / c_before, "after_rows_per_s": a.n / c_after,
                      "after_with_state_rows_per_s": a.n / c_state,
                      "cpu_s": {"before": c_before, "after": c_after, "after_with_state": c_state}}
    print(f"estcal online FILE: {nb / c_before:,.0f} rows/s (--relinearize 1, {nb} rows, {c_before:.1f} s CPU) → "
          f"{a.n / c_after:,.0f} rows/s ({a.n} rows, {c_after:.1f} s CPU): ×{(a.n / c_after) / (nb / c_before):.1f}; "
          f"with --state (checkpoint every 100 rows): {a.n / c_state:,.0f} rows/s", flush=True)
    if a.previous is not None:
        c_prev, code = child_cpu([*args[:1], str(head), *args[1:]], str(a.previous))
        out["command"]["previous_rows_per_s"] = nb / c_prev if code == 0 else None
        print(f"estcal online FILE with {a.previous}: {nb / c_prev:,.0f} rows/s ({nb} rows, {c_prev:.1f} s CPU)"
              if code == 0 else f"{a.previous} failed (exit {code})", flush=True)
    if a.json:
        a.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
