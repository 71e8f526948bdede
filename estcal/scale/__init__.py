"""Scaling out: many independent tasks (Monte Carlo, restarts, fleets) on processes or Dask.

* :mod:`estcal.scale.runner` — :func:`run_tasks`, one task runner for serial,
  process-pool and Dask execution with per-task seeds and reported failures;
* the fleet job itself is :mod:`estcal.workflows.fleet`, and a simulated fleet for tests and
  benchmarks (``estcal simulate --fleet N``) :mod:`estcal.simulate.fleet`.
"""
from .runner import SCHEDULERS, RunResult, TaskError, TaskFailure, check_scheduler, run_tasks, task_seeds

__all__ = ["SCHEDULERS", "RunResult", "TaskError", "TaskFailure", "check_scheduler", "run_tasks", "task_seeds"]
