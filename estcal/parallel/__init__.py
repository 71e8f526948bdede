"""Parallel manipulators: Gough–Stewart platform model and calibration.

* :mod:`estcal.parallel.gough` — model (Models 36/42), IK, Jacobians, FK, robot files.
* :mod:`estcal.parallel.daney` — Daney's constrained-leg linear calibration.
* :mod:`estcal.parallel.simulate` — simulated data with the shared noise/error models.
* :mod:`estcal.parallel.calibration` — classical IK/FK-residual calibration
  (shared estimators through a Problem adapter), identifiability, CLI entry points.

CLI entry points: :func:`is_gough_file`, :func:`load_gough`,
:func:`load_gough_data`, :func:`calibrate_gough`, :func:`identifiable_gough`,
:func:`simulate_gough`.
"""
from .calibration import (  # noqa: F401
    GoughCalibrationResult,
    GoughData,
    GoughEstimationProblem,
    calibrate_gough,
    identifiable_gough,
    load_gough_data,
    simulate_gough_data,
)
from .simulate import GoughSimulation, simulate_gough  # noqa: F401
from .gough import FKResult, GoughPlatform, Workspace, is_gough_file, left_hand, load_gough  # noqa: F401
