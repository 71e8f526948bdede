"""Checksums of the files estcal writes, so that a changed digit or a cut file is refused on reading.

A file written by estcal carries the SHA-256 of its own content:

* text files (saved models, :func:`estcal.io.robotfile.save_robot` with ``checksum=True``): a comment
  line ``# content-sha256: <hex>`` whose hash covers every byte *after* that line. YAML ignores
  comments, so older readers still read the file; a file cut at any line boundary or edited by
  hand no longer matches. Deleting the line accepts a deliberate hand edit;
* JSON state (online checkpoints): a key ``content_sha256`` over the canonical JSON of the other
  keys (sorted keys, compact separators; floats round-trip exactly in Python's JSON).

And of what estcal reads as a stream: :class:`PrefixHasher` follows the SHA-256 of the input consumed
so far, so that a resumed online run checks it reads the input of the checkpointed one
(:class:`CheckpointError` otherwise; :mod:`estcal.io.stream`, :mod:`estcal.estimate.checkpoint`).
"""
from __future__ import annotations

import hashlib
import json
import re

from estcal.base.errors import InputError

__all__ = ["CHECKSUM_PREFIX", "stamp_text", "verify_text", "stamp_json", "verify_json", "CheckpointError",
           "file_sha256", "PrefixHasher"]

CHECKSUM_PREFIX = "# content-sha256: "
_LINE = re.compile(r"^# content-sha256: ([0-9a-f]{64})[ \t]*\r?\n", re.MULTILINE)


def _sha(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def stamp_text(head: str, body: str) -> str:
    """``head`` (comment lines), the checksum line of ``body``, then ``body``."""
    return f"{head}{CHECKSUM_PREFIX}{_sha(body)}\n{body}"


def verify_text(text: str, where: str, error=ValueError, what: str = "file") -> bool:
    """Check the checksum line of ``text`` if it has one; returns whether it had one. A mismatch
    raises ``error`` naming the file and what to do."""
    m = _LINE.search(text)
    if m is None:
        return False
    body = text[m.end():]
    if _sha(body) != m.group(1):
        line = text.count("\n", 0, m.start()) + 1
        n = body.count("\n")
        raise error(f"{where}: the content differs from the checksum estcal wrote at line {line} — the {what} was "
                    f"changed or cut after it was written ({n} line(s) follow the checksum now); restore it from the "
                    f"original, or delete line {line} to accept a deliberate hand edit")
    return True


def _canonical(d: dict) -> str:
    return json.dumps(d, sort_keys=True, separators=(",", ":"), allow_nan=True)


def stamp_json(d: dict) -> dict:
    """``d`` with ``content_sha256`` of its other keys."""
    out = {k: v for k, v in d.items() if k != "content_sha256"}
    out["content_sha256"] = _sha(_canonical(out))
    return out


def verify_json(d: dict, where: str, error=ValueError, what: str = "file") -> bool:
    """Check ``content_sha256`` of a loaded JSON mapping if present; returns whether it was."""
    if "content_sha256" not in d:
        return False
    rest = {k: v for k, v in d.items() if k != "content_sha256"}
    if _sha(_canonical(rest)) != d["content_sha256"]:
        raise error(f"{where}: the content differs from the checksum estcal wrote (content_sha256) — the {what} was "
                    f"changed after it was written; restore it, or start again without it")
    return True


class CheckpointError(InputError):
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
