"""The column vocabulary of a dataset file (docs/dataset.md, "Columns"), and its error.

Shared by the dataset loader (:mod:`estcal.io.dataset`), which reads estcal's columns, and the
column maps (:mod:`estcal.io.columnmap`), which turn a publisher's columns into them: both
import it, neither imports the other's vocabulary.
"""
from __future__ import annotations

import re

from estcal.base.errors import InputError

__all__ = ["DatasetError", "CONTEXT_COLUMNS", "QUAT_COLUMNS", "POSE_COLUMNS", "METHOD_COLUMNS", "NUMBERED",
           "is_number"]

#: the context of a row passed to the non-geometric effects: time (s), temperature (°C), payload (kg)
CONTEXT_COLUMNS = ("t", "temperature", "payload")
#: a unit quaternion, scalar first
QUAT_COLUMNS = ("qw", "qx", "qy", "qz")
#: a full pose of the measured frame: its origin and its orientation
POSE_COLUMNS = ("x", "y", "z") + QUAT_COLUMNS
#: columns read by the measurement methods (docs/methods.md) and the TIAGo files' time window
METHOD_COLUMNS = ("group", "pair", "distance", "plane_a", "plane_b", "plane_c", "t_start_robot", "t_end_robot")
#: a coordinate of measured point k: ``x1``, ``y1``, ``z1``, ``x2`` …
NUMBERED = re.compile(r"^([xyz])(\d+)$")


class DatasetError(InputError):
    """A dataset problem; the message names the file, line and column."""


def is_number(text: str) -> bool:
    """True when ``text`` reads as a float (a header field that is a number: no header row)."""
    try:
        float(text)
    except ValueError:
        return False
    return True
