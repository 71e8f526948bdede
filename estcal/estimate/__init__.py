"""Estimators: batch least squares (here), and the probabilistic/recursive backends."""
from .lsq import LSQ_METHODS, calibrate_lsq
from .registration import kabsch, register_base
from .result import CalibrationResult, accuracy, pose_errors

__all__ = ["calibrate_lsq", "CalibrationResult", "accuracy", "pose_errors", "LSQ_METHODS", "kabsch",
           "register_base"]
