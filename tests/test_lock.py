"""The run lock of state and chain files (estcal.base.lock, docs/reliability.md "Resuming interrupted work")."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from estcal.base.lock import LockedError, RunLock, lock_path


def test_second_holder_is_refused_and_release_frees(tmp_path):
    f = tmp_path / "s.json"
    a = RunLock(f, "--state").acquire()
    assert lock_path(f).read_text().strip() == str(os.getpid())
    with pytest.raises(LockedError, match=rf"s\.json: in use by another running estcal process \(pid {os.getpid()}\)"
                                          r" — wait for it to finish, or give this run another --state"):
        RunLock(f, "--state").acquire()
    a.release()
    assert not lock_path(f).exists()
    with RunLock(f):
        pass


def test_lock_of_a_killed_process_is_free(tmp_path):
    """The kernel drops a flock with its process: a kill -9 leaves a lock file, not a lock."""
    f = tmp_path / "s.json"
    code = f"from estcal.base.lock import RunLock; import os; RunLock({str(f)!r}).acquire(); os._exit(0)"
    subprocess.run([sys.executable, "-c", code], check=True)
    assert lock_path(f).exists()
    with RunLock(f):
        pass


def test_mcmc_chain_is_locked(tmp_path):
    from estcal.estimate.chainfile import ChainFileError
    from estcal.estimate.mcmc import sample_posterior

    chain = tmp_path / "c.h5"
    with RunLock(chain, "--chain"):
        with pytest.raises(ChainFileError, match=r"c\.h5: in use by another running estcal process"):
            sample_posterior(None, chain=str(chain))
    with pytest.raises(ChainFileError, match=r"is a folder"):
        sample_posterior(None, chain=str(tmp_path))
