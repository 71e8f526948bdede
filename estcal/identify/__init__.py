"""Identifiable (base) parameters by QR (GECARO Appendix III) and priorities (GECARO §1.5).

:func:`select_identifiable` is the one entry for the identifiable set (:mod:`.select`);
:func:`identify` analyses a robot and a measurement method (:mod:`.analysis`); the priority rules
are :mod:`.priorities`; the rank scan and the named tolerances :mod:`.core`.
"""
from .analysis import identify
from .core import DATA_TOL, STRUCTURAL_TOL, format_relation, resolve_priorities
from .priorities import gecaro_priorities, gecaro_table2_priorities, load_priorities, priorities_from_matrix
from .select import (IdentifiabilityResult, Selection, UnidentifiableError, check_identifiable, expand_patterns,
                     identifiable, observation_matrix, select_identifiable)

__all__ = ["identifiable", "IdentifiabilityResult", "resolve_priorities", "format_relation", "identify",
           "gecaro_priorities", "priorities_from_matrix", "load_priorities", "observation_matrix",
           "select_identifiable", "Selection", "check_identifiable", "UnidentifiableError", "expand_patterns",
           "gecaro_table2_priorities", "STRUCTURAL_TOL", "DATA_TOL"]
