"""BLAS threads: the calibration matrices are tall and thin, and threads only spin on them.

:func:`single_thread_blas` runs BLAS/LAPACK single-threaded inside a block (the least-squares
fits, the factor-graph QR, each task of the task runner).
"""
from __future__ import annotations

import contextlib
import ctypes
import glob
import os

import numpy as np

__all__ = ["single_thread_blas"]


_BLAS_SETTERS = None


def _blas_thread_setters():
    """(get, set) pairs of every OpenBLAS loaded by numpy/scipy wheels (ctypes, no dependency)."""
    global _BLAS_SETTERS
    if _BLAS_SETTERS is not None:
        return _BLAS_SETTERS
    pairs = []
    roots = {os.path.dirname(os.path.dirname(np.__file__))}
    for root in roots:
        for lib in glob.glob(os.path.join(root, "numpy.libs", "*openblas*.so*")) + \
                glob.glob(os.path.join(root, "scipy.libs", "*openblas*.so*")):
            try:
                h = ctypes.CDLL(lib)
            except OSError:
                continue
            for suffix in ("64_", "_64_", ""):
                get = getattr(h, f"scipy_openblas_get_num_threads{suffix}", None)
                set_ = getattr(h, f"scipy_openblas_set_num_threads{suffix}", None)
                if get is not None and set_ is not None:
                    pairs.append((get, set_))
                    break
            else:
                get = getattr(h, "openblas_get_num_threads", None)
                set_ = getattr(h, "openblas_set_num_threads", None)
                if get is not None and set_ is not None:
                    pairs.append((get, set_))
    _BLAS_SETTERS = pairs
    return pairs


@contextlib.contextmanager
def single_thread_blas(enabled: bool = True):
    """Run BLAS/LAPACK single-threaded inside the block.

    The calibration matrices are tall and thin (M × p with p ≲ 100): OpenBLAS's
    threads give no speed-up on them and, on a busy machine, their spin-waiting
    made a 50-pose PUMA fit ~10× slower (measured in ``benchmarks/bench_calibration.py``).
    Uses the OpenBLAS setters of the numpy/scipy wheels through ctypes (found once, ~1 µs a
    call), else ``threadpoolctl`` when installed (it scans the loaded libraries at every call:
    ~1.7 ms, more than a small fit's linear algebra); a no-op when neither is available or
    BLAS already runs one thread (``estcal`` commands: :mod:`estcal.cli.main`).
    """
    if not enabled:
        yield
        return
    pairs = _blas_thread_setters()
    if not pairs:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:
            yield
            return
        with threadpool_limits(1, user_api="blas"):
            yield
        return
    old = []
    for get, set_ in pairs:
        try:
            n = int(get())
            if n != 1:
                set_(1)
            old.append(n)
        except Exception:  # pragma: no cover - exotic BLAS builds
            old.append(None)
    try:
        yield
    finally:
        for (get, set_), n in zip(pairs, old):
            if n is not None and n != 1:
                set_(n)
