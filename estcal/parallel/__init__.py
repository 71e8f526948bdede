"""Parallel manipulators: Gough–Stewart platform model and calibration.

* :mod:`estcal.parallel.gough` — model (Models 36/42), IK, Jacobians, FK, robot files.
* :mod:`estcal.parallel.daney` — Daney's constrained-leg linear calibration.
* :mod:`estcal.parallel.calibration` — classical IK/FK-residual calibration,
  identifiability, entry points for the CLI.
"""
from .gough import GoughPlatform, Workspace, FKResult, left_hand, load_gough, is_gough_file  # noqa: F401
