"""Scaling figures: many PUMA calibrations serially, on local processes and on a Dask LocalCluster.

Figures (wall-clock; the 1-minute load average ``os.getloadavg()[0]`` is recorded
beside every one, because the machine may be shared):

* ``calibrations``: ``--n`` (200) independent PUMA 560 LM calibrations (50 full
  poses, CMM noise, the 30 identifiable parameters of the full level — the
  ``puma_lm`` case of ``bench_calibration.py``) run by
  :func:`estcal.scale.run_tasks` serially, on a ``ProcessPoolExecutor`` and on a
  ``--workers`` (2) LocalCluster (started once, time reported apart); speed-up =
  serial / parallel wall time; the estimates are checked identical to serial;
* ``overhead``: per-task cost of the Dask path — ``--noop`` (1,000) tasks that
  do nothing, one task per job (``chunksize=1``) and in default chunks;
* ``memory``: resident memory of each Dask worker (MB) after the calibrations,
  and of this process;
* ``fleet``: ``estcal fleet``'s unit of work (load CSV + robot file, identifiable
  set, LM, validation, write the saved model) on a simulated fleet of ``--fleet``
  (40) robots, serial and on the cluster; bytes read and written per robot;
* ``projection``: from those costs, the wall time of a fleet of ``--project``
  (100,000) robots × 50 poses on N workers, and which resource saturates first
  (see docs/scaling.md for the model and its assumptions).

``--json PATH`` writes every figure; ``--quick`` runs a small version (CI smoke).
"""
from __future__ import annotations

import argparse
import functools
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_calibration import puma_problem  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402
from estcal.scale import run_tasks  # noqa: E402

# Assumed infrastructure of a production cluster (not measured here; stated in docs/scaling.md)
ASSUMED = {"scheduler_tasks_per_s": 3000.0,   # one Dask scheduler, ~300 µs of scheduler CPU per task
           "storage_mb_per_s": 1000.0,        # shared file system, aggregate
           "metadata_ops_per_s": 20000.0,     # file opens/creates per second on that file system
           "network_mb_per_s_per_worker": 100.0}


def load() -> float:
    return round(os.getloadavg()[0], 2)


def calibrate(task):
    """One PUMA calibration (module level: picklable); returns the estimate."""
    from estcal.estimate import calibrate_lsq

    prob, names = task
    return calibrate_lsq(prob, "lm", free=names).estimate


def calibrate_seed(task):
    """Monte-Carlo style: the task is a seed; the worker simulates its PUMA problem and calibrates
    it (small task input, as in a coverage or detection-power study)."""
    from bench_calibration import puma_problem

    seed, names = task
    prob, _ = puma_problem(50, seed, names)
    return calibrate((prob, names))


def noop(x):
    return x


def rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2 ** 20


def cpu_s() -> float:
    return time.process_time()


def worker_cpu(client) -> float:
    return float(sum(client.run(cpu_s).values()))


def timed(fn, *a, **k):
    l0 = load()
    t = time.perf_counter()
    c = time.process_time()
    out = fn(*a, **k)
    return out, time.perf_counter() - t, time.process_time() - c, max(l0, load())


def puma_problems(n, poses=50):
    """``n`` PUMA problems of ``bench_calibration`` (seeds 0 … n − 1), one identifiable-set search."""
    prob0, names = puma_problem(poses, 0)
    return [(prob0, names)] + [puma_problem(poses, seed, names) for seed in range(1, n)]


def bench_calibrations(client, n, workers):
    t = time.perf_counter()
    tasks = puma_problems(n)
    build = time.perf_counter() - t
    calibrate(tasks[0])  # warm-up (imports, caches)
    ser, ts, cs, ls = timed(run_tasks, calibrate, tasks, progress=False)
    prc, tp, _, lp = timed(run_tasks, calibrate, tasks, scheduler="processes", n_workers=workers, progress=False)
    run_tasks(calibrate, tasks[: 2 * workers], scheduler=client, chunksize=1, progress=False)  # worker warm-up
    w0 = worker_cpu(client)
    dsk, td, _, ld = timed(run_tasks, calibrate, tasks, scheduler=client, progress=False)
    wcpu = worker_cpu(client) - w0
    dsk1, td1, _, ld1 = timed(run_tasks, calibrate, tasks, scheduler=client, chunksize=1, progress=False)
    same = all(np.array_equal(a, b) for r in (prc, dsk, dsk1) for a, b in zip(ser.values(), r.values()))
    # the same calibrations with the simulation inside the task (a seed in, an estimate out)
    seeds = [(i, tasks[0][1]) for i in range(n)]
    calibrate_seed(seeds[0])
    sser, tss, _, lss = timed(run_tasks, calibrate_seed, seeds, progress=False)
    run_tasks(calibrate_seed, seeds[: 2 * workers], scheduler=client, chunksize=1, progress=False)
    sdsk, tsd, _, lsd = timed(run_tasks, calibrate_seed, seeds, scheduler=client, progress=False)
    same = same and all(np.array_equal(a, b) for a, b in zip(sser.values(), sdsk.values()))
    return {"n": n, "poses": 50, "n_parameters": len(tasks[0][1]), "build_s": build,
            "serial_s": ts, "serial_cpu_s": cs, "serial_ms_per_task": 1e3 * ts / n, "load_serial": ls,
            "processes_s": tp, "processes_speedup": ts / tp, "load_processes": lp,
            "dask_s": td, "dask_speedup": ts / td, "load_dask": ld, "dask_worker_cpu_s": wcpu,
            "dask_cpu_efficiency": cs / wcpu,
            "dask_chunksize1_s": td1, "dask_chunksize1_speedup": ts / td1, "load_dask_chunksize1": ld1,
            "identical_to_serial": bool(same), "workers": workers,
            "seeded_serial_s": tss, "load_seeded_serial": lss, "seeded_dask_s": tsd,
            "seeded_dask_speedup": tss / tsd, "load_seeded_dask": lsd}


def bench_overhead(client, n):
    _, t1, _, l1 = timed(run_tasks, noop, range(n), scheduler=client, chunksize=1, progress=False)
    _, tc, _, lc = timed(run_tasks, noop, range(n), scheduler=client, progress=False)
    _, tp, _, lp = timed(run_tasks, noop, range(n), scheduler="processes", n_workers=2, chunksize=1,
                         progress=False)
    _, tsr, _, ls = timed(run_tasks, noop, range(n), progress=False)
    return {"n": n, "dask_ms_per_task_chunksize1": 1e3 * t1 / n, "load_dask_chunksize1": l1,
            "dask_ms_per_task_chunked": 1e3 * tc / n, "load_dask_chunked": lc,
            "processes_ms_per_task_chunksize1": 1e3 * tp / n, "load_processes": lp,
            "serial_ms_per_task": 1e3 * tsr / n, "load_serial": ls}


def bench_memory(client):
    per = client.run(rss_mb)
    return {"worker_rss_mb": sorted(float(v) for v in per.values()), "client_rss_mb": rss_mb(), "load": load()}


def _folder_bytes(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def bench_fleet(client, n, tmp):
    from estcal.workflows.fleet import FleetOptions, run_fleet
    from estcal.simulate.fleet import simulate_fleet

    from estcal.workflows.fleet import discover_fleet, process_robot

    root = Path(tmp) / "fleet"
    simulate_fleet(n, root, n_poses=50, n_validate=50, seed=1, progress=False)
    inp = _folder_bytes(root) / n
    # warm-up (imports, first calls) here and on every worker, outside the timings
    job, warm = discover_fleet(root)[0], FleetOptions(save_models=str(Path(tmp) / "warm"))
    process_robot(job, warm)
    client.run(process_robot, job, warm)
    s, ts, cs, ls = timed(run_fleet, root, FleetOptions(save_models=str(Path(tmp) / "m1")), progress=False)
    w0 = worker_cpu(client)
    d, td, _, ld = timed(run_fleet, root, FleetOptions(save_models=str(Path(tmp) / "m2")), scheduler=client,
                         progress=False)
    wcpu = worker_cpu(client) - w0
    out = _folder_bytes(Path(tmp) / "m1") / max(1, s.n_ok)
    return {"n": n, "ok": s.n_ok, "serial_s": ts, "serial_ms_per_robot": 1e3 * ts / n, "load_serial": ls,
            "serial_cpu_ms_per_robot": 1e3 * cs / n,
            "dask_s": td, "dask_speedup": ts / td, "load_dask": ld, "dask_worker_cpu_s": wcpu,
            "dask_cpu_efficiency": cs / wcpu, "input_kb_per_robot": inp / 1024,
            "model_kb_per_robot": out / 1024, "files_per_robot": 4}


def projection(fleet, overhead, memory, robots=100_000, workers=(2, 10, 100, 1000, 10000), chunk=100):
    """Wall time of ``robots`` robots on N workers: the slowest of compute, scheduler, storage, metadata."""
    # CPU time of one robot in the serial run, I/O included: the wall time on a dedicated core
    # (the wall time of this run is inflated when the machine is shared)
    t_robot = fleet["serial_cpu_ms_per_robot"] / 1e3
    mb_robot = (fleet["input_kb_per_robot"] + fleet["model_kb_per_robot"]) / 1024
    tasks = robots / chunk
    rows = []
    for N in workers:
        limits = {"compute": robots * t_robot / N,
                  "scheduler": tasks / ASSUMED["scheduler_tasks_per_s"],
                  "storage": robots * mb_robot / ASSUMED["storage_mb_per_s"],
                  "metadata": robots * fleet["files_per_robot"] / ASSUMED["metadata_ops_per_s"],
                  "network": robots * mb_robot / (N * ASSUMED["network_mb_per_s_per_worker"])}
        first = max(limits, key=limits.get)
        rows.append({"workers": N, "wall_s": limits[first], "bound_by": first, **{f"{k}_s": v for k, v in
                                                                                 limits.items()}})
    return {"robots": robots, "poses": 50, "robots_per_task": chunk, "cpu_s_per_robot": t_robot,
            "mb_per_robot": mb_robot, "worker_rss_mb": max(memory["worker_rss_mb"]), "assumed": ASSUMED,
            "rows": rows}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=200, help="PUMA calibrations")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--noop", type=int, default=1000, help="empty tasks for the overhead figure")
    ap.add_argument("--fleet", type=int, default=40, help="robots of the simulated fleet")
    ap.add_argument("--project", type=int, default=100_000, help="robots of the projected fleet")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.noop, args.fleet = 20, 100, 6
    from distributed import Client, LocalCluster

    out = {"environment": {"python": platform.python_version(), "cpus": os.cpu_count(),
                           "machine": platform.machine(), "load_start": list(os.getloadavg())}}
    t = time.perf_counter()
    import dask

    # the workers import bench_calibration (seeded tasks) like this process does
    os.environ["PYTHONPATH"] = os.pathsep.join([str(REPO / "benchmarks"), str(REPO),
                                                os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    with dask.config.set({"distributed.worker.profile.enabled": False}), \
            LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                         dashboard_address=":0") as cluster, Client(cluster) as client:
        out["cluster_start_s"] = time.perf_counter() - t
        out["calibrations"] = bench_calibrations(client, args.n, args.workers)
        c = out["calibrations"]
        print(f"{c['n']} PUMA calibrations (50 poses, {c['n_parameters']} parameters): serial {c['serial_s']:.2f} s "
              f"({c['serial_ms_per_task']:.1f} ms each, load {c['load_serial']}); processes×{args.workers} "
              f"{c['processes_s']:.2f} s = {c['processes_speedup']:.2f}× (load {c['load_processes']}); Dask "
              f"LocalCluster×{args.workers} {c['dask_s']:.2f} s = {c['dask_speedup']:.2f}× (load {c['load_dask']}), "
              f"one task per job {c['dask_chunksize1_speedup']:.2f}×; identical to serial: "
              f"{c['identical_to_serial']}; cluster start {out['cluster_start_s']:.1f} s; CPU: serial "
              f"{c['serial_cpu_s']:.2f} s, Dask workers {c['dask_worker_cpu_s']:.2f} s (efficiency "
              f"{c['dask_cpu_efficiency']:.2f})")
        print(f"  the same with the simulation inside each task (a seed in, an estimate out): serial "
              f"{c['seeded_serial_s']:.2f} s (load {c['load_seeded_serial']}), Dask LocalCluster×{args.workers} "
              f"{c['seeded_dask_s']:.2f} s = {c['seeded_dask_speedup']:.2f}× (load {c['load_seeded_dask']})")
        out["overhead"] = o = bench_overhead(client, args.noop)
        print(f"per-task overhead ({o['n']} empty tasks): Dask one task per job {o['dask_ms_per_task_chunksize1']:.2f} ms "
              f"(load {o['load_dask_chunksize1']}), chunked {o['dask_ms_per_task_chunked']:.3f} ms; processes "
              f"{o['processes_ms_per_task_chunksize1']:.3f} ms; serial {o['serial_ms_per_task'] * 1e3:.1f} µs")
        out["memory"] = m = bench_memory(client)
        print(f"memory: workers {', '.join(f'{v:.0f}' for v in m['worker_rss_mb'])} MB RSS; client "
              f"{m['client_rss_mb']:.0f} MB (load {m['load']})")
        tmp = tempfile.mkdtemp(prefix="estcal-bench-scale-")
        try:
            out["fleet"] = f = bench_fleet(client, args.fleet, tmp)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        print(f"fleet of {f['n']} robots: serial {f['serial_s']:.2f} s ({f['serial_ms_per_robot']:.1f} ms per robot, "
              f"CPU {f['serial_cpu_ms_per_robot']:.1f} ms, load {f['load_serial']}); Dask×{args.workers} {f['dask_s']:.2f} s = {f['dask_speedup']:.2f}× "
              f"(load {f['load_dask']}, CPU efficiency {f['dask_cpu_efficiency']:.2f}); {f['input_kb_per_robot']:.0f} kB in, {f['model_kb_per_robot']:.0f} kB "
              f"model out per robot")
    out["projection"] = p = projection(out["fleet"], out["overhead"], out["memory"], robots=args.project)
    print(f"projection, {p['robots']:,} robots × 50 poses ({p['cpu_s_per_robot'] * 1e3:.0f} ms of one core and "
          f"{p['mb_per_robot'] * 1024:.0f} kB per robot, {p['robots_per_task']} robots per task):")
    for r in p["rows"]:
        print(f"  {r['workers']:>6} workers: {r['wall_s']:>9.1f} s, bound by {r['bound_by']} (compute "
              f"{r['compute_s']:.1f} s, scheduler {r['scheduler_s']:.1f} s, storage {r['storage_s']:.1f} s, "
              f"metadata {r['metadata_s']:.1f} s, network {r['network_s']:.2f} s)")
    out["environment"]["load_end"] = list(os.getloadavg())
    if args.json:
        write_json(args.json, out)
    return out


if __name__ == "__main__":
    main()
