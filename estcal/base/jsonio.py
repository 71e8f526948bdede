"""JSON output shared by the CLI, the experiments and the benchmarks.

Results are plain data: numpy arrays become lists, numpy scalars Python
numbers, dataclasses with ``to_dict()`` their dict. The output is *strict* JSON
(RFC 8259) that every JSON reader accepts: NaN and ±inf (an undefined standard
deviation, an infinite criterion) are written as ``null`` — Python's ``NaN`` /
``Infinity`` extension is not JSON. Files are written atomically
(:mod:`estcal.base.atomic`): a crash leaves the old file or the new one, never half.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from .atomic import atomic_write_text

__all__ = ["to_jsonable", "write_json", "dumps"]


def to_jsonable(v):
    """Recursively convert numpy / dataclass-like values to JSON-serialisable Python data."""
    np = sys.modules.get("numpy")  # no numpy value can exist before numpy is imported (cheap start-up)
    if np is not None:
        if isinstance(v, np.ndarray):
            return to_jsonable(v.tolist()) if v.dtype.kind in "fcO" else v.tolist()
        if isinstance(v, (np.floating, np.integer, np.bool_)):
            v = v.item()
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): to_jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [to_jsonable(x) for x in v]
    if isinstance(v, Path):
        return str(v)
    if hasattr(v, "to_dict") and callable(v.to_dict):
        return to_jsonable(v.to_dict())
    return v


def write_json(path, obj, announce: bool = False) -> Path:
    """Write ``obj`` as indented strict JSON to ``path`` (atomically, parent folders
    created; non-finite numbers as ``null``); returns the path."""
    path = Path(path)
    atomic_write_text(path, json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n")
    if announce:
        print(f"wrote {path}")
    return path


def dumps(obj, **kw) -> str:
    """Strict JSON text of ``obj`` (see :func:`write_json`)."""
    return json.dumps(to_jsonable(obj), allow_nan=False, **kw)
