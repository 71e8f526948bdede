"""Atomic output files: never leave a truncated result behind.

Every file estcal writes goes through :func:`atomic_write`: the content is
written to a temporary file in the *target's own directory* (so the final
``os.replace`` is a same-filesystem rename, atomic on POSIX and Windows),
flushed and fsync'ed, then renamed over the target. A process killed at any
moment leaves either the old file or the complete new one — never a partial
file that a later command would accept — plus at worst a hidden
``.<name>.*.tmp`` file, which the next successful write of the same target
does not depend on.

Example
-------
>>> with atomic_write("out.csv") as fh:          # doctest: +SKIP
...     fh.write("a,b\\n1,2\\n")
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from .errors import InputError

__all__ = ["refuse_input", "atomic_path", "atomic_write", "atomic_write_text", "atomic_write_bytes", "atomic_savefig"]


def refuse_input(path, inputs) -> None:
    """Raise :class:`~estcal.base.errors.InputError` (a ValueError) when ``path`` is one of ``inputs`` (files a result was computed from:
    its dataset, validation files, robot file): inputs are never overwritten, in Python as on the
    command line (:func:`estcal.cli.checks.check_outputs`)."""
    real = os.path.realpath(path)
    for src in inputs:
        if src and Path(str(src)).is_file() and os.path.realpath(src) == real:
            raise InputError(f"{path}: is an input of this result ({src}) — write it to another file "
                             f"(inputs are never overwritten)")


def _umask() -> int:
    mask = os.umask(0)  # the only portable read of the umask is to set it
    os.umask(mask)
    return mask


_UMASK = _umask()


def _final_mode(path: Path) -> int:
    """The permission bits the file would have had if written in place: those of the file it
    replaces, else the usual ``0o666 & ~umask`` (``mkstemp`` creates ``0o600``)."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_UMASK


@contextlib.contextmanager
def _replacing(path):
    """``(fd, tmp)``: an open temporary file beside ``path`` (its folders created) that replaces ``path``, with
    the permissions a file written in place would have, when the ``with`` block ends without an exception —
    and is removed when it raises (``path`` untouched). The one mechanism of :func:`atomic_path` and
    :func:`atomic_write`; the caller owns ``fd`` (closes it, or writes through it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        yield fd, Path(tmp)
        os.chmod(tmp, _final_mode(path))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path, durable: bool = True):
    """Context manager yielding the path of a temporary file beside ``path`` that replaces
    ``path`` on success (fsync'ed, then renamed), for writers that open the file themselves
    (h5py, a copy to edit). On an exception the temporary file is removed and ``path`` is
    left untouched. Its parent folders are created.

    ``durable=False``: renamed without the fsync — still whole or absent after a killed process,
    but a power failure may leave it empty or cut under its final name. Only for files a later
    reader checks before it trusts them (a fleet's result rows: the fsync was most of the
    command's CPU per robot, docs/scaling.md)."""
    with _replacing(path) as (fd, tmp):
        os.close(fd)
        yield tmp
        if durable:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", encoding: str | None = "utf-8", newline: str | None = None,
                 durable: bool = True):
    """Context manager yielding a file object whose content replaces ``path`` on success.

    Parameters
    ----------
    path : str or Path
        Final destination. Its parent folders are created.
    mode : {'w', 'wb'}
        Text or binary.
    encoding, newline : passed to :func:`open` in text mode.
    durable : fsync before the rename (:func:`atomic_path`).

    On an exception inside the ``with`` block the temporary file is removed and
    ``path`` is left untouched (:func:`atomic_path`).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    kw = {} if "b" in mode else {"encoding": encoding, "newline": newline}
    with _replacing(path) as (fd, tmp):
        # written through the temporary file's own descriptor, fsync'ed before it is closed (atomic_path,
        # for writers that open the file themselves, has to reopen it)
        with os.fdopen(fd, mode, **kw) as fh:
            yield fh
            if durable:
                fh.flush()
                os.fsync(fh.fileno())


def atomic_write_text(path, text: str, encoding: str = "utf-8", durable: bool = True) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path (``durable``: :func:`atomic_path`)."""
    with atomic_write(path, "w", encoding=encoding, durable=durable) as fh:
        fh.write(text)
    return Path(path)


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_write(path, "wb") as fh:
        fh.write(data)
    return Path(path)


def atomic_savefig(fig, path, **kwargs) -> Path:
    """``fig.savefig`` to ``path`` atomically (the format follows the suffix, as matplotlib's)."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".").lower() or "png")
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, **kwargs)
    return path
