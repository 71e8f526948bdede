"""Run many independent tasks serially, on local processes or on a Dask cluster — same results.

This is a thin layer over :mod:`concurrent.futures` and :mod:`dask.distributed`,
not a scheduler of our own. :func:`run_tasks` calls ``fn(task)`` (or
``fn(task, seed)``) for every task and returns a :class:`RunResult`: the values
in task order and a :class:`TaskFailure` (index, short repr of the inputs,
error, traceback) for each task that raised — one failing task never stops the
others.

Schedulers (``scheduler=`` argument, ``--scheduler`` CLI option):

* ``"serial"`` — a loop in this process;
* ``"processes"`` — a :class:`concurrent.futures.ProcessPoolExecutor`;
* ``"local"`` — a :class:`dask.distributed.LocalCluster` started for the call
  (one thread per worker process) and closed afterwards;
* ``"tcp://host:8786"`` (any Dask address) — an existing cluster;
* a :class:`dask.distributed.Client` or any :class:`concurrent.futures.Executor`
  — used as is and left open (reuse one cluster for many calls).

Reproducibility: results never depend on which worker ran a task or in which
order. With ``seed=`` each task gets its own ``numpy.random.SeedSequence``
child, ``SeedSequence(seed).spawn(n)[i]`` for task ``i``, passed as ``fn``'s
second argument; the same seed gives bit-identical results on every scheduler
(``tests/test_scale.py``).

Every task runs with single-threaded BLAS, whatever the scheduler (same
numbers; no oversubscription of the cores by BLAS threads).

Overhead: tasks travel in *chunks* (a list of tasks per submitted job; by
default about eight chunks per worker), so a per-task cost of a few
milliseconds is not swamped by the scheduler's per-job cost (measured in
docs/scaling.md).

``fn`` must be picklable for the process and Dask schedulers (a module-level
function, or a :func:`functools.partial` of one).
"""
from __future__ import annotations

import contextlib
import math
import os
import time
import traceback
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from estcal.base.blas import single_thread_blas
from estcal.base.errors import EstcalError
from estcal.base.progress import nested

__all__ = ["SCHEDULERS", "TaskFailure", "TaskError", "RunResult", "run_tasks", "task_seeds",
           "check_scheduler", "short_repr"]

SCHEDULERS = ("serial", "processes", "local")

#: glibc's ``MALLOC_TRIM_THRESHOLD_`` for the workers of a LocalCluster (bytes; docs/scaling.md)
TRIM_THRESHOLD = 32 * 2 ** 20
#: the Dask settings of a LocalCluster's processes (docs/scaling.md; the benchmark's cluster takes them as
#: ``DASK_…`` environment variables)
WORKER_CONFIG = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "1s",
                 "distributed.worker.memory.monitor-interval": "1s"}


def short_repr(x, limit: int = 80) -> str:
    """A one-line repr of a task's inputs, cut to ``limit`` characters."""
    try:
        r = repr(x)
    except Exception:  # noqa: BLE001 - a broken __repr__ must not hide the task's real error
        r = f"<{type(x).__name__}>"
    r = " ".join(r.split())
    return r if len(r) <= limit else r[: limit - 1] + "…"


@dataclass
class TaskFailure:
    """A task that raised: its position, its inputs (short repr), the error and the traceback."""

    index: int
    inputs: str
    error: str
    traceback: str = field(default="", repr=False)

    def __str__(self) -> str:
        return f"task {self.index} ({self.inputs}): {self.error}"

    def to_dict(self) -> dict:
        return {"index": self.index, "inputs": self.inputs, "error": self.error}


class TaskError(EstcalError, RuntimeError):
    """Raised by :meth:`RunResult.values` when some tasks failed; lists them."""

    def __init__(self, failures: list[TaskFailure]):
        self.failures = failures
        lines = [str(f) for f in failures[:5]] + ([f"… and {len(failures) - 5} more"] if len(failures) > 5 else [])
        super().__init__(f"{len(failures)} task(s) failed:\n  " + "\n  ".join(lines))


@dataclass
class RunResult:
    """Outcome of :func:`run_tasks`, in task order.

    results : the value of each task (``None`` where the task failed)
    failures : one :class:`TaskFailure` per failed task, by index
    scheduler : what ran the tasks; ``n_workers``; ``wall_s`` wall-clock seconds of the run
    """

    results: list
    failures: list
    scheduler: str
    n_workers: int
    wall_s: float

    @property
    def ok(self) -> bool:
        return not self.failures

    @property
    def failed(self) -> set:
        return {f.index for f in self.failures}

    def values(self) -> list:
        """Every task's value; raises :class:`TaskError` naming the failed tasks if any failed."""
        if self.failures:
            raise TaskError(self.failures)
        return list(self.results)

    def __len__(self) -> int:
        return len(self.results)


def task_seeds(seed, n: int) -> list:
    """``SeedSequence(seed).spawn(n)``: one independent stream per task, fixed by its index."""
    return np.random.SeedSequence(seed).spawn(n)


def check_scheduler(scheduler) -> None:
    """Raise ``ValueError`` with the accepted values unless ``scheduler`` is one of them."""
    if scheduler is None or isinstance(scheduler, Executor) or hasattr(scheduler, "submit"):
        return
    if isinstance(scheduler, str) and (scheduler in SCHEDULERS or "://" in scheduler):
        return
    raise ValueError(f"unknown scheduler {scheduler!r}: use serial, processes, local (a Dask LocalCluster) "
                     f"or the address of a running Dask scheduler, e.g. tcp://host:8786")


# ----------------------------------------------------------------- worker side
def _run_one(fn, index, task, seed):
    try:
        return True, (fn(task) if seed is None else fn(task, seed))
    except Exception as exc:  # noqa: BLE001 - every task error is reported, not raised
        msg = f"{type(exc).__name__}: {exc}".strip()
        return False, TaskFailure(index, short_repr(task), msg.splitlines()[0] if msg else type(exc).__name__,
                                  traceback.format_exc())


def _run_chunk(fn, chunk):
    """Run a chunk ``[(index, task, seed), …]``; module level so that every pool can pickle it.

    BLAS runs single-threaded on every scheduler: a worker process is one core's
    worth of work, the result does not depend on BLAS's thread count (its
    reductions' order), and OpenBLAS's spinning threads do not slow a serial run
    on a busy machine (the serial fleet ran 4× slower with them, docs/scaling.md).
    Progress bars inside a task stay quiet (the runner's own bar counts the tasks)."""
    with single_thread_blas(), nested():
        return _run_items(fn, chunk)


def _run_items(fn, chunk):
    return [(i,) + _run_one(fn, i, t, s) for i, t, s in chunk]


# ----------------------------------------------------------------- client side
def _progress(total, desc, progress):
    if not progress:
        return None
    from estcal.base.progress import progress as bar

    # "auto": only on a terminal's stderr, not in CI, not inside another bar (estcal.base.progress)
    return bar(total=total, desc=desc or "tasks", unit="task", enabled=None if progress == "auto" else True)


def _default_workers(scheduler) -> int:
    return max(1, min(os.cpu_count() or 1, 2 if scheduler == "local" else os.cpu_count() or 1))


def run_tasks(fn: Callable, tasks: Sequence, *, scheduler="serial", seed=None, n_workers: int | None = None,
              chunksize: int | None = None, max_chunksize: int | None = None, progress="auto",
              desc: str | None = None, on_done: Callable | None = None) -> RunResult:
    """Run ``fn`` on every task; a failing task is reported, not raised.

    Parameters
    ----------
    fn : ``fn(task)`` or, with ``seed``, ``fn(task, seed_sequence)``.
    tasks : the inputs, one per task (small objects: they are pickled to the workers).
    scheduler : ``"serial"`` | ``"processes"`` | ``"local"`` | a Dask address | a Dask
        ``Client`` or ``concurrent.futures.Executor`` (see the module docstring).
    seed : int, SeedSequence or None — with a seed, task ``i`` receives
        ``SeedSequence(seed).spawn(len(tasks))[i]``.
    n_workers : workers of the pool or LocalCluster (default: the CPU count; 2 for ``local``).
    chunksize : tasks per submitted job (default ``ceil(n / (8 · workers))``; 1 = one job per task).
    max_chunksize : upper bound of the default ``chunksize`` (results then arrive, and a lost worker's
        work is redone, in pieces of at most this many tasks).
    progress : ``"auto"`` (a tqdm bar on a terminal's stderr only), True or False.
    on_done : ``on_done(index, value, failure)`` called in this process for every task as its chunk
        arrives (in completion order, each task once): ``value`` is the task's value and ``failure``
        ``None``, or ``value`` is ``None`` and ``failure`` its :class:`TaskFailure` — e.g. to save
        each result as it arrives.

    A Dask worker lost during the run (killed, out of memory) is Dask's business: the scheduler
    reruns its tasks on the other workers, and their result arrives once; a chunk during which more
    than ``distributed.scheduler.allowed-failures`` workers (default 3) died (``KilledWorker``: a
    task that kills every worker it runs on) reports its tasks as failures, "not run (…)".
    """
    check_scheduler(scheduler)
    tasks = list(tasks)
    n = len(tasks)
    seeds = task_seeds(seed, n) if seed is not None else [None] * n
    items = list(zip(range(n), tasks, seeds))
    t0 = time.perf_counter()
    results: list[Any] = [None] * n
    failures: dict[int, TaskFailure] = {}

    def collect(out):
        for i, ok, v in out:
            if ok:
                results[i] = v
            else:
                failures[i] = v
            if on_done is not None:
                on_done(i, v if ok else None, None if ok else v)

    label = scheduler if isinstance(scheduler, str) else type(scheduler).__name__
    if scheduler in (None, "serial") or n == 0:

        bar = _progress(n, desc, progress)
        with single_thread_blas():  # as on the workers (see _run_chunk)
            for it in items:
                collect(_run_items(fn, [it]))
                if bar is not None:
                    bar.update(1)
        if bar is not None:
            bar.close()
        return RunResult(results, [failures[i] for i in sorted(failures)], "serial", 1, time.perf_counter() - t0)

    own = None
    client = executor = None
    try:
        if isinstance(scheduler, str):
            if scheduler == "processes":
                workers = n_workers or _default_workers(scheduler)
                own = executor = ProcessPoolExecutor(max_workers=workers)
            else:
                client, own = _dask_client(scheduler, n_workers)
                workers = len(client.nthreads()) or (n_workers or 1)
        elif hasattr(scheduler, "nthreads"):  # a dask Client
            client = scheduler
            workers = len(client.nthreads()) or 1
        else:
            executor = scheduler
            workers = n_workers or getattr(scheduler, "_max_workers", None) or os.cpu_count() or 1
        cs = chunksize or max(1, min(math.ceil(n / (8 * workers)), max_chunksize or n))
        chunks = [items[k:k + cs] for k in range(0, n, cs)]
        bar = _progress(n, desc, progress)
        if client is not None:
            from distributed import as_completed as dask_completed

            futs = {client.submit(_run_chunk, fn, c, pure=False): c for c in chunks}
            done_iter = dask_completed(list(futs))
        else:
            futs = {executor.submit(_run_chunk, fn, c): c for c in chunks}
            done_iter = as_completed(list(futs))
        for f in done_iter:
            chunk = futs.pop(f)  # released as it arrives: a worker keeps no result it has delivered
            try:
                out = f.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker or unpicklable task fails its chunk only
                msg = f"{type(exc).__name__}: {exc}".strip().splitlines()[0]
                out = [(i, False, TaskFailure(i, short_repr(t), f"not run ({msg})", "")) for i, t, _ in chunk]
            del f
            collect(out)
            if bar is not None:
                bar.update(len(chunk))
        if bar is not None:
            bar.close()
    finally:
        if own is not None:
            own.shutdown() if isinstance(own, Executor) else own.close()
    return RunResult(results, [failures[i] for i in sorted(failures)], label, int(workers),
                     time.perf_counter() - t0)


@contextlib.contextmanager
def _trim_threshold():
    """glibc's trim threshold for the workers a nanny is about to start (docs/scaling.md).

    A nanny passes ``MALLOC_TRIM_THRESHOLD_`` from its own process's environment before Dask's configuration,
    and writes Dask's value (65536) into that environment when it starts a worker — so after any LocalCluster
    of Dask's defaults in this process the configuration alone no longer reaches the workers. Here the
    variable is set for the start unless the user chose another value than Dask's, then restored."""
    var = "MALLOC_TRIM_THRESHOLD_"
    old = os.environ.get(var)
    if old not in (None, "65536"):  # the user's own choice
        yield
        return
    os.environ[var] = str(TRIM_THRESHOLD)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(var, None)
        else:
            os.environ[var] = old


class _OwnCluster:
    """A LocalCluster and its Client, closed together."""

    def __init__(self, cluster, client):
        self.cluster, self.client = cluster, client

    def close(self):
        self.client.close()
        self.cluster.close()


def _dask_client(scheduler: str, n_workers):
    try:
        from distributed import Client, LocalCluster
    except ImportError:  # the dask extra is not installed
        from estcal.base.errors import MissingExtraError

        raise MissingExtraError(f"scheduler {scheduler!r}", "dask", "dask.distributed") from None
    if scheduler == "local":
        import dask

        # one thread per process: the work is GIL-bound Python + small numpy calls; no
        # statistical profiler (a thread sampling the task's stack every 10 ms, half of
        # an idle worker's CPU), and the event loop's health check every second rather than
        # every 20 ms (each check takes the GIL from the running task), the nannies' memory monitor every second
        # rather than every 100 ms; glibc's trim threshold at 32 MiB instead of the 64 kB the nannies set (at 64 kB
        # every robot hands its freed arrays back to the system and faults them in again: 8–14 % more CPU per
        # robot) — docs/scaling.md
        with dask.config.set(WORKER_CONFIG), _trim_threshold():
            cluster = LocalCluster(n_workers=n_workers or _default_workers("local"), threads_per_worker=1,
                                   processes=True, dashboard_address=":0")
        client = Client(cluster)
        return client, _OwnCluster(cluster, client)
    client = Client(scheduler, timeout="10s")
    return client, client
