"""Display units of parameters (mm for lengths, mrad for angles, dimensionless gains).

The one rule lives in :func:`estcal.cli.units.display_unit` (``docs/conventions.md``,
"Units on the command line"); the reports use the same function.
"""
from estcal.cli.units import display_unit

__all__ = ["display_unit"]
