"""Progress bars: quiet in pipes and CI, visible on a terminal or when forced, outermost bar only."""
from __future__ import annotations

import io

import pytest

import estcal.progress as prog
from estcal.progress import progress, progress_enabled


class _TTY(io.StringIO):
    def isatty(self):
        return True


@pytest.fixture
def clean_env(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.delenv("ESTCAL_PROGRESS", raising=False)
    return monkeypatch


def test_quiet_when_stderr_is_not_a_terminal(clean_env, capsys):
    assert not progress_enabled()  # pytest's captured stderr is no TTY
    total = 0
    with progress(range(50), desc="quiet-bar", delay=0) as bar:
        for i in bar:
            total += i
    assert total == sum(range(50))  # the stand-in iterates like the iterable
    with progress(total=5, desc="quiet-manual") as bar:
        bar.update(5)
        bar.set_postfix(x=1)
    err = capsys.readouterr().err
    assert "quiet" not in err and err == ""


def test_visible_when_forced(clean_env, capsys):
    with progress(total=4, desc="forced-bar", enabled=True) as bar:
        for _ in range(4):
            bar.update(1)
    assert "forced-bar" in capsys.readouterr().err
    clean_env.setenv("ESTCAL_PROGRESS", "1")
    for _ in progress(range(3), desc="env-forced"):
        pass
    assert "env-forced" in capsys.readouterr().err


def test_terminal_ci_and_env_rules(clean_env):
    tty = _TTY()
    assert progress_enabled(stream=tty)
    clean_env.setenv("CI", "true")
    assert not progress_enabled(stream=tty)  # CI logs stay clean even on a pseudo-terminal
    assert progress_enabled(True, stream=tty)
    clean_env.delenv("CI")
    clean_env.setenv("ESTCAL_PROGRESS", "0")
    assert not progress_enabled(stream=tty)


def test_on_a_terminal_only_the_outermost_bar_draws(clean_env):
    tty = _TTY()
    clean_env.setattr(prog.sys, "stderr", tty)
    with progress(total=2, desc="outer", delay=0) as outer:
        assert not isinstance(outer, prog._Quiet)
        inner = progress(total=3, desc="inner", delay=0)
        assert isinstance(inner, prog._Quiet)  # nested automatic bar: quiet
        inner.close()
        outer.update(2)
    assert "outer" in tty.getvalue() and "inner" not in tty.getvalue()
    again = progress(total=1, desc="next", delay=0)  # the outer one closed: bars draw again
    assert not isinstance(again, prog._Quiet)
    again.close()
    assert prog._open_auto == 0
