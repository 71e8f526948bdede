"""Parallel manipulators: the Gough–Stewart platform model (layer 2, docs/parallel.md).

* :mod:`estcal.parallel.gough` — model (Models 36/42), IK, Jacobians, FK, robot files.
* :mod:`estcal.parallel.data` — measurements (poses + leg readings), their files, synthetic data.
* :mod:`estcal.parallel.residuals` — IK/FK residuals, per-pose noise covariance, analytic Jacobians.
* :mod:`estcal.parallel.daney` — Daney's constrained-leg linear calibration.

Calibration, identifiability and simulation run in :mod:`estcal.workflows.gough` (the shared
estimators of :mod:`estcal.estimate` on :class:`~estcal.parallel.residuals.GoughResiduals`).
"""
from .data import GoughData, load_gough_data, simulate_gough_data  # noqa: F401
from .gough import FKResult, GoughPlatform, Workspace, is_gough_file, left_hand, load_gough  # noqa: F401
from .residuals import GoughResiduals  # noqa: F401
