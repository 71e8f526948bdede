"""estcal: probabilistic and recursive estimation for robot kinematic calibration."""
__version__ = "0.1.0"
