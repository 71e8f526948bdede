"""A calibration problem: one robot, one or more (method, dataset) terms, one noise model each.

:class:`Problem` owns the parameter vector the estimators iterate on — the
robot's parameters plus the unknowns the methods add (plane coefficients, …)
— and stacks every term's rows, weighted per row by its noise. Every
estimator in :mod:`estcal.estimate` (least squares, Kalman, factor graph,
MCMC) consumes a Problem, so they share residuals, Jacobians and names.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estcal.kinematics.parameters import ParameterVector

from .base import Method, NoiseModel, Rows, get_method, method_for_dataset

__all__ = ["Term", "Problem"]


@dataclass
class Term:
    method: Method
    data: object  # estcal.io.dataset.Dataset
    noise: NoiseModel


class Problem:
    """Robot + measurement terms.

    Parameters
    ----------
    robot : SerialRobot (its ``params.free`` mask is the default free set).
    terms : list of ``(method, dataset[, noise])``; ``method`` may be a name or
        a :class:`Method`, or ``None`` to infer it from the dataset's columns.
    noise : default :class:`NoiseModel` for terms without one.

    Attributes
    ----------
    robot : the robot with the methods' extra unknowns appended to its parameters.
    params : its :class:`ParameterVector` (names, values, free mask).
    """

    def __init__(self, robot, terms, noise: NoiseModel | None = None):
        noise = noise or NoiseModel()
        built = []
        for t in terms:
            if isinstance(t, Term):
                built.append(t)
                continue
            method, data, *rest = t
            if method is None:
                method = method_for_dataset(data, robot)
            elif isinstance(method, str):
                method = get_method(method)
            built.append(Term(method, data, rest[0] if rest and rest[0] is not None else noise))
        extra_names, extra_values = [], []
        for t in built:
            for name, value in t.method.extra_parameters(robot, t.data):
                if name not in extra_names and name not in robot.params:
                    extra_names.append(name)
                    extra_values.append(value)
        if extra_names:
            robot = robot.copy(robot.params.extend(extra_names, extra_values, kind="other"))
        self.robot = robot
        self.terms = built

    @property
    def params(self) -> ParameterVector:
        return self.robot.params

    def evaluate(self, theta=None, jacobian: bool = True) -> Rows:
        """Stacked rows of all terms at the full parameter vector ``theta``."""
        theta = self.params.values if theta is None else np.asarray(theta, float)
        return Rows.concatenate([t.method.rows(self.robot, theta, t.data, t.noise, jacobian)
                                 for t in self.terms])

    def evaluate_many(self, thetas) -> np.ndarray:
        """Residuals ``e`` (W, M) at every row of ``thetas`` (W, P), rows ordered as :meth:`evaluate`.

        The classical methods (position, pose, points) use one batched kinematics
        call per term for all W vectors — effects included
        (:meth:`estcal.kinematics.chain.SerialRobot.kinematics` with θ (W, P));
        other methods are evaluated θ by θ (:meth:`Method.residuals_many`)."""
        TH = np.atleast_2d(np.asarray(thetas, float))

        def term(t):
            if hasattr(t.method, "residuals_many"):
                return t.method.residuals_many(self.robot, TH, t.data)
            # a duck-typed method (not a Method subclass): θ by θ
            return np.stack([t.method.rows(self.robot, th, t.data, t.noise, False).e for th in TH])

        return np.concatenate([term(t) for t in self.terms], axis=1)

    def with_free(self, names) -> "Problem":
        """Copy whose free set is exactly ``names`` (patterns allowed)."""
        new = Problem.__new__(Problem)
        new.robot = self.robot.copy(self.robot.params.with_free(names))
        new.terms = self.terms
        return new

    def with_values(self, theta) -> "Problem":
        new = Problem.__new__(Problem)
        new.robot = self.robot.with_values(theta)
        new.terms = self.terms
        return new

    def __repr__(self) -> str:
        ts = ", ".join(f"{t.method.name}:{t.data.n}" for t in self.terms)
        return f"Problem({self.robot.name!r}, terms=[{ts}], {len(self.params)} parameters, " \
               f"{int(self.params.free.sum())} free)"
