"""Measurement methods (GECARO): residual rows + analytic Jacobian rows, and the Problem that stacks them."""
from .base import (METHODS, Method, NoiseModel, PointsMethod, PoseMethod, PositionMethod, Rows, get_method,
                   method_for_dataset, register_method)
from .problem import Problem, Term
from . import links  # noqa: F401,E402  (registers the GECARO link, plane and distance methods)

__all__ = ["Method", "NoiseModel", "Rows", "PositionMethod", "PoseMethod", "PointsMethod", "METHODS",
           "get_method", "register_method", "method_for_dataset", "Problem", "Term"]
