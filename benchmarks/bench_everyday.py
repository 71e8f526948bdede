"""Everyday speed: the commands a user runs first, before and after, side by side in one run.

Each figure is the CPU time (user + system) of a child process (``resource.getrusage(RUSAGE_CHILDREN)``),
the median of ``--repeat`` runs, for this checkout ("after") and, with ``--baseline DIR``, for another
checkout with its own ``DIR/.venv`` ("before"), interleaved so that both see the same load:

* ``import``: ``python -c "import estcal.cli.main"`` (target ≤ 0.25 s);
* ``help``: ``estcal --help`` (target ≤ 0.25 s);
* ``calibrate``: ``estcal calibrate --robot puma560 m50.csv`` — 50 simulated full poses (noise
  0.05 mm / 0.5 mrad, seed 1; the whole process: start-up, checks, fit, table) (target ≤ 0.8 s);
* ``diagnose``: ``estcal diagnose`` of one TIAGo session (``../shared/data/tiago``, training file)
  with the default options (target ≤ 3 s), which now include the posture-grouped error budget;
  ``diagnose-no-budget``: the analysis the baseline's ``diagnose`` made (``--no-budget`` after);
* ``diagnose-sessions``: ``estcal diagnose`` of both TIAGo sessions with the default options, error budget
  included (target ≤ 6 s); ``diagnose-recommended``: both sessions, the baseline running the command its
  README recommended for accuracy at new postures (``--geometric prior --residual-model gp-joints --folds 10``,
  one run: minutes), this checkout its default — the answer to the same question, before and after;
* ``refuse-identical``: ``estcal calibrate`` of ``--rows`` identical pose rows (default 10⁶), refused
  (exit 3; target ≤ 15 s);
* ``refuse-5-postures``: ``estcal calibrate`` of the same number of rows cycling over 5 distinct
  postures (30 equations for the 30 parameters the full level identifies), refused (exit 3);
* ``tiago-lm``: the TIAGo 11-30 full-level LM fit of ``benchmarks/bench_calibration.py`` (same data,
  start and free set) in a child of each checkout, CPU ms of ``calibrate_lsq`` in process, and
  FIGAROH's model in scipy's LM on the same problem (``figaroh_compare``, when ``import figaroh``
  works): the ratio FIGAROH / estcal (target ≥ 50×);
* ``online``: ``benchmarks/bench_online.py --n ROWS --previous DIR/.venv/bin/estcal`` — rows per CPU
  second of the whole ``estcal online`` command, this checkout and the baseline's.

The children run with the BLAS thread variables (``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``,
``MKL_NUM_THREADS``) removed from the environment, as a user's shell has them, and without
``PYTHONDONTWRITEBYTECODE``, so that both checkouts run from compiled bytecode as an installed package does
(``compileall`` writes it for both before any timing, as pip does at install time). Usage::

    python benchmarks/bench_everyday.py --baseline ../baseline [--repeat 3] [--rows 1000000] [--json out.json]
    python benchmarks/bench_everyday.py --skip refuse-identical refuse-5-postures online   # the quick ones

Figures and the causes found: docs/benchmarks.md, "Everyday commands".
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

REPO = Path(__file__).resolve().parents[1]
TIAGO = REPO.parent / "shared" / "data" / "tiago"
SESSIONS = [TIAGO / "qualisys_2021-11-30_static_postures.csv", TIAGO / "qualisys_2021-11-26_static_postures.csv"]
BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
TARGETS = {"import": ("≤", 0.25, "s"), "help": ("≤", 0.25, "s"), "calibrate": ("≤", 0.8, "s"),
           "diagnose": ("≤", 3.0, "s"), "diagnose-sessions": ("≤", 6.0, "s"), "refuse-identical": ("≤", 15.0, "s"), "tiago-lm": ("≥", 50.0, "×"),
           "online": ("≥", 10_000.0, "rows/s")}
ROWS = ("import", "help", "calibrate", "diagnose", "diagnose-no-budget", "diagnose-sessions", "diagnose-recommended",
        "refuse-identical", "refuse-5-postures", "tiago-lm", "online")
#: the command the baseline's README recommended for accuracy at new postures (refused by this checkout)
FORMER_RECOMMENDED = ["--geometric", "prior", "--residual-model", "gp-joints", "--folds", "10"]


class Side:
    """A checkout with its virtual environment: ``python`` and the ``estcal`` command of that venv."""

    def __init__(self, name: str, python: Path):
        self.name, self.python = name, Path(python)
        self.estcal = self.python.with_name("estcal")

    @classmethod
    def of_checkout(cls, name: str, root: Path) -> "Side":
        py = Path(root) / ".venv" / "bin" / "python"
        if not py.exists():
            raise SystemExit(f"{py} not found: --baseline needs a checkout with its own .venv")
        return cls(name, py)


def _env() -> dict:
    # PYTHONDONTWRITEBYTECODE too: an installed package runs from its compiled bytecode (pip compiles it at
    # install time); with the variable set, every run of an editable checkout recompiles its ~130 modules
    return {k: v for k, v in os.environ.items() if k not in BLAS_VARIABLES + ("PYTHONDONTWRITEBYTECODE",)}


def child_cpu(cmd, cwd) -> tuple[float, int, str]:
    """(user + system CPU seconds, exit code, stdout) of ``cmd`` in a child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, cwd=cwd, env=_env())
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, p.returncode, p.stdout + p.stderr


def _median(xs):
    xs = sorted(xs)
    return xs[len(xs) // 2] if len(xs) % 2 else 0.5 * (xs[len(xs) // 2 - 1] + xs[len(xs) // 2])


def timed(sides, make_cmd, repeat, cwd, expect_rc=0) -> dict:
    """Median CPU seconds of ``make_cmd(side)`` per side, the sides interleaved run by run."""
    runs = {s.name: [] for s in sides}
    for _ in range(repeat):
        for s in sides:
            cpu, rc, out = child_cpu(make_cmd(s), cwd)
            if rc != expect_rc:
                raise RuntimeError(f"{s.name}: {' '.join(map(str, make_cmd(s)))} exited {rc} (expected {expect_rc}):\n"
                                   f"{out[-1500:]}")
            runs[s.name].append(cpu)
    return {k: {"cpu_s": _median(v), "runs_s": v} for k, v in runs.items()}


def write_inputs(work: Path, after: Side, rows: int) -> dict:
    """m50.csv (50 simulated PUMA full poses) and the two refusal files of ``rows`` rows."""
    m50 = work / "m50.csv"
    subprocess.run([str(after.estcal), "simulate", "--robot", "puma560", "--n", "50", "--measure", "pose",
                    "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--seed", "1", "-o", str(m50)],
                   check=True, capture_output=True, env=_env())
    lines = m50.read_text().splitlines()
    out = {"m50": m50, "identical": work / "identical.csv", "five": work / "five.csv"}
    with open(out["identical"], "w") as f:
        f.write(lines[0] + "\n")
        f.write((lines[1] + "\n") * rows)
    with open(out["five"], "w") as f:
        f.write(lines[0] + "\n")
        block = "\n".join(lines[1:6]) + "\n"
        f.write(block * (rows // 5) + "\n".join(lines[1:1 + rows % 5]) + ("\n" if rows % 5 else ""))
    return out


def tiago_lm_child(repeat: int) -> dict:
    """CPU ms (median of ``repeat``) of the TIAGo full-level LM fit of ``bench_calibration.figaroh_compare``,
    with whatever estcal this interpreter imports (works with the API before and after the layering)."""
    import numpy as np

    try:
        from estcal.workflows.calibrate import run_calibration
    except ImportError:  # before the workflow layer
        from estcal.estimate.levels import run_calibration
    try:
        from estcal.base.blas import single_thread_blas
    except ImportError:
        from estcal.estimate.lsq import single_thread_blas
    from estcal.estimate import calibrate_lsq
    from estcal.io import load_dataset
    from estcal.io.robotfile import load_robot
    from estcal.methods import NoiseModel, Problem

    robot = load_robot(TIAGO / "tiago_48_schunk.urdf", root="base_footprint", tip="wrist_ft_tool_link", n_markers=1)
    train = load_dataset(TIAGO / "qualisys_2021-11-30_static_postures.csv", robot, points=1)
    _, sel, _ = run_calibration(robot, train, level="full", noise=NoiseModel(position=1e-3))
    prob = Problem(robot.with_values(np.asarray(sel.theta, float)), [(None, train, NoiseModel(position=1e-3))])
    cpu = []
    for _ in range(repeat + 1):  # the first run warms the caches of the kinematics
        with single_thread_blas():
            t = time.process_time()
            res = calibrate_lsq(prob, "lm", free=sel.identifiable)
            cpu.append(time.process_time() - t)
    return {"cpu_ms": 1e3 * _median(cpu[1:]), "iterations": int(res.n_iterations),
            "rmse_mm": float(res.accuracy["train"]["after"]["rmse_mm"]), "n_parameters": len(sel.identifiable),
            "estimate": [float(v) for v in res.estimate], "std": [float(v) for v in res.std]}


def tiago_lm(sides, repeat, cwd) -> dict:
    out = {}
    for s in sides:
        p = subprocess.run([str(s.python), str(Path(__file__).resolve()), "--tiago-lm-child", str(repeat)],
                           capture_output=True, text=True, cwd=cwd, env=_env())
        if p.returncode:
            raise RuntimeError(f"{s.name}: TIAGo LM child failed:\n{p.stderr[-1500:]}")
        out[s.name] = json.loads(p.stdout.strip().splitlines()[-1])
    try:
        sys.path.insert(0, str(REPO / "benchmarks"))
        from bench_calibration import bench_figaroh

        fig = bench_figaroh(repeat)
    except Exception as exc:  # noqa: BLE001 - the estcal figures stand without the peer
        fig = {"available": False, "error": f"{type(exc).__name__}: {exc}"}
    out["figaroh"] = {k: v for k, v in fig.items() if k not in ("figaroh_parameters",)}
    if "figaroh_cpu_ms" in fig:
        for s in sides:
            out[s.name]["ratio_vs_figaroh"] = fig["figaroh_cpu_ms"] / out[s.name]["cpu_ms"]
    if len(sides) == 2:
        import numpy as np

        a, b = out[sides[0].name], out[sides[1].name]
        out["max_difference_sigma"] = float(np.max(np.abs(np.subtract(a["estimate"], b["estimate"]))
                                                   / np.asarray(a["std"])))
    for s in sides:
        out[s.name].pop("estimate"), out[s.name].pop("std")
    return out


def online(sides, rows, cwd) -> dict:
    """rows/s of the whole ``estcal online`` command (bench_online.py, its ``--previous`` for the baseline)."""
    with tempfile.TemporaryDirectory() as tmp:
        js = Path(tmp) / "online.json"
        cmd = [sys.executable, str(REPO / "benchmarks" / "bench_online.py"), "--n", str(rows),
               "--before-rows", str(max(1000, rows // 10)), "--json", str(js)]
        base = [s for s in sides if s.name == "before"]
        if base:
            cmd += ["--previous", str(base[0].estcal)]
        p = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, env=_env())
        if p.returncode:
            raise RuntimeError(f"bench_online.py failed:\n{p.stderr[-1500:]}")
        return json.loads(js.read_text())


def _fmt(v, unit):
    if unit == "×":
        return f"{v:.1f}×"
    if unit == "rows/s":
        return f"{v:,.0f} rows/s"
    return f"{v:.3f} s"


def _verdict(row, value):
    if row not in TARGETS or value is None:
        return ""
    op, target, unit = TARGETS[row]
    ok = value <= target if op == "≤" else value >= target
    return f"target {op} {_fmt(target, unit)}: {'met' if ok else 'NOT met'}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline", type=Path, help="a checkout with its own .venv: the 'before' column")
    ap.add_argument("--repeat", type=int, default=3, help="runs per command and side (median)")
    ap.add_argument("--rows", type=int, default=1_000_000, help="rows of the two refusal files")
    ap.add_argument("--online-rows", type=int, default=20_000, help="rows of the online stream")
    ap.add_argument("--skip", nargs="*", default=[], choices=ROWS, help="rows of the table not to measure")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--tiago-lm-child", type=int, metavar="REPEAT", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.tiago_lm_child is not None:
        print(json.dumps(tiago_lm_child(a.tiago_lm_child)))
        return None
    after = Side("after", Path(sys.executable))
    sides = [Side.of_checkout("before", a.baseline), after] if a.baseline else [after]
    for s, root in zip(sides, ([a.baseline] if a.baseline else []) + [REPO]):
        # the bytecode pip writes at install time, for both checkouts, before any timing
        subprocess.run([str(s.python), "-m", "compileall", "-q", str(Path(root) / "estcal")], check=True,
                       capture_output=True, env=_env())
    skip = set(a.skip)
    if not TIAGO.exists():
        skip |= {"diagnose", "diagnose-no-budget", "diagnose-sessions", "diagnose-recommended", "tiago-lm"}
        print(f"TIAGo data not found at {TIAGO}: diagnose and tiago-lm skipped")
    out = {"environment": {"load_average_at_start": list(os.getloadavg()), "cpus": os.cpu_count(),
                           "python": sys.version.split()[0], "repeat": a.repeat,
                           "sides": {s.name: str(s.python) for s in sides}}, "rows": {}}
    print(f"load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; CPU time (user + system) of "
          f"each child, median of {a.repeat}")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        files = write_inputs(work, after, a.rows if not {"refuse-identical", "refuse-5-postures"} <= skip else 10)
        commands = {
            "import": (lambda s: [s.python, "-c", "import estcal.cli.main"], 0),
            "help": (lambda s: [s.estcal, "--help"], 0),
            "calibrate": (lambda s: [s.estcal, "calibrate", "--robot", "puma560", files["m50"]], 0),
            "diagnose": (lambda s: [s.estcal, "diagnose", TIAGO / "qualisys_2021-11-30_static_postures.csv",
                                    "--robot", "tiago"], 0),
            # the same analysis as the baseline's (its diagnose had no error budget): --no-budget after
            "diagnose-no-budget": (lambda s: [s.estcal, "diagnose", TIAGO / "qualisys_2021-11-30_static_postures.csv",
                                              "--robot", "tiago"] + (["--no-budget"] if s.name == "after" else []), 0),
            "diagnose-sessions": (lambda s: [s.estcal, "diagnose", *SESSIONS, "--robot", "tiago"], 0),
            "diagnose-recommended": (lambda s: [s.estcal, "diagnose", *SESSIONS, "--robot", "tiago"]
                                     + (FORMER_RECOMMENDED if s.name == "before" else []), 0),
            "refuse-identical": (lambda s: [s.estcal, "calibrate", "--robot", "puma560", files["identical"]], 3),
            "refuse-5-postures": (lambda s: [s.estcal, "calibrate", "--robot", "puma560", files["five"]], 3),
        }
        for row in ROWS:
            if row in skip:
                continue
            t = time.perf_counter()
            if row in commands:
                make, rc = commands[row]
                reps = 1 if row.startswith("refuse") or row == "diagnose-recommended" else a.repeat
                r = timed(sides, make, reps, work, rc)
                vals = {k: v["cpu_s"] for k, v in r.items()}
                unit = "s"
            elif row == "tiago-lm":
                r = tiago_lm(sides, max(a.repeat, 5), work)
                vals = {s.name: r[s.name].get("ratio_vs_figaroh") for s in sides}
                unit = "×"
            else:
                r = online(sides, a.online_rows, work)
                vals = {"before": r["command"].get("previous_rows_per_s") if a.baseline else None,
                        "after": r["command"]["after_rows_per_s"]}
                unit = "rows/s"
            out["rows"][row] = r
            cells = "   ".join(f"{k} {_fmt(v, unit) if v is not None else '—'}" for k, v in vals.items())
            print(f"{row:18s} {cells}   {_verdict(row, vals.get('after'))}   ({time.perf_counter() - t:.0f} s wall)")
            if row == "tiago-lm":
                for s in sides:
                    print(f"{'':18s} {s.name}: estcal {r[s.name]['cpu_ms']:.2f} ms CPU, {r[s.name]['iterations']} "
                          f"iterations, train RMSE {r[s.name]['rmse_mm']:.3f} mm")
                f = r["figaroh"]
                if "figaroh_cpu_ms" in f:
                    print(f"{'':18s} FIGAROH model + scipy LM {f['figaroh_cpu_ms']:.1f} ms CPU "
                          f"({f['figaroh_nfev']} evaluations), train RMSE {f['figaroh_rmse_mm']:.3f} mm")
                else:
                    print(f"{'':18s} FIGAROH not run: {f.get('error')}")
                if "max_difference_sigma" in r:
                    print(f"{'':18s} estimates before vs after: max {r['max_difference_sigma']:.1e} σ")
    out["environment"]["load_average_at_end"] = list(os.getloadavg())
    print(f"load average at end {os.getloadavg()[0]:.1f}")
    if a.json:
        a.json.write_text(json.dumps(out, indent=2, default=str))
    return out


if __name__ == "__main__":
    main()
