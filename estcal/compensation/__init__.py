"""Compensation: corrected joint commands from a calibrated model (docs/compensation.md).

>>> from estcal.compensation import compensate        # doctest: +SKIP
>>> res = compensate("model.yaml", targets, q_start)  # doctest: +SKIP
>>> res.readings, res.reachable, res.error_mm, res.std_mm  # doctest: +SKIP
"""
from .core import CompensationResult, compensate, split_targets
from .solve import SolveResult, parameter_jacobian, propagate, solve_readings

__all__ = ["compensate", "CompensationResult", "split_targets", "solve_readings", "SolveResult",
           "parameter_jacobian", "propagate"]
