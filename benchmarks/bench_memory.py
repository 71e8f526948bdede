"""Peak memory (RSS) and wall time of the data-heavy commands on large datasets.

Each command runs in its own process under ``/usr/bin/time -v`` ("Maximum resident set
size"; on systems without it, ``resource.getrusage(RUSAGE_CHILDREN)`` of a fresh child), on
a PUMA 560 pose dataset of N rows simulated once per size (noise 0.05 mm / 0.5 mrad)::

    python benchmarks/bench_memory.py --n 20000 100000 --json out.json
    python benchmarks/bench_memory.py --quick            # N = 5000, for a smoke run
    python benchmarks/bench_memory.py --commands check-random frames-random   # 50 MB of random numbers

Commands measured: ``simulate`` (always: it writes the dataset), ``fk``, ``identifiable --data``,
``online --free (5 parameters)``, ``online-state`` (the same with ``--state``: a checkpoint every
100 rows, the journal appended), ``calibrate`` (full level, LM) and ``calibrate-robust`` (the same
with ``--robust huber``: iteratively reweighted), ``calibrate-gtsam`` and ``calibrate-kalman``
(the same with ``--estimator gtsam`` / ``kalman``); ``check-random`` and ``frames-random``: ``estcal check``
and ``estcal frames`` on 50 MB of random numbers under a joint/position header. Figures: docs/benchmarks.md
("Memory on large datasets").
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ESTCAL = str(Path(sys.executable).parent / "estcal")
FREE = "offset_2,offset_3,a_2,d_3,alpha_3"


def run(args, timeout):
    """(peak RSS MB, wall s, exit code) of ``estcal args`` in a child process."""
    cmd = [ESTCAL, *args]
    if shutil.which("time") or os.path.exists("/usr/bin/time"):
        t0 = time.perf_counter()
        p = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, timeout=timeout)
        wall = time.perf_counter() - t0
        m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
        return (int(m.group(1)) / 1024 if m else float("nan")), wall, p.returncode
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(after, before) / 1024, wall, p.returncode


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[20000, 100000], help="dataset sizes (poses)")
    ap.add_argument("--commands", nargs="+", default=["fk", "identifiable", "online", "calibrate"],
                    choices=["fk", "identifiable", "online", "online-state", "calibrate", "calibrate-robust",
                             "calibrate-gtsam", "calibrate-kalman", "check-random", "frames-random"])
    ap.add_argument("--random-mb", type=float, default=50.0,
                    help="size of the random-numbers file of check-random / frames-random (MB)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per command")
    ap.add_argument("--quick", action="store_true", help="N = 5000 only")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    sizes = [5000] if a.quick else a.n
    out = []
    random_cmds = [c for c in a.commands if c.endswith("-random")]
    a.commands = [c for c in a.commands if c not in random_cmds]
    if random_cmds:
        out += random_numbers(random_cmds, a.random_mb, a.timeout)
    if not a.commands:
        sizes = []
    with tempfile.TemporaryDirectory() as d:
        for n in sizes:
            data = Path(d) / f"pose{n}.csv"
            rss, wall, rc = run(["simulate", "--robot", "puma560", "--n", str(n), "--measure", "pose",
                                 "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--seed", "1", "-o", str(data)],
                                a.timeout)
            assert rc == 0, f"simulate failed for N = {n}"
            out.append({"command": "simulate", "n_poses": n, "file_mb": data.stat().st_size / 2**20,
                        "peak_rss_mb": rss, "wall_s": wall, "exit_code": rc})
            print(f"{'simulate':13s} N={n:8d}  file {out[-1]['file_mb']:7.1f} MB  peak RSS {rss:8.1f} MB  "
                  f"{wall:8.1f} s  exit {rc}", flush=True)
            cmds = {
                "fk": ["fk", str(data), "--robot", "puma560", "-o", str(Path(d) / "fk.csv")],
                "identifiable": ["identifiable", "--robot", "puma560", "--data", str(data)],
                "online": ["online", str(data), "--robot", "puma560", "--free", FREE, "--every", "1000000"],
                "online-state": ["online", str(data), "--robot", "puma560", "--free", FREE, "--every", "1000000",
                                 "--state", str(Path(d) / f"state{n}.json")],
                "calibrate": ["calibrate", str(data), "--robot", "puma560"],
                "calibrate-robust": ["calibrate", str(data), "--robot", "puma560", "--robust", "huber"],
                "calibrate-gtsam": ["calibrate", str(data), "--robot", "puma560", "--estimator", "gtsam"],
                "calibrate-kalman": ["calibrate", str(data), "--robot", "puma560", "--estimator", "kalman"],
            }
            for c in a.commands:
                rss, wall, rc = run(cmds[c], a.timeout)
                row = {"command": c, "n_poses": n, "file_mb": data.stat().st_size / 2**20, "peak_rss_mb": rss,
                       "wall_s": wall, "exit_code": rc}
                out.append(row)
                print(f"{c:13s} N={n:8d}  file {row['file_mb']:7.1f} MB  peak RSS {rss:8.1f} MB  "
                      f"{wall:8.1f} s  exit {rc}", flush=True)
    if a.json:
        a.json.write_text(json.dumps(out, indent=2))
    return out


def random_numbers(commands, mb: float, timeout: float) -> list:
    """Peak RSS and wall time of ``estcal check`` (robot puma560) and ``estcal frames`` (the PUMA 560 as a URDF,
    ``estcal.export_urdf``) on a file of ``mb`` MB of uniform random numbers under the header j1…j6,x,y,z
    (joints in ±1 rad, positions in ±0.5 m: they pass the loader's unit checks). Before the bounded paths:
    check 2 min 47 s and 2.15 GB on 50 MB, frames 1.5 GB."""
    import numpy as np

    import estcal

    out = []
    with tempfile.TemporaryDirectory() as d:
        urdf = Path(d) / "puma560.urdf"
        estcal.export_urdf(estcal.load_robot("puma560"), urdf)
        header = ["j1", "j2", "j3", "j4", "j5", "j6", "x", "y", "z"]
        n = int(mb * 2**20 / (20 * len(header)))  # ~20 characters a field
        rng = np.random.default_rng(0)
        f = Path(d) / "random.csv"
        np.savetxt(f, np.c_[rng.uniform(-1, 1, (n, 6)), rng.uniform(-0.5, 0.5, (n, 3))], delimiter=",",
                   header=",".join(header), comments="", fmt="%.17g")
        for c in commands:
            robot = "puma560" if c == "check-random" else str(urdf)
            rss, wall, rc = run([c.split("-")[0], str(f), "--robot", robot], timeout)
            row = {"command": c, "n_poses": n, "file_mb": f.stat().st_size / 2**20, "peak_rss_mb": rss,
                   "wall_s": wall, "exit_code": rc}
            out.append(row)
            print(f"{c:13s} N={n:8d}  file {row['file_mb']:7.1f} MB  peak RSS {rss:8.1f} MB  {wall:8.1f} s  "
                  f"exit {rc}", flush=True)
    return out


if __name__ == "__main__":
    main()
