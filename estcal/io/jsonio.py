"""JSON output shared by the CLI, the experiments and the benchmarks.

Results are plain data: numpy arrays become lists, numpy scalars Python
numbers, dataclasses with ``to_dict()`` their dict, NaN/inf stay as JSON's
``NaN``/``Infinity`` (Python's json extension, readable by json.loads).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["to_jsonable", "write_json"]


def to_jsonable(v):
    """Recursively convert numpy / dataclass-like values to JSON-serialisable Python data."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
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
    """Write ``obj`` as indented JSON to ``path`` (parent folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(obj), indent=2))
    if announce:
        print(f"wrote {path}")
    return path
