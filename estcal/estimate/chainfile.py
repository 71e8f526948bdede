"""Resumable MCMC chains: emcee's HDF5 backend plus what a resumed run must reuse.

``estcal calibrate --method mcmc --chain FILE`` stores the chain in FILE (emcee's
:class:`~emcee.backends.HDFBackend`, group ``mcmc``: walker positions, log-probabilities,
acceptance counts and the sampler's random state after every step) and, in group
``estcal``, the sampling frame the chain's coordinates are written in — the whitening
centre and covariance (the sampler works in z with θ = θ̂ + L z), the free parameter names —
and a fingerprint of the target (residuals and σ of the data at the linearisation point,
prior stds, number of walkers, moves, noise-scale flag).

Run again with the same FILE and the same data and options: the sampler continues from
the last stored step with the stored random state, so the chain is *extended* — its first
part is the saved chain, bit for bit (``tests/test_mcmc_chain.py``). A FILE whose
fingerprint differs is refused (never overwritten).

Steps are buffered in memory and written in blocks (:class:`BufferedHDFBackend`): a block
is appended to a *copy* of the file, which is fsync'ed and renamed over it — HDF5 is not
journaled, so writing in place could leave a damaged file after a kill; with copy-and-rename
a ``kill -9`` at any instant leaves the previous or the new complete chain. Blocks are written
when at least ten times the last block's write time has passed since the previous one (the
copy costs ≤ ~10 % of the sampling time, whatever the file size) and at the end; a killed run
loses at most the steps since the last block.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path

import numpy as np

from estcal.base.atomic import atomic_path
from estcal.base.errors import InputError, require

__all__ = ["ChainFileError", "BufferedHDFBackend", "check_chain_path", "open_chain", "fingerprint"]


class ChainFileError(InputError):
    """A chain file that cannot be continued by this run."""


def fingerprint(problem, theta, extra: dict) -> str:
    """SHA-256 of the data's residuals and σ at ``theta`` and of the sampling options."""
    r = problem.evaluate(theta, jacobian=False)
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(r.e, float).tobytes())
    h.update(np.ascontiguousarray(r.sigma, float).tobytes())
    h.update(json.dumps(extra, sort_keys=True, default=str).encode())
    return h.hexdigest()


def _backend_class():
    from emcee.backends import HDFBackend
    from emcee.state import State

    class _Buffered(HDFBackend):
        """HDFBackend that keeps steps in memory and writes them in atomic blocks (:meth:`flush`)."""

        def __init__(self, filename, name="mcmc"):
            super().__init__(filename, name=name)
            self._buf = []
            self._last_flush = time.monotonic()
            self._flush_cost = 0.0

        def grow(self, ngrow, blobs):
            if blobs is not None:
                raise ChainFileError("chain files do not store blobs")

        def save_step(self, state, accepted):
            self._buf.append((np.array(state.coords), np.array(state.log_prob), np.array(accepted, int),
                              tuple(state.random_state)))

        # reads see the stored steps followed by the buffered ones
        @property
        def _stored(self):
            return super().iteration

        @property
        def iteration(self):
            return self._stored + len(self._buf)

        @property
        def accepted(self):
            acc = super().accepted
            return acc + np.sum([b[2] for b in self._buf], axis=0) if self._buf else acc

        def get_value(self, name, flat=False, thin=1, discard=0):
            if name == "blobs":  # never stored (grow refuses them)
                return None
            if name not in ("chain", "log_prob"):
                raise ChainFileError(f"chain files store chain and log_prob, not {name!r}")
            with self.open() as f:
                v = f[self.name][name][: f[self.name].attrs["iteration"]]
            if self._buf:
                v = np.concatenate([v, np.stack([b[0 if name == "chain" else 1] for b in self._buf])])
            v = v[discard + thin - 1::thin]
            if flat:
                v = v.reshape((-1,) + v.shape[2:])
            return v

        def get_last_sample(self):
            if not self._buf:
                return super().get_last_sample()
            c, lp, _, rs = self._buf[-1]
            return State(c, log_prob=lp, random_state=rs)

        def maybe_flush(self):
            """Flush when the time since the last block is ≥ 10× the cost of writing one, so the
            copy-and-rename below costs ≤ ~10 % of the sampling time however large the file."""
            if self._buf and time.monotonic() - self._last_flush >= 10 * self._flush_cost:
                self.flush()

        def flush(self):
            """Append the buffered steps to a copy of the file and rename it over the file (a kill at
            any instant leaves the previous or the new complete chain)."""
            h5py = require("h5py", "an MCMC chain file (--chain)")

            if not self._buf:
                return
            t0 = time.monotonic()
            n = len(self._buf)

            path = Path(self.filename)
            with atomic_path(path) as tmp:
                shutil.copyfile(path, tmp)
                shutil.copymode(path, tmp)
                with h5py.File(tmp, "a") as f:
                    g = f[self.name]
                    it = int(g.attrs["iteration"])
                    g["chain"].resize(it + n, axis=0)
                    g["log_prob"].resize(it + n, axis=0)
                    g["chain"][it:it + n] = np.stack([b[0] for b in self._buf])
                    g["log_prob"][it:it + n] = np.stack([b[1] for b in self._buf])
                    g["accepted"][:] += np.sum([b[2] for b in self._buf], axis=0)
                    for i, v in enumerate(self._buf[-1][3]):
                        g.attrs[f"random_state_{i}"] = v
                    g.attrs["iteration"] = it + n
            self._buf = []
            self._last_flush = time.monotonic()
            self._flush_cost = self._last_flush - t0

    return _Buffered


def BufferedHDFBackend(filename, name="mcmc"):  # noqa: N802 - a factory standing for the class
    """Buffered emcee HDF5 backend (class built lazily: emcee is optional)."""
    return _backend_class()(filename, name=name)


def check_chain_path(path) -> Path:
    """``path`` as a Path, or :class:`ChainFileError` when it is a folder."""
    path = Path(path)
    if path.is_dir():
        raise ChainFileError(f"{path}: is a folder — give a file name for the chain (e.g. {path / 'chain.h5'})")
    return path


def open_chain(path, *, names, fp: str, n_walkers: int, ndim: int):
    """``(backend, saved)``: the chain backend for ``path`` and the stored frame ``{center, covariance}``
    when the file holds a chain this run can continue (None for a new chain)."""
    h5py = require("h5py", "an MCMC chain file (--chain)")

    path = check_chain_path(path)
    backend = BufferedHDFBackend(str(path))
    if not path.exists() or path.stat().st_size == 0:
        return backend, None
    if not h5py.is_hdf5(path):
        raise ChainFileError(f"{path}: not an HDF5 file — estcal creates the chain file: give a new file name, or "
                             f"the file of an earlier chain to continue it")
    try:
        with h5py.File(path, "r") as f:
            if "mcmc" not in f or int(f["mcmc"].attrs.get("iteration", 0)) == 0:
                saved = None
            elif "estcal" not in f:
                raise ChainFileError(f"{path}: an HDF5 chain not written by estcal — choose another --chain file")
            else:
                g = f["estcal"]
                info = json.loads(g.attrs["info"])
                saved = {"center": g["center"][...], "covariance": g["covariance"][...], **info}
    except OSError as exc:
        raise ChainFileError(f"{path}: unreadable chain file ({exc}); it may have been damaged by a kill during "
                             f"a write — move it away and start a new chain") from None
    if saved is None:
        return backend, None
    if saved["fingerprint"] != fp or saved["names"] != list(names) or saved["n_walkers"] != n_walkers \
            or saved["ndim"] != ndim:
        what = [k for k, v in (("data or sampling options", saved["fingerprint"] != fp),
                               ("free parameters", saved["names"] != list(names)),
                               ("walkers", saved["n_walkers"] != n_walkers)) if v]
        raise ChainFileError(f"{path}: this chain was sampled with other {', '.join(what) or 'settings'} — "
                             f"continue it with the same data and options, or choose another --chain file")
    return backend, saved


def write_frame(path, *, names, fp: str, n_walkers: int, ndim: int, center, covariance) -> None:
    """Store the sampling frame of a new chain (group ``estcal``)."""
    h5py = require("h5py", "an MCMC chain file (--chain)")

    with h5py.File(path, "a") as f:
        if "estcal" in f:
            del f["estcal"]
        g = f.create_group("estcal")
        g.create_dataset("center", data=np.asarray(center, float))
        g.create_dataset("covariance", data=np.asarray(covariance, float))
        g.attrs["info"] = json.dumps({"fingerprint": fp, "names": list(names), "n_walkers": int(n_walkers),
                                      "ndim": int(ndim)})
