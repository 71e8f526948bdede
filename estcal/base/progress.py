"""Progress bars for long work: visible on a terminal, silent in pipes, logs and CI.

:func:`progress` wraps :mod:`tqdm` (writing to stderr, so that a command's
stdout stays parseable) and returns a quiet stand-in with the same small
interface (iteration, ``update``, ``set_postfix``, ``close``, context manager)
when a bar should not be drawn. It is drawn when

* ``enabled=True`` is passed, or the environment variable ``ESTCAL_PROGRESS``
  is ``1`` (forced), or
* ``enabled`` is None (automatic) and stderr is a terminal, the ``CI``
  variable is unset or empty, ``ESTCAL_PROGRESS`` is not ``0``, and no other
  automatic bar is open (nested loops — the LM iterations inside a diagnosis's
  cross-validation, a Monte-Carlo repetition's calibration — show only the
  outermost bar).

Automatic bars appear only after ``delay`` seconds (0.5 s by default), so
quick runs never flash a bar.

Example
-------
>>> from estcal.base.progress import progress
>>> with progress(total=3, desc="restarts") as bar:   # quiet here: doctest's stderr is no TTY
...     for _ in range(3):
...         bar.update(1)
"""
from __future__ import annotations

import functools
import os
import sys

__all__ = ["progress", "progress_enabled", "nested"]

_open_auto = 0  # automatic bars currently open (only the outermost is drawn)


def progress_enabled(enabled: bool | None = None, stream=None) -> bool:
    """Whether a bar would be drawn (see the module docstring for the rules)."""
    if enabled is not None:
        return bool(enabled)
    env = os.environ.get("ESTCAL_PROGRESS", "").strip().lower()
    if env in ("1", "true", "yes", "always"):
        return True
    if env in ("0", "false", "no", "never"):
        return False
    if os.environ.get("CI", "").strip() not in ("", "0", "false"):
        return False
    if _open_auto:
        return False
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or replaced streams
        return False


class nested:
    """Context in which automatic bars stay quiet, as inside an open bar: for work that runs
    as one task of an outer loop in another process (a worker of
    :func:`estcal.scale.runner.run_tasks`), where the outer bar's count is not visible."""

    def __enter__(self):
        global _open_auto
        _open_auto += 1
        return self

    def __exit__(self, *exc):
        global _open_auto
        _open_auto -= 1
        return False


class _Quiet:
    """Same interface as a tqdm bar, draws nothing."""

    def __init__(self, iterable=None, total=None, **_):
        self.iterable = iterable
        self.total = total
        self.n = 0

    def __iter__(self):
        for x in self.iterable:
            self.n += 1
            yield x

    def __len__(self):
        return len(self.iterable) if self.iterable is not None else int(self.total or 0)

    def update(self, n=1):
        self.n += n

    def set_postfix(self, *args, **kwargs):
        pass

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


@functools.lru_cache(maxsize=None)
def _bar_class():
    from tqdm import tqdm

    class _Bar(tqdm):
        """tqdm that keeps the count of open automatic bars."""

        def __init__(self, *args, auto: bool = False, **kwargs):
            global _open_auto
            self._auto = auto
            if auto:
                _open_auto += 1
            try:
                super().__init__(*args, **kwargs)
            except BaseException:
                if auto:
                    _open_auto -= 1
                    self._auto = False
                raise

        def close(self):
            global _open_auto
            if getattr(self, "_auto", False):
                _open_auto -= 1
                self._auto = False
            super().close()

    return _Bar


def progress(iterable=None, total=None, desc: str = "", enabled: bool | None = None, unit: str = "it",
             delay: float | None = None, leave: bool = False, **kwargs):
    """A progress bar over ``iterable`` (or a manual one with ``total`` and ``update``).

    Parameters
    ----------
    iterable : optional iterable to wrap.
    total : number of expected steps (default ``len(iterable)`` when it has one).
    desc : label shown before the bar.
    enabled : True forces a bar, False suppresses it, None decides automatically.
    delay : seconds before an automatic bar first appears (default 0.5; 0 when forced).
    leave : keep the finished bar on screen.

    Returns a tqdm bar writing to stderr, or a quiet object with the same interface.
    Use it as a context manager (or call ``close()``) so that nesting is tracked.
    """
    forced = enabled is True or (enabled is None and os.environ.get("ESTCAL_PROGRESS", "").strip().lower()
                                 in ("1", "true", "yes", "always"))
    if not progress_enabled(enabled):
        return _Quiet(iterable, total)
    if delay is None:
        delay = 0.0 if forced else 0.5
    return _bar_class()(iterable, total=total, desc=desc, unit=unit, file=sys.stderr, delay=delay, leave=leave,
                        dynamic_ncols=True, auto=not forced, **kwargs)
