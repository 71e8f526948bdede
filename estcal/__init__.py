"""estcal: probabilistic and recursive estimation for robot kinematic calibration.

The Python API in a few names (docs/api.md)::

    import estcal
    robot = estcal.load_robot("puma560")                  # name, robot file, saved model or URDF
    data = estcal.load_dataset("train.csv", robot)        # CSV -> Dataset (or pass the path)
    result = estcal.calibrate(robot, data, estimator="lm", validate=["valid.csv"])
    print(result.parameter("a_2"))                        # (estimate, std), SI units
    diagnosis = estcal.diagnose(robot, data)              # which non-geometric effect, and the gain
    result.save_model("model.yaml")                       # reload with estcal.load_robot("model.yaml")

Names are resolved lazily (module ``__getattr__``), so ``import estcal`` imports no
numerical library; gtsam / filterpy / emcee load only when their estimator runs.
"""
from estcal.base.version import __version__

# public name -> "module:attribute", imported on first access
_API = {
    # robots and data
    "load_robot": "estcal.io.robotfile:load_robot",
    "save_robot": "estcal.io.robotfile:save_robot",
    "load_dataset": "estcal.io.dataset:load_dataset",
    "write_dataset": "estcal.io.dataset:write_dataset",
    "Dataset": "estcal.io.dataset:Dataset",
    "NoiseModel": "estcal.methods.base:NoiseModel",
    # the workflow
    "calibrate": "estcal.api:calibrate",
    "diagnose": "estcal.api:diagnose",
    "OnlineCalibrator": "estcal.workflows.online:OnlineCalibrator",
    "CalibrationResult": "estcal.estimate.result:CalibrationResult",
    "DiagnosisResult": "estcal.discrepancy.diagnose:DiagnosisResult",
    "estimator_names": "estcal.estimate.registry:estimator_names",
    "estimator_options": "estcal.estimate.registry:estimator_options",
    "calibration_covariance": "estcal.io.robotfile:calibration_covariance",
    # using a saved model (added by their work packages; one line each):
    "compensate": "estcal.compensation.core:compensate",
    "export_urdf": "estcal.kinematics.urdf_export:export_urdf",
    "export_ur_kinematics": "estcal.workflows.export:export_ur_kinematics",
}

__all__ = ["__version__", *_API]


def __getattr__(name):
    target = _API.get(name)
    if target is None:
        raise AttributeError(f"module 'estcal' has no attribute {name!r}")
    import importlib

    mod, attr = target.split(":")
    value = getattr(importlib.import_module(mod), attr)
    globals()[name] = value  # cache: later accesses skip __getattr__
    return value


def __dir__():
    return sorted(set(globals()) | set(_API))
