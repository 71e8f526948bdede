"""A real Dask cluster on this machine, started as a user starts one: ``dask scheduler`` and
``dask worker`` processes talking TCP on the loopback interface (tests/test_fleet_cluster.py,
benchmarks/bench_scale.py).

    with LoopbackCluster(2) as cl:          # scheduler + 2 workers, one thread each
        cl.address                          # tcp://127.0.0.1:PORT, for --scheduler
        cl.worker_pids()                    # {worker address: pid of the worker process}

Only the processes it started are stopped, by their own handles.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["LoopbackCluster"]


class LoopbackCluster:
    """``dask scheduler`` + ``n_workers`` × ``dask worker --nthreads 1`` on 127.0.0.1.

    nanny : start each worker under a nanny (``dask worker``'s default, which restarts a worker
        that died); ``False`` (``--no-nanny``): a killed worker stays dead.
    env : extra environment variables of the processes (e.g. Dask configuration).
    """

    def __init__(self, n_workers: int = 2, nanny: bool = False, env: dict | None = None, timeout: float = 120.0):
        self.n_workers, self.nanny, self.timeout = n_workers, nanny, timeout
        self.env = {**os.environ, **(env or {})}
        self.dir = Path(tempfile.mkdtemp(prefix="estcal-dask-"))
        self.procs: list[subprocess.Popen] = []
        self.address = None
        self.client = None

    def _start(self, *args, log: str) -> subprocess.Popen:
        fh = open(self.dir / log, "w")
        p = subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=fh, stderr=subprocess.STDOUT,
                             env=self.env, cwd=self.dir)
        fh.close()
        self.procs.append(p)
        return p

    def __enter__(self):
        from distributed import Client

        sfile = self.dir / "scheduler.json"
        try:
            self.scheduler = self._start("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                         "--scheduler-file", str(sfile), log="scheduler.log")
            t0 = time.monotonic()
            while not sfile.is_file() or not sfile.read_text().strip():
                if self.scheduler.poll() is not None or time.monotonic() - t0 > self.timeout:
                    raise RuntimeError(f"dask scheduler did not start:\n{self.log('scheduler.log')}")
                time.sleep(0.05)
            self.address = json.loads(sfile.read_text())["address"]
            self.workers = [self.start_worker(i) for i in range(self.n_workers)]
            self.client = Client(self.address, timeout="30s")
            self.client.wait_for_workers(self.n_workers, timeout=self.timeout)
        except BaseException:
            self.close()
            raise
        return self

    def start_worker(self, i: int) -> subprocess.Popen:
        return self._start("worker", self.address, "--nthreads", "1", "--no-dashboard", "--name", f"w{i}",
                           "--nanny" if self.nanny else "--no-nanny", "--local-directory", str(self.dir / f"w{i}"),
                           log=f"worker{i}.log")

    def log(self, name: str) -> str:
        try:
            return (self.dir / name).read_text()[-3000:]
        except OSError:
            return ""

    def worker_pids(self) -> dict:
        """``{worker address: pid}`` of the worker processes (under a nanny, the nanny's child)."""
        return self.client.run(os.getpid)

    def scheduler_pid(self) -> int:
        return self.scheduler.pid

    def close(self):
        if self.client is not None:
            self.client.close()
            self.client = None
        for p in reversed(self.procs):  # workers first, then the scheduler
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    def __exit__(self, *exc):
        self.close()
        return False
