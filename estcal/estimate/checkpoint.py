"""Checkpoints of a recursive (Kalman) calibration, so a killed ``estcal online`` loses nothing.

A checkpoint is one JSON file written atomically (:mod:`estcal.io.atomic`: temp file,
fsync, rename — a ``kill -9`` at any instant leaves the previous complete checkpoint or the
new one). It holds everything the next filter step depends on, so that a resumed run
performs exactly the same floating-point operations as an uninterrupted one and ends with
bit-identical estimates and covariance (``tests/test_online_checkpoint.py``):

* the filter: ``estimate`` (x), ``covariance`` (P), ``Q``, the noise stds that build R,
  the full parameter vector the fixed parameters take (``theta0``);
* the position in the input: data rows processed, last CSV line, bytes consumed and the
  SHA-256 of those bytes (``input_sha256_prefix``) plus the SHA-256 of the whole input file
  when the run started (``input_sha256``);
* the options that change the estimates (robot, free set, q, filter, method, noise, prior);
* the innovation record (NIS, dimensions, whitened innovations), the burn-in and the printed
  history, so the final innovation tests and JSON match too.

JSON floats are written with Python's shortest round-trip repr, so x and P come back
bit for bit. ``parameters`` / ``estimate`` / ``covariance`` use the layout
``estcal next-pose --state`` reads (:class:`estcal.design.sequential.CalibrationState`).

Resume rule: the first ``input_bytes`` bytes of the input must hash to
``input_sha256_prefix`` (the processed rows are unchanged; a file that has *grown* since —
a stream being appended to — is accepted), and every estimate-changing option must be equal.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

__all__ = ["FORMAT", "CheckpointError", "PrefixHasher", "filter_checkpoint", "save_checkpoint",
           "load_checkpoint", "restore_filter", "option_differences", "file_sha256"]

FORMAT = "estcal-online-checkpoint"
VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (wrong file, other input, other options)."""


def file_sha256(path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for b in iter(lambda: fh.read(chunk), b""):
            h.update(b)
    return h.hexdigest()


class PrefixHasher:
    """SHA-256 and byte count of the input consumed so far (updated line by line)."""

    def __init__(self):
        self.h = hashlib.sha256()
        self.n = 0

    def update(self, raw: bytes) -> None:
        self.h.update(raw)
        self.n += len(raw)

    def hexdigest(self) -> str:
        return self.h.hexdigest()


def filter_checkpoint(flt, *, options: dict, rows: int, line: int, hasher: PrefixHasher, input_sha256,
                      burn, history, finished: bool = False) -> dict:
    """The checkpoint dictionary of a :class:`~estcal.estimate.kalman.ParameterFilter`."""
    mon = flt.monitor
    return {
        "format": FORMAT, "version": VERSION, "finished": bool(finished),
        "parameters": list(flt.names), "estimate": flt.x.tolist(), "covariance": flt.P.tolist(),
        "std": flt.std.tolist(), "Q": np.asarray(flt.Q, float).tolist(), "theta0": flt.theta0.tolist(),
        "kind": flt.kind, "n_steps": int(flt.n_steps), "n_rows": int(flt.n_rows),
        "rows": int(rows), "line": int(line), "input_bytes": int(hasher.n),
        "input_sha256_prefix": hasher.hexdigest(), "input_sha256": input_sha256,
        "options": dict(options), "burn": burn, "history": history,
        "innovations": {"nis": list(mon.nis), "dims": list(mon.dims), "white": [w.tolist() for w in mon.white]},
    }


def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` atomically (never a partial file)."""
    from estcal.io.atomic import atomic_write_text

    return atomic_write_text(path, json.dumps(state))


def load_checkpoint(path) -> dict:
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: checkpoint not found (write one with --state {path})")
    try:
        d = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{path}: not a readable checkpoint ({exc})") from None
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an estcal online checkpoint (no format {FORMAT!r})")
    if d.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {d.get('version')}, this estcal reads {VERSION}")
    return d


def option_differences(saved: dict, current: dict) -> list[str]:
    """``option: current (checkpoint: saved)`` for every option that differs."""
    out = []
    for k in sorted(set(saved) | set(current)):
        if saved.get(k) != current.get(k):
            out.append(f"{k}: {current.get(k)!r} (checkpoint: {saved.get(k)!r})")
    return out


def restore_filter(flt, state: dict) -> None:
    """Put the checkpointed x, P, counters and innovation record into a fresh filter."""
    from estcal.estimate.innovation import InnovationMonitor

    if list(flt.names) != list(state["parameters"]):
        raise CheckpointError(f"checkpoint parameters {state['parameters']} differ from {flt.names}")
    if not np.array_equal(flt.theta0, np.asarray(state["theta0"], float)):
        i = int(np.flatnonzero(flt.theta0 != np.asarray(state["theta0"], float))[0])
        raise CheckpointError(f"the robot's parameter values differ from the checkpointed run's (entry {i}); "
                              f"resume with the same robot file")
    flt.f.x = np.asarray(state["estimate"], float)
    flt.f.P = np.asarray(state["covariance"], float)
    flt.n_steps = int(state["n_steps"])
    flt.n_rows = int(state["n_rows"])
    mon = InnovationMonitor()
    inn = state["innovations"]
    mon.nis = [float(v) for v in inn["nis"]]
    mon.dims = [int(v) for v in inn["dims"]]
    mon.white = [np.asarray(w, float) for w in inn["white"]]
    flt.monitor = mon
