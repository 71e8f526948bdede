"""One writer per state file: an advisory lock held for the whole run.

Two ``estcal online --state S`` (or ``--resume S``) runs, or two MCMC runs on one
``--chain FILE``, would append to the same journal or chain and leave a state that
belongs to neither. :class:`RunLock` takes an exclusive, non-blocking
``flock(2)`` on ``<file>.lock`` beside the file; the second run is refused at
once with the first one's process id. The kernel releases the lock when its
process dies, so a ``kill -9`` never leaves a stale lock behind (the file that
remains is empty of meaning: the next run locks it again).

Where ``fcntl`` does not exist (Windows) the lock is a no-op.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

from .errors import EstcalError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

__all__ = ["RunLock", "LockedError", "lock_path"]


class LockedError(EstcalError, RuntimeError):
    """The file is being written by another running process."""


def lock_path(path) -> Path:
    path = Path(path)
    return path.with_name(path.name + ".lock")


class RunLock:
    """Exclusive lock on ``path`` for this process (context manager, or :meth:`acquire` /
    :meth:`release`). ``what`` names the file in the message (``--state``, ``--chain`` …)."""

    def __init__(self, path, what: str = "file"):
        self.path = Path(path)
        self.what = what
        self.lock = lock_path(self.path)
        self._fd = None

    def acquire(self) -> "RunLock":
        if fcntl is None:
            return self
        self.lock.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.lock, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = ""
                with contextlib.suppress(OSError):
                    pid = os.pread(fd, 32, 0).decode(errors="replace").strip()
                os.close(fd)
                raise LockedError(f"{self.path}: in use by another running estcal process"
                                  f"{f' (pid {pid})' if pid else ''} — wait for it to finish, or give this run "
                                  f"another {self.what}") from None
            # the lock file may have been removed and re-created between open and flock by a
            # releasing run: hold the lock only if the path still names the locked file
            try:
                same = os.stat(self.lock).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.lock)  # while still locked: a waiting opener re-checks the inode
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
