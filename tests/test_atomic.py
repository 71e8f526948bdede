"""Atomic output files (estcal.base.atomic): complete file or the old one, never a partial one."""
import os
import subprocess
import sys
import textwrap

import pytest

from estcal.base.atomic import atomic_write, atomic_write_bytes, atomic_write_text


def test_replaces_content_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "sub" / "out.txt"
    atomic_write_text(p, "old")
    atomic_write_text(p, "new")
    assert p.read_text() == "new"
    assert os.listdir(p.parent) == ["out.txt"]
    atomic_write_bytes(p, b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01"


def test_exception_keeps_old_file(tmp_path):
    p = tmp_path / "out.txt"
    atomic_write_text(p, "old")
    with pytest.raises(RuntimeError):
        with atomic_write(p) as fh:
            fh.write("half")
            raise RuntimeError("boom")
    assert p.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_killed_writer_leaves_old_file(tmp_path):
    """SIGKILL in the middle of a large write: the target still holds the old content."""
    p = tmp_path / "out.txt"
    atomic_write_text(p, "old")
    code = textwrap.dedent(f"""
        import os, signal
        from estcal.base.atomic import atomic_write
        with atomic_write({str(p)!r}) as fh:
            fh.write("x" * 1_000_000)
            fh.flush()
            os.kill(os.getpid(), signal.SIGKILL)
    """)
    r = subprocess.run([sys.executable, "-c", code])
    assert r.returncode == -9
    assert p.read_text() == "old"


def test_bad_mode():
    with pytest.raises(ValueError, match="mode"):
        with atomic_write("x", "a"):
            pass


def test_new_file_has_the_permissions_of_a_plain_write(tmp_path):
    """A temporary file is created 0600; the renamed output must not be (others could not read it)."""
    plain = tmp_path / "plain.txt"
    with open(plain, "w") as fh:  # what the user's umask gives an ordinary write
        fh.write("x")
    atomic_write_text(tmp_path / "atomic.txt", "x")
    assert (tmp_path / "atomic.txt").stat().st_mode & 0o7777 == plain.stat().st_mode & 0o7777


def test_replaced_file_keeps_its_permissions(tmp_path):
    target = tmp_path / "out.csv"
    target.write_text("old")
    os.chmod(target, 0o640)
    atomic_write_text(target, "new")
    assert target.read_text() == "new" and target.stat().st_mode & 0o7777 == 0o640
