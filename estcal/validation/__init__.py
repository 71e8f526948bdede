"""Validation that cannot cheat: postures, posture-grouped folds, seen/new splits, the repeatability floor.

Layer 4 (docs/architecture.md): numpy/scipy and the rigid transforms of kinematics, no estimator.
Every cross-validation of estcal draws its folds from :func:`grouped_folds` so that the twin of a held-out row —
the same posture measured in another session or twice in one file — is never in training
(docs/real-data.md).
"""
from .postures import (DEFAULT_TOL_M, DEFAULT_TOL_RAD, extrapolation_distance, grouped_folds, inside_ranges,
                       joint_tolerances, n_postures, posture_groups, seen_postures)
from .repeatability import repeatability_floor
from .splits import rmse_mm, rmse_se_mm, seen_new_scores, validation_split

__all__ = ["DEFAULT_TOL_M", "DEFAULT_TOL_RAD", "extrapolation_distance", "grouped_folds", "inside_ranges",
           "joint_tolerances", "n_postures", "posture_groups", "seen_postures", "repeatability_floor", "rmse_mm",
           "rmse_se_mm", "seen_new_scores", "validation_split"]
