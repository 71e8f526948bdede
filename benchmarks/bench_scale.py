"""Scaling figures: ``estcal fleet`` on a real Dask cluster, and (``--local``) the LocalCluster figures.

The cluster run (default) starts ``dask scheduler`` and ``--workers`` (2) ``dask worker
--nthreads 1`` processes, with their nannies, on the loopback interface (tests/dask_cluster.py)
and runs the commands a user types, each in its own process, on fleets generated on demand
(``estcal simulate --fleet N --on-demand``, 50 + 50 poses per robot):

* ``serial``: ``estcal fleet`` on ``--serial-robots`` (2,000) robots without Dask, then the same
  robots on the cluster: the speed-up (wall time of the commands, and of the runs alone), the
  rows checked identical; ``--repeats`` (3) such pairs, alternated (each later pair on a fresh
  cluster), and their median — this machine's speed drifts by several per cent over minutes;
* ``big``: ``--robots`` (10,000) robots on the cluster — wall time; every process's CPU (workers,
  scheduler, the command); peak RSS of each worker (sampled every 0.2 s, and /proc VmHWM), of the
  scheduler and of the command; the scheduler's CPU per task beyond its idle heartbeat; the disk
  the per-robot results take; then the same command again (every robot skipped);
* ``noop``: the round trip of an empty Dask task on this cluster (one per task);
* ``projection``: from those measured costs, the wall time of ``--project`` (100,000) robots on N
  workers and what saturates first (compute, the scheduler, the one client).

The 1-minute load average is printed with the figures (the machine may be shared; wall-clock
speed-ups under load mean little, CPU times are the robust figures). ``--json PATH`` writes
every figure; ``--quick`` runs a small version.
"""
from __future__ import annotations

import argparse
import functools
import math
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
sys.path.insert(0, str(REPO / "tests"))  # dask_cluster: the scheduler and workers as a user starts them

from bench_calibration import puma_problem  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402
from estcal.scale import run_tasks  # noqa: E402
from estcal.scale.runner import TRIM_THRESHOLD, WORKER_CONFIG  # noqa: E402  (the LocalCluster's own settings)

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


# ------------------------------------------------------------ a real cluster: dask scheduler + dask worker
def _proc_status(pid: int, key: str) -> float:
    """A /proc/PID/status memory line in MB (VmRSS: resident now; VmHWM: the peak since start)."""
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _cpu(pids) -> dict:
    import psutil

    out = {}
    for pid in pids:
        t = psutil.Process(pid).cpu_times()
        out[pid] = t.user + t.system
    return out


class Sampler:
    """Peak resident memory (MB) of some processes, sampled every ``dt`` seconds in a thread."""

    def __init__(self, pids: dict, dt: float = 0.2):
        import threading

        self.pids, self.dt, self.peak = dict(pids), dt, {k: 0.0 for k in pids}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        import psutil

        while not self._stop.is_set():
            for k, pid in self.pids.items():
                try:
                    self.peak[k] = max(self.peak[k], psutil.Process(pid).memory_info().rss / 2 ** 20)
                except psutil.Error:
                    pass
            self._stop.wait(self.dt)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()


#: the Dask settings of docs/scaling.md, for the scheduler, the nannies and the workers: no statistical
#: profiler (a thread sampling the running task every 10 ms) and the event loop's health check every
#: second instead of every 20 ms (each check takes the GIL from the running task: 2 ms of a worker's
#: CPU per robot and ~15 % slower robots with the 20 ms default, measured on an idle machine), and the nanny's
#: memory monitor every second instead of every 100 ms (an idle scheduler with two workers and their nannies:
#: 1.03 → 0.54 s of CPU in 30 s), and glibc's trim threshold at 32 MiB instead of the 64 kB a nanny gives its
#: worker (at 64 kB a robot's freed arrays go back to the system and are faulted in again: 8–14 % more CPU per
#: robot, measured in one process with and without it; the nanny takes the variable from its environment)
WORKER_ENV = {**{"DASK_" + k.upper().replace(".", "__").replace("-", "_"): str(v) for k, v in WORKER_CONFIG.items()},
              "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD)}


def estcal_cmd(*args, out: Path, sample: dict | None = None) -> dict:
    """Run ``estcal ARGS`` as a user does (its own process); wall time, the process's CPU time and peak
    RSS (``wait4``), its stdout; with ``sample`` ({name: pid}), the peak RSS of those processes too."""
    import subprocess

    cmd = [sys.executable, "-m", "estcal.cli.main", *map(str, args)]
    l0 = load()
    t = time.perf_counter()
    with open(out, "w") as fh:
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env={**os.environ, "COLUMNS": "160"})
        pids = {"client": p.pid, **(sample or {})}
        with Sampler(pids) as smp:
            _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t
    text = out.read_text()
    if p.returncode != 0:
        raise RuntimeError(f"estcal {' '.join(map(str, args))} exited {p.returncode}:\n{text[-3000:]}")
    return {"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "max_rss_mb": ru.ru_maxrss / 1024,
            "peak_rss_mb": smp.peak, "load": max(l0, load()), "output": text}


def _rows(results: Path) -> dict:
    import json

    return {p.stem: json.loads(p.read_text())["row"] for p in results.glob("*.json")}


def _disk(folder: Path) -> tuple[int, int]:
    """(bytes of the files, bytes of disk they occupy) under ``folder``."""
    files = [f.stat() for f in folder.rglob("*") if f.is_file()]
    return sum(st.st_size for st in files), sum(st.st_blocks * 512 for st in files)


def _summary(path: Path) -> dict:
    import json

    return json.loads(path.read_text())


def _first_line(text: str) -> str:
    return next((ln for ln in text.splitlines() if ln.startswith("estcal fleet")), text.splitlines()[0])


def bench_cluster(robots: int, serial_robots: int, workers: int, noop: int, tmp: Path, profiler: bool = False,
                  repeats: int = 1) -> dict:
    """``estcal fleet DIR --scheduler tcp://…`` on a real cluster: ``dask scheduler`` + ``workers`` ×
    ``dask worker --nthreads 1`` (with their nannies, as a user starts them) on the loopback interface."""
    import math

    from dask_cluster import LoopbackCluster

    from estcal.workflows.fleet import ROBOTS_PER_TASK

    big, small, warm = tmp / f"fleet{robots}", tmp / f"fleet{serial_robots}", tmp / "warm"
    for n, d in ((serial_robots, small), (2 * workers, warm), (robots, big)):
        sim = estcal_cmd("simulate", "--fleet", n, "--on-demand", "--out", d, "--seed", 1, out=tmp / "sim.txt")
    out = {"robots": robots, "serial_robots": serial_robots, "workers": workers, "poses": 50, "profiler": profiler,
           "robots_per_task": ROBOTS_PER_TASK, "description_bytes": _disk(big)[0],
           "simulate_output": sim["output"].strip()}
    # the same robots as folders (what --on-demand saves): measured on 20 robots
    estcal_cmd("simulate", "--fleet", 20, "--out", tmp / "files", "--seed", 1, out=tmp / "files.txt")
    out["folder_fleet_disk_bytes_per_robot"] = _disk(tmp / "files")[1] / 20
    print(out["simulate_output"])
    # the command's fixed cost (start-up, imports, a few robots), subtracted from the per-robot CPU figures
    w = estcal_cmd("fleet", warm, "--results", tmp / "r_warm_serial", out=tmp / "warm_serial.txt")
    out["command_fixed"] = {"cpu_s": w["cpu_s"], "max_rss_mb": w["max_rss_mb"], "wall_s": w["wall_s"]}
    s = estcal_cmd("fleet", small, "--results", tmp / "r_serial", "--json", tmp / "serial.json",
                   out=tmp / "serial.txt")
    out["serial"] = {k: v for k, v in s.items() if k != "output"}
    out["serial"].update(line=_first_line(s["output"]), run_s=_summary(tmp / "serial.json")["wall_s"],
                         cpu_ms_per_robot=1e3 * (s["cpu_s"] - w["cpu_s"]) / (serial_robots - 2 * workers))
    print(f"serial, {serial_robots:,} robots: {s['wall_s']:.1f} s (the run {out['serial']['run_s']:.1f} s: "
          f"{1e3 * out['serial']['run_s'] / serial_robots:.1f} ms per robot; CPU {out['serial']['cpu_ms_per_robot']:.1f} "
          f"ms per robot; load {s['load']})\n  {out['serial']['line']}")
    t = time.perf_counter()
    env = {} if profiler else WORKER_ENV
    with LoopbackCluster(workers, nanny=True, env=env) as cl:
        out["cluster_start_s"] = time.perf_counter() - t
        pids = cl.worker_pids()
        wpid = {f"worker{k}": pid for k, pid in enumerate(sorted(pids.values()))}
        import psutil

        nanny = {f"nanny{k}": psutil.Process(pid).ppid() for k, pid in enumerate(sorted(pids.values()))}
        out["worker_rss_idle_mb"] = {k: _proc_status(p, "VmRSS") for k, p in wpid.items()}
        out["nanny_rss_mb"] = {k: _proc_status(p, "VmRSS") for k, p in nanny.items()}
        w = estcal_cmd("fleet", warm, "--scheduler", cl.address, "--results", tmp / "r_warm", out=tmp / "warm.txt")
        out["warm_up_s"] = w["wall_s"]
        w = estcal_cmd("fleet", warm, "--scheduler", cl.address, "--results", tmp / "r_warm2", out=tmp / "warm.txt")
        out["client_fixed"] = {"cpu_s": w["cpu_s"], "max_rss_mb": w["max_rss_mb"], "wall_s": w["wall_s"]}
        out["worker_rss_warm_mb"] = {k: _proc_status(p, "VmRSS") for k, p in wpid.items()}
        c = estcal_cmd("fleet", small, "--scheduler", cl.address, "--results", tmp / "r_small", "--json",
                       tmp / "small.json", out=tmp / "small.txt")
        out["cluster_small"] = {k: v for k, v in c.items() if k != "output"}
        out["cluster_small"]["run_s"] = _summary(tmp / "small.json")["wall_s"]
        out["speedup"] = s["wall_s"] / c["wall_s"]
        out["speedup_run"] = out["serial"]["run_s"] / out["cluster_small"]["run_s"]
        out["identical_to_serial"] = _rows(tmp / "r_serial") == _rows(tmp / "r_small")
        print(f"cluster ({workers} workers), the same {serial_robots:,} robots: {c['wall_s']:.1f} s = "
              f"{out['speedup']:.2f}x serial (the runs alone: {out['cluster_small']['run_s']:.1f} s = "
              f"{out['speedup_run']:.2f}x; load {c['load']}); rows identical to serial: "
              f"{out['identical_to_serial']}\n  {_first_line(c['output'])}")
        # the scheduler's CPU when nothing runs (heartbeats), subtracted from its CPU per task
        c0, t0 = _cpu([cl.scheduler_pid()]), time.perf_counter()
        time.sleep(5.0)
        out["scheduler_idle_cpu_per_s"] = (_cpu([cl.scheduler_pid()])[cl.scheduler_pid()]
                                           - c0[cl.scheduler_pid()]) / (time.perf_counter() - t0)
        # the big run: every process's CPU, the workers' and the scheduler's memory
        watched = {**wpid, **nanny, "scheduler": cl.scheduler_pid()}
        cpu0 = _cpu(watched.values())
        b = estcal_cmd("fleet", big, "--scheduler", cl.address, "--results", tmp / "r_big", "--json",
                       tmp / "big.json", out=tmp / "big.txt", sample=watched)
        cpu1 = _cpu(watched.values())
        cpu = {k: cpu1[p] - cpu0[p] for k, p in watched.items()}
        n_tasks = math.ceil(robots / ROBOTS_PER_TASK)
        out["big"] = {k: v for k, v in b.items() if k != "output"}
        out["big"].update(
            line=_first_line(b["output"]), n_tasks=n_tasks, cpu_s=cpu,
            worker_peak_rss_mb={k: max(b["peak_rss_mb"][k], _proc_status(p, "VmHWM")) for k, p in wpid.items()},
            worker_cpu_ms_per_robot=1e3 * sum(cpu[k] for k in wpid) / robots,
            scheduler_cpu_ms_per_task=1e3 * max(0.0, cpu["scheduler"] - out["scheduler_idle_cpu_per_s"]
                                                * b["wall_s"]) / n_tasks,
            client_cpu_ms_per_robot=1e3 * (b["cpu_s"] - out["client_fixed"]["cpu_s"]) / robots,
            client_rss_mb_per_robot=max(0.0, b["max_rss_mb"] - out["client_fixed"]["max_rss_mb"]) / robots,
            run_s=_summary(tmp / "big.json")["wall_s"])
        r = estcal_cmd("fleet", big, "--scheduler", cl.address, "--results", tmp / "r_big", out=tmp / "rerun.txt")
        out["rerun"] = {"wall_s": r["wall_s"], "line": _first_line(r["output"])}
        out["results_disk"] = dict(zip(("bytes", "disk_bytes"), _disk(tmp / "r_big")))
        # the scheduler's cost per task: empty tasks, one per Dask task, from this process
        from distributed import Client

        with Client(cl.address) as client:
            run_tasks(noop, range(10), scheduler=client, chunksize=1, progress=False)
            _, tn, _, ln = timed(run_tasks, noop, range(noop), scheduler=client, chunksize=1, progress=False)
        out["noop_ms_per_task"], out["noop_load"] = 1e3 * tn / noop, ln
    bb = out["big"]
    out["speedup_throughput"] = (out["serial"]["run_s"] / serial_robots) / (bb["run_s"] / robots)
    print(f"cluster, {robots:,} robots x 50 poses ({n_tasks} tasks of {ROBOTS_PER_TASK}): {b['wall_s']:.1f} s "
          f"(load {b['load']}); {robots / b['wall_s']:.1f} robots/s: {out['speedup_throughput']:.2f}x the serial "
          f"run's robots/s\n  {bb['line']}")
    print(f"  workers: CPU {bb['worker_cpu_ms_per_robot']:.1f} ms per robot (serial {out['serial']['cpu_ms_per_robot']:.1f} "
          f"ms: CPU efficiency {out['serial']['cpu_ms_per_robot'] / bb['worker_cpu_ms_per_robot']:.2f}); peak RSS {', '.join(f'{v:.0f}' for v in bb['worker_peak_rss_mb'].values())} MB (idle after start "
          f"{', '.join(f'{v:.0f}' for v in out['worker_rss_idle_mb'].values())} MB, after the warm-up "
          f"{', '.join(f'{v:.0f}' for v in out['worker_rss_warm_mb'].values())} MB); nannies "
          f"{', '.join(f'{v:.0f}' for v in out['nanny_rss_mb'].values())} MB")
    print(f"  scheduler: CPU {bb['scheduler_cpu_ms_per_task']:.2f} ms per task (beyond its idle "
          f"{1e3 * out['scheduler_idle_cpu_per_s']:.1f} ms per s), peak RSS "
          f"{b['peak_rss_mb']['scheduler']:.0f} MB; empty tasks one per Dask task: {out['noop_ms_per_task']:.2f} ms "
          f"each (load {out['noop_load']})")
    print(f"  client (estcal fleet): CPU {bb['client_cpu_ms_per_robot']:.2f} ms per robot beyond its start-up "
          f"({out['client_fixed']['cpu_s']:.1f} s), peak RSS {b['max_rss_mb']:.0f} MB "
          f"({1e3 * bb['client_rss_mb_per_robot']:.1f} kB per robot); results {out['results_disk']['bytes'] / robots:.0f} B per robot "
          f"({out['results_disk']['disk_bytes'] / 2 ** 20:.0f} MB on disk for {robots:,}); as folders the fleet "
          f"would take {out['folder_fleet_disk_bytes_per_robot'] * robots / 2 ** 20:.0f} MB, its description "
          f"takes {out['description_bytes']} B")
    print(f"  rerun: {out['rerun']['wall_s']:.1f} s\n  {out['rerun']['line']}")
    print(f"  cluster start {out['cluster_start_s']:.1f} s; first run on fresh workers ({2 * workers} robots) "
          f"{out['warm_up_s']:.1f} s")
    # the speed-up again, serial and cluster alternated: this machine's speed drifts by several per cent over
    # minutes (two serial commands side by side once ran faster than one alone), so one pair is one sample
    out["pairs"] = [{"speedup": out["speedup"], "speedup_run": out["speedup_run"], "load": out["cluster_small"]["load"]}]
    for k in range(1, repeats):
        out["pairs"].append(_speedup_pair(k, small, warm, workers, env, tmp))
    sp = [q["speedup"] for q in out["pairs"]]
    sr = [q["speedup_run"] for q in out["pairs"]]
    out["speedup_median"], out["speedup_run_median"] = float(np.median(sp)), float(np.median(sr))
    if repeats > 1:
        print(f"speed-up over {repeats} alternated pairs (serial, then the cluster): commands "
              f"{', '.join(f'{v:.2f}x' for v in sp)} (median {out['speedup_median']:.2f}x); runs alone "
              f"{', '.join(f'{v:.2f}x' for v in sr)} (median {out['speedup_run_median']:.2f}x)")
    return out


def _speedup_pair(k: int, small: Path, warm: Path, workers: int, env: dict, tmp: Path) -> dict:
    """One more serial-then-cluster pair on the same robots: the serial command with no cluster running, then
    a fresh cluster (warmed up as above) and the same command on it."""
    from dask_cluster import LoopbackCluster

    s = estcal_cmd("fleet", small, "--results", tmp / f"r_serial{k}", "--json", tmp / f"serial{k}.json",
                   out=tmp / "serial.txt")
    with LoopbackCluster(workers, nanny=True, env=env) as cl:
        for j in range(2):
            estcal_cmd("fleet", warm, "--scheduler", cl.address, "--results", tmp / f"r_warm{k}_{j}",
                       out=tmp / "warm.txt")
        c = estcal_cmd("fleet", small, "--scheduler", cl.address, "--results", tmp / f"r_small{k}", "--json",
                       tmp / f"small{k}.json", out=tmp / "small.txt")
    return {"speedup": s["wall_s"] / c["wall_s"],
            "speedup_run": _summary(tmp / f"serial{k}.json")["wall_s"] / _summary(tmp / f"small{k}.json")["wall_s"],
            "serial_wall_s": s["wall_s"], "cluster_wall_s": c["wall_s"], "load": max(s["load"], c["load"]),
            "identical_to_serial": _rows(tmp / f"r_serial{k}") == _rows(tmp / f"r_small{k}")}


def projection_measured(c: dict, robots: int = 100_000, workers=(2, 10, 100, 1000)) -> dict:
    """Wall time of ``robots`` generated robots on N workers from the costs measured in :func:`bench_cluster`:
    the slowest of the workers' compute, the scheduler's CPU, and the one client's CPU (rows saved)."""
    b = c["big"]
    per_robot = b["worker_cpu_ms_per_robot"] / 1e3
    tasks = math.ceil(robots / c["robots_per_task"])
    client_rss_per_robot = b["client_rss_mb_per_robot"]
    rows = []
    for n in workers:
        limits = {"compute": robots * per_robot / n, "scheduler": tasks * b["scheduler_cpu_ms_per_task"] / 1e3,
                  "client": robots * b["client_cpu_ms_per_robot"] / 1e3}
        first = max(limits, key=limits.get)
        rows.append({"workers": n, "wall_s": limits[first], "bound_by": first,
                     **{f"{k}_s": v for k, v in limits.items()}})
    return {"robots": robots, "tasks": tasks, "cpu_s_per_robot": per_robot, "rows": rows,
            "worker_peak_rss_mb": max(b["worker_peak_rss_mb"].values()),
            "client_rss_mb": b["max_rss_mb"] + client_rss_per_robot * (robots - c["robots"]),
            "results_disk_mb": c["results_disk"]["disk_bytes"] / c["robots"] * robots / 2 ** 20}


def run_local(args, out) -> None:
    """The LocalCluster figures: PUMA calibrations, per-task overhead, memory, a 40-robot folder fleet."""
    from distributed import Client, LocalCluster

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


def print_projection(p: dict) -> None:
    print(f"projection from these measured costs, {p['robots']:,} robots x 50 poses generated on demand "
          f"({p['tasks']:,} tasks, {1e3 * p['cpu_s_per_robot']:.1f} ms of worker CPU per robot):")
    for r in p["rows"]:
        print(f"  {r['workers']:>5} workers: {r['wall_s']:>8.0f} s, bound by {r['bound_by']} (compute "
              f"{r['compute_s']:.0f} s, scheduler {r['scheduler_s']:.1f} s, client {r['client_s']:.0f} s)")
    print(f"  memory: {p['worker_peak_rss_mb']:.0f} MB per worker whatever the fleet size; the client "
          f"{p['client_rss_mb']:.0f} MB; results {p['results_disk_mb']:.0f} MB on disk")


def print_targets(c: dict, p: dict) -> None:
    """The figures the cluster benchmark is judged on, in one place, with the load they were measured at."""
    b = c["big"]
    rss = max(b["worker_peak_rss_mb"].values())
    print(f"figures (load average {c['cluster_small']['load']} during the speed-up, {b['load']} during the "
          f"{c['robots']:,}-robot run; wall-clock speed-ups only mean something on an idle machine):")
    n = len(c["pairs"])
    print(f"  speed-up {c['workers']} workers vs serial, {c['serial_robots']:,} robots"
          + (f", median of {n} alternated pairs" if n > 1 else "") + f": {c['speedup_median']:.2f}x (commands), "
          f"{c['speedup_run_median']:.2f}x (runs alone); {c['speedup_throughput']:.2f}x from the {c['robots']:,}-robot "
          f"run's robots/s — target >= 1.8x")
    print(f"  peak RSS per worker: {rss:.0f} MB — target <= 150 MB: {'met' if rss <= 150 else 'NOT met'}")
    print(f"  scheduler overhead per task ({c['robots_per_task']} robots): {b['scheduler_cpu_ms_per_task']:.2f} ms "
          f"of scheduler CPU; round trip of an empty task {c['noop_ms_per_task']:.2f} ms")
    print(f"  wall time for {c['robots']:,} robots: {b['wall_s']:.1f} s; projected {p['robots']:,} robots: "
          + ", ".join(f"{r['workers']} workers {r['wall_s']:.0f} s ({r['bound_by']})" for r in p["rows"]))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", type=int, default=10_000, help="robots of the cluster run (50 poses each)")
    ap.add_argument("--serial-robots", type=int, default=2_000,
                    help="robots run serially and on the cluster for the speed-up")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3, help="serial-then-cluster pairs for the speed-up, "
                    "alternated (the first pair before the big run, the others after it)")
    ap.add_argument("--noop", type=int, default=1000, help="empty tasks for the overhead figure")
    ap.add_argument("--dask-defaults", dest="profiler", action="store_true", help="start the scheduler and "
                    "workers with Dask's default settings (statistical profiler on, event-loop check every "
                    "20 ms) instead of those of docs/scaling.md")
    ap.add_argument("--project", type=int, default=100_000, help="robots of the projected fleet")
    ap.add_argument("--local", action="store_true", help="also the LocalCluster figures (PUMA calibrations, "
                    "overhead, a 40-robot folder fleet)")
    ap.add_argument("--n", type=int, default=200, help="PUMA calibrations (--local)")
    ap.add_argument("--fleet", type=int, default=40, help="robots of the folder fleet (--local)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.noop, args.fleet, args.robots, args.serial_robots, args.repeats = 20, 100, 6, 200, 60, 2
    out = {"environment": {"python": platform.python_version(), "cpus": os.cpu_count(),
                           "machine": platform.machine(), "load_start": list(os.getloadavg()),
                           "date": time.strftime("%Y-%m-%d %H:%M")}}
    print(f"{out['environment']['date']}, {os.cpu_count()} CPUs, load average at start "
          f"{', '.join(f'{v:.2f}' for v in os.getloadavg())} (1, 5, 15 min)")
    tmp = Path(tempfile.mkdtemp(prefix="estcal-bench-cluster-"))
    try:
        out["cluster"] = bench_cluster(args.robots, args.serial_robots, args.workers, args.noop, tmp,
                                       args.profiler, args.repeats)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out["projection"] = p = projection_measured(out["cluster"], robots=args.project)
    print_projection(p)
    print_targets(out["cluster"], p)
    if args.local:
        run_local(args, out)
    out["environment"]["load_end"] = list(os.getloadavg())
    print(f"load average at the end {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
    if args.json:
        write_json(args.json, out)
    return out


if __name__ == "__main__":
    main()
