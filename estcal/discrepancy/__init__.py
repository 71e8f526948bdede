"""What the simulation gets wrong: diagnose measured data, name the non-geometric cause,
extend the model and measure the gain (docs/discrepancy.md).

>>> from estcal.discrepancy import diagnose            # doctest: +SKIP
>>> res = diagnose(robot, data, validate=[data2], noise=2e-4)
>>> res.answer["expected_mm"], res.causes

See ``docs/discrepancy.md``.
"""
from .analysis import partial_joint_residuals, residual_analysis, residual_figures
from .diagnose import Candidate, Cause, DiagnosisResult, default_candidates, diagnose
from .geometric import fit_geometric, geometric_candidates, gravity_ready

__all__ = ["diagnose", "DiagnosisResult", "Cause", "Candidate", "default_candidates",
           "residual_analysis", "partial_joint_residuals", "residual_figures", "fit_geometric", "geometric_candidates",
           "gravity_ready"]
