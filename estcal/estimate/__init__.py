"""Estimators: batch least squares (here), and the probabilistic/recursive backends."""
from .lsq import LSQ_METHODS, UnidentifiableError, calibrate_lsq, check_identifiable
from .registration import kabsch, register_base
from .result import CalibrationResult, accuracy, pose_errors

__all__ = ["calibrate_lsq", "CalibrationResult", "accuracy", "pose_errors", "UnidentifiableError",
           "check_identifiable", "LSQ_METHODS", "kabsch", "register_base"]
