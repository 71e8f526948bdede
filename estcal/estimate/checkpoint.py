"""Checkpoints of a recursive (Kalman) calibration, so a killed ``estcal online`` loses nothing.

A checkpoint is one JSON file written atomically (:mod:`estcal.base.atomic`: temp file,
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
* the burn-in, and a pointer (file name, byte count, SHA-256) into the run's **journal**.

The journal, ``<state>.journal`` beside the checkpoint, holds what grows with the stream: the
innovation record (NIS, dimension and whitened innovation of every row — what the final
innovation tests need) and the printed history. Rewriting them into every checkpoint would make
a 10⁶-row run write O(N²) bytes; instead each checkpoint *appends* the records since the last
one (binary float64, fsync'ed) and then renames the new JSON into place. Bytes beyond the
checkpoint's byte count (a kill between the append and the rename) are ignored and cut on
resume, so the journal and the checkpoint always agree. Journal record layout: ``[tag, n,
payload (n values)]`` with tag 0 = one innovation step ``[NIS, w_1 … w_m]`` and tag 1 = one
history entry ``[row, line, NIS, NIS/row, trace P, estimate (p), std (p)]``.

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
import os
from pathlib import Path

import numpy as np

from estcal.io.integrity import CheckpointError, PrefixHasher, file_sha256  # where the input is read too

__all__ = ["FORMAT", "CheckpointError", "PrefixHasher", "Journal", "journal_path", "filter_checkpoint",
           "save_checkpoint", "load_checkpoint", "restore_filter", "option_differences", "file_sha256"]

FORMAT = "estcal-online-checkpoint"
VERSION = 3  # 2: the innovation record and history moved to the journal; 3: linearisation segment, source
READABLE = (2, 3)
_INNOVATION, _HISTORY = 0.0, 1.0


def journal_path(state_path) -> Path:
    """The journal of the checkpoint ``state_path``: ``<state>.journal`` beside it."""
    state_path = Path(state_path)
    return state_path.with_name(state_path.name + ".journal")


class Journal:
    """Append-only record of an online run (innovations and printed history) beside its checkpoint.

    ``Journal.start(state)`` begins an empty one; ``Journal.resume(state, saved, saved_path)``
    continues the journal a checkpoint points to (checked against its byte count and SHA-256;
    bytes past the count are cut) or, for a new ``--state`` path, copies its checkpointed part.
    :meth:`append` writes what the monitor and history gained since the last call and returns
    the pointer the next checkpoint stores."""

    def __init__(self, path: Path, steps: int = 0, entries: int = 0, nbytes: int = 0, hasher=None):
        self.path = Path(path)
        self.steps, self.entries, self.bytes = steps, entries, nbytes
        self.h = hasher or hashlib.sha256()
        self._off = None

    @classmethod
    def start(cls, state_path) -> "Journal":
        path = journal_path(state_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:  # a journal without its checkpoint is of no use: start empty
            os.fsync(fh.fileno())
        return cls(path)

    @staticmethod
    def read(saved: dict, saved_path) -> tuple[bytes, dict]:
        """The checkpointed bytes of the journal ``saved`` points to, checked."""
        ptr = saved.get("journal")
        if not isinstance(ptr, dict):
            raise CheckpointError(f"{saved_path}: no journal entry in the checkpoint")
        path = Path(saved_path).with_name(str(ptr["file"]))
        n = int(ptr["bytes"])
        try:
            with open(path, "rb") as fh:
                data = fh.read(n)
        except OSError as exc:
            raise CheckpointError(f"{path}: cannot read the journal of {saved_path} ({exc.strerror or exc}) — "
                                  f"a checkpoint is two files, {Path(saved_path).name} and {path.name}; keep "
                                  f"them together") from None
        if len(data) < n or hashlib.sha256(data).hexdigest() != ptr["sha256"]:
            raise CheckpointError(f"{path}: the journal does not match its checkpoint {saved_path} "
                                  f"({len(data)} of {n} bytes, or other content) — it was changed or belongs to "
                                  f"another run")
        return data, ptr

    @classmethod
    def resume(cls, state_path, saved: dict, saved_path) -> "Journal":
        data, ptr = cls.read(saved, saved_path)
        h = hashlib.sha256(data)
        path = journal_path(state_path)
        if path.resolve() == Path(saved_path).with_name(str(ptr["file"])).resolve():
            with open(path, "r+b") as fh:  # cut what a killed run appended after its last checkpoint
                fh.truncate(len(data))
                os.fsync(fh.fileno())
        else:
            from estcal.base.atomic import atomic_write_bytes

            atomic_write_bytes(path, data)
        return cls(path, int(ptr["steps"]), int(ptr["history"]), len(data), h)

    def append(self, monitor, history: list) -> dict:
        """Write the innovation steps and history entries not yet in the journal; fsync."""
        parts = []
        nis, dims, white = monitor.nis, monitor.dims, monitor.white_flat
        if self._off is None:  # whitened components already in the journal (once; then kept up to date)
            self._off = int(np.sum(dims[:self.steps], dtype=np.int64))
        off = self._off
        if len(nis) > self.steps:  # records [tag, m + 1, NIS, w_1 … w_m] of the new steps, built at once
            m = np.asarray(dims[self.steps:], np.int64)
            nw = int(m.sum())
            start = np.r_[0, np.cumsum(m + 3)[:-1]]
            rec = np.empty(int(start[-1] + m[-1] + 3))
            rec[start], rec[start + 1], rec[start + 2] = _INNOVATION, m + 1.0, nis[self.steps:]
            within = np.arange(nw) - np.repeat(np.r_[0, np.cumsum(m)[:-1]], m)
            rec[np.repeat(start + 3, m) + within] = white[off:off + nw]
            parts.append(rec)
            off += nw
        for e in history[self.entries:]:
            vals = [e["row"], e["line"], e["nis"], e["nis_per_row"], e["trace_P"], *e["estimate"], *e["std"]]
            parts.append(np.concatenate([[_HISTORY, float(len(vals))], np.asarray(vals, float)]))
        if parts:
            raw = np.concatenate(parts).astype("<f8").tobytes()
            with open(self.path, "ab") as fh:
                fh.write(raw)
                fh.flush()
                os.fsync(fh.fileno())
            self.h.update(raw)
            self.bytes += len(raw)
        self.steps, self.entries, self._off = len(nis), len(history), off
        return {"file": self.path.name, "bytes": self.bytes, "sha256": self.h.hexdigest(), "steps": self.steps,
                "history": self.entries}


def parse_journal(data: bytes, n_params: int):
    """``(nis, dims, white_flat, history)`` of journal bytes (the layout in the module docstring)."""
    a = np.frombuffer(data, "<f8")
    nis, dims, white, history = [], [], [], []
    i = 0
    while i < a.size:
        tag, n = a[i], int(a[i + 1])
        rec = a[i + 2:i + 2 + n]
        if rec.size != n:
            raise CheckpointError(f"journal: record at value {i} is cut short")
        if tag == _INNOVATION:
            nis.append(rec[0])
            dims.append(n - 1)
            white.append(rec[1:])
        elif tag == _HISTORY:
            p = (n - 5) // 2
            history.append({"row": int(rec[0]), "line": int(rec[1]), "nis": float(rec[2]),
                            "nis_per_row": float(rec[3]), "trace_P": float(rec[4]),
                            "estimate": rec[5:5 + p].tolist(), "std": rec[5 + p:5 + 2 * p].tolist()})
        else:
            raise CheckpointError(f"journal: unknown record tag {tag!r} at value {i}")
        i += 2 + n
    white = np.concatenate(white) if white else np.zeros(0)
    return np.asarray(nis, float), np.asarray(dims, np.int64), white, history


def filter_checkpoint(flt, *, options: dict, rows: int, position: dict, burn, journal: dict,
                      finished: bool = False, lin=None, source=None) -> dict:
    """The checkpoint dictionary of a :class:`~estcal.estimate.kalman.ParameterFilter`; ``journal`` is
    the pointer :meth:`Journal.append` returned for the records up to this point; ``position`` the
    input read so far (``line``, ``input_bytes``, ``input_sha256_prefix``, ``input_sha256``); ``lin``
    the linearisation state the next step depends on (:func:`estcal.estimate.kalman.run_steps`:
    segment start, linearisation point, the step it was set at, evaluation window)."""
    return {
        "format": FORMAT, "version": VERSION, "finished": bool(finished),
        "parameters": list(flt.names), "estimate": flt.x.tolist(), "covariance": flt.P.tolist(),
        "std": flt.std.tolist(), "Q": np.asarray(flt.Q, float).tolist(), "theta0": flt.theta0.tolist(),
        "kind": flt.kind, "n_steps": int(flt.n_steps), "n_rows": int(flt.n_rows),
        "rows": int(rows), "line": position.get("line"), "input_bytes": int(position.get("input_bytes", 0)),
        "input_sha256_prefix": position.get("input_sha256_prefix"), "input_sha256": position.get("input_sha256"),
        "source": source, "options": dict(options), "burn": burn, "journal": journal,
        "lin": None if lin is None else {"start": int(lin[0]), "x": np.asarray(lin[1], float).tolist(),
                                         "at": int(lin[2]), "window": int(lin[3])},
    }


def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` atomically (never a partial file)."""
    from estcal.base.atomic import atomic_write_text
    from estcal.io.integrity import stamp_json

    return atomic_write_text(path, json.dumps(stamp_json(state)))  # a changed digit is refused on resume


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
    if d.get("version") not in READABLE:
        raise CheckpointError(f"{path}: checkpoint version {d.get('version')}, this estcal reads "
                              f"{', '.join(map(str, READABLE))}")
    from estcal.io.integrity import verify_json

    verify_json(d, str(path), CheckpointError, "checkpoint")
    d.pop("content_sha256", None)
    return d


def option_differences(saved: dict, current: dict) -> list[str]:
    """``option: current (checkpoint: saved)`` for every option that differs."""
    out = []
    for k in sorted(set(saved) | set(current)):
        if saved.get(k) != current.get(k):
            out.append(f"{k}: {current.get(k)!r} (checkpoint: {saved.get(k)!r})")
    return out


def restore_filter(flt, state: dict, state_path) -> list:
    """Put the checkpointed x, P, counters and innovation record into a fresh filter; returns the
    printed history (both read from the checkpoint's journal)."""
    from estcal.estimate.innovation import InnovationMonitor

    if list(flt.names) != list(state["parameters"]):
        raise CheckpointError(f"checkpoint parameters {state['parameters']} differ from {flt.names}")
    if not np.array_equal(flt.theta0, np.asarray(state["theta0"], float)):
        i = int(np.flatnonzero(flt.theta0 != np.asarray(state["theta0"], float))[0])
        raise CheckpointError(f"the robot's parameter values differ from the checkpointed run's (entry {i}); "
                              f"resume with the same robot file")
    data, ptr = Journal.read(state, state_path)
    nis, dims, white, history = parse_journal(data, len(flt.names))
    if nis.size != int(ptr["steps"]) or len(history) != int(ptr["history"]) or nis.size != int(state["n_steps"]):
        raise CheckpointError(f"{state_path}: the journal holds {nis.size} steps and {len(history)} history "
                              f"entries, the checkpoint names {state['n_steps']} and {ptr['history']}")
    flt.f.x = np.asarray(state["estimate"], float)
    flt.f.P = np.asarray(state["covariance"], float)
    flt.n_steps = int(state["n_steps"])
    flt.n_rows = int(state["n_rows"])
    flt.monitor = InnovationMonitor.from_record(nis, dims, white)
    return history
