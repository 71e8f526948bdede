"""Repeatability across sessions: per-session parameter deviations as process noise.

Session s sees ``θ_s = θ + E u_s``, ``u_s ~ N(0, Q)`` on a chosen subset of the
parameters (joint offsets after re-homing, the base after the tracker moved, …).
:func:`fit_sessions` estimates θ, the sessions' deviations and Q (REML), solved
three agreeing ways (GLS, a gtsam factor graph, a filterpy filter with process
noise at the session boundaries); :func:`predict_session` scores a new session
against intervals that carry θ's covariance plus Q; :func:`update_session` and
:func:`recalibration_curve` answer "how many poses must I re-measure each
morning". See ``docs/repeatability.md``.
"""
from .fit import SessionFit, fit_sessions, session_problems
from .formulations import solve_factor_graph, solve_gls, solve_kalman
from .predict import choose_poses, coverage_band, predict_session, recalibration_curve, update_session
from .select import choose_vary
from .simulate import simulate_sessions
from .system import gls, reml, reml_objective

__all__ = ["SessionFit", "fit_sessions", "session_problems", "solve_gls", "solve_factor_graph", "solve_kalman",
           "predict_session", "coverage_band", "update_session", "choose_poses", "recalibration_curve",
           "choose_vary", "simulate_sessions", "gls", "reml", "reml_objective"]
