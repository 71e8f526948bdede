"""Simulated calibration datasets: true robot = nominal + parameter errors + effects,
poses from the textbook strategies S1–S4, measurement/joint noise and quantisation,
ground truth as JSON. See ``docs/simulation.md``."""
from estcal.methods.base import NoiseModel  # the one noise model (docs/conventions.md, "Noise")

from .core import (DEFAULT_EFFECT_STD, ErrorModel, SimulationResult, SimulationSummary, parse_effect_spec,
                   random_errors, simulate)
from .strategies import STRATEGIES, block_sizes, generate_poses

__all__ = ["simulate", "SimulationResult", "SimulationSummary", "NoiseModel", "ErrorModel", "random_errors",
           "parse_effect_spec", "generate_poses", "STRATEGIES", "block_sizes", "DEFAULT_EFFECT_STD"]
