"""Identifiable (base) parameters by QR (GECARO Appendix III) and priorities (GECARO §1.5)."""
from .analysis import (expand_patterns, gecaro_priorities, gecaro_table2_priorities, identify, load_priorities, observation_matrix,
                       priorities_from_matrix, select_identifiable)
from .core import IdentifiabilityResult, format_relation, identifiable, resolve_priorities

__all__ = ["identifiable", "IdentifiabilityResult", "resolve_priorities", "format_relation", "identify",
           "gecaro_priorities", "priorities_from_matrix", "load_priorities", "observation_matrix",
           "select_identifiable", "expand_patterns", "gecaro_table2_priorities"]
