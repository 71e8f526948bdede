"""Experiment design for calibration: criteria, optimal plans, sequential next-pose selection.

* :mod:`estcal.design.criteria` — condition numbers, observability indices O1–O5,
  D/A/E/G, Klimchik's test-pose criterion, accuracy maps (vectorised over plans);
* :mod:`estcal.design.model` — :class:`DesignModel` (robot + method + noise + prior →
  Jacobian blocks and information matrices), identifiable subsets, workspace constraints;
* :mod:`estcal.design.plans` — greedy / Fedorov / DETMAX, continuous multi-start,
  replication, random-plan baselines;
* :mod:`estcal.design.update` — Woodbury (Kalman) covariance updates for candidates;
* :mod:`estcal.design.sequential` — next-pose proposal and the active calibration loop;
* :mod:`estcal.design.montecarlo` — Monte-Carlo check of a plan's predicted accuracy.
"""
from .criteria import (CRITERIA, AccuracyMap, PlanCriteria, accuracy_map, covariance, criterion_value,
                       evaluate_all, information_matrix, test_pose_criterion)
from .model import DesignModel, ToolBox, identifiable_subset, resolve_robot
from .montecarlo import MonteCarloResult, monte_carlo_test_pose_error
from .plans import (BaselineStats, Plan, detmax, evaluate_plan, fedorov_exchange, greedy, load_candidates,
                    optimise_continuous, optimise_discrete, random_baseline, random_candidates, replicate)
from .sequential import ActiveRun, CalibrationState, NextPose, active_calibration, kalman_update, propose_next_pose
from .update import woodbury_covariance

__all__ = ["CRITERIA", "AccuracyMap", "PlanCriteria", "accuracy_map", "covariance", "criterion_value",
           "evaluate_all", "information_matrix", "test_pose_criterion", "DesignModel", "ToolBox",
           "identifiable_subset", "resolve_robot", "MonteCarloResult", "monte_carlo_test_pose_error",
           "BaselineStats", "Plan", "detmax", "evaluate_plan", "fedorov_exchange", "greedy", "load_candidates",
           "optimise_continuous", "optimise_discrete", "random_baseline", "random_candidates", "replicate",
           "ActiveRun", "CalibrationState", "NextPose", "active_calibration", "kalman_update",
           "propose_next_pose", "woodbury_covariance"]
