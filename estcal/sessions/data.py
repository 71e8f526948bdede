"""Sessions in data: several files (one per session) or one file with a ``session`` column."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["stack_sessions", "split_sessions", "session_name"]


def session_name(data, i: int) -> str:
    """A readable session name: the file's stem, else ``session<i+1>``."""
    return Path(data.path).stem if getattr(data, "path", None) else f"session{i + 1}"


def stack_sessions(datasets, names=None):
    """One Dataset holding every session's rows, with a ``session`` column (0, 1, …).

    Context and extra columns present in every session are kept; time ``t`` is kept as
    recorded (per-session time is the caller's choice). Each row keeps its CSV line.
    """
    from estcal.io.dataset import Dataset

    if not datasets:
        raise ValueError("stack_sessions needs at least one dataset")
    kinds = {d.kind for d in datasets}
    if len(kinds) != 1:
        raise ValueError(f"sessions of different kinds cannot be stacked: {sorted(kinds)}")
    jn = list(datasets[0].joint_names)
    for d in datasets[1:]:
        if list(d.joint_names) != jn:
            raise ValueError(f"{d.where}: joints {d.joint_names} differ from the first session's {jn}")

    def cat(attr):
        vals = [getattr(d, attr) for d in datasets]
        return None if any(v is None for v in vals) else np.concatenate(vals)

    common = lambda attr: set.intersection(*[set(getattr(d, attr)) for d in datasets])  # noqa: E731
    ctx = {k: np.concatenate([d.context[k] for d in datasets]) for k in sorted(common("context"))}
    cols = {k: np.concatenate([d.columns[k] for d in datasets]) for k in sorted(common("columns"))}
    cols["session"] = np.concatenate([np.full(d.n, i, float) for i, d in enumerate(datasets)])
    names = list(names or [session_name(d, i) for i, d in enumerate(datasets)])
    out = Dataset(jn, cat("readings"), datasets[0].kind, cat("points"), cat("R"), cat("p"), ctx, cols,
                  np.concatenate([d.lines for d in datasets]), " + ".join(d.where for d in datasets))
    out.warnings = [w for d in datasets for w in d.warnings]
    out.session_names = names
    out.sessions = list(datasets)  # the parts, for provenance (a saved model lists every file)
    return out


def split_sessions(data):
    """The sessions of a dataset with a ``session`` column (in order of first appearance); a
    dataset without one is a single session."""
    if "session" not in data.columns:
        return [data]
    s = np.asarray(data.columns["session"])
    if not np.all(np.isfinite(s)):
        bad = int(np.flatnonzero(~np.isfinite(s))[0])
        raise ValueError(f"{data.where}, line {int(data.lines[bad])}: the 'session' column is empty")
    _, first = np.unique(s, return_index=True)
    out = []
    for v in s[np.sort(first)]:
        part = data.subset(s == v)
        part.columns.pop("session", None)
        out.append(part)
    return out
