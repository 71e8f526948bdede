"""Progress bars: quiet in pipes and CI, visible on a terminal or when forced, outermost bar only."""
from __future__ import annotations

import io

import pytest

import estcal.base.progress as prog
from estcal.base.progress import progress, progress_enabled


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


def test_large_data_commands_show_a_bar(clean_env, tmp_path, capsys):
    """fk, identifiable, calibrate and online draw a bar on large files (here: forced, with the
    chunk size lowered so that a 300-pose file is "large"); stdout stays the result alone."""
    from typer.testing import CliRunner

    import estcal.methods.reduced as red
    import estcal.kinematics.chunked as chk
    from estcal.cli.main import app

    runner = CliRunner()
    data = tmp_path / "d.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "300", "--measure", "pose", "--seed", "2",
                            "-o", str(data)])
    assert r.exit_code == 0, r.output
    clean_env.setattr(red, "CHUNK_POSES", 100)
    clean_env.setattr(chk, "CHUNK", 100)
    clean_env.setenv("ESTCAL_PROGRESS", "1")
    runs = {"fk": ["fk", str(data), "--robot", "puma560", "-o", str(tmp_path / "fk.csv")],
            "poses (Jacobian)": ["identifiable", "--robot", "puma560", "--data", str(data)],
            "calibrate (lm": ["calibrate", str(data), "--robot", "puma560", "--allow-ill-conditioned"],
            "online": ["online", str(data), "--robot", "puma560", "--free", "offset_2,a_2", "--every", "1000"]}
    for label, args in runs.items():
        r = runner.invoke(app, args)
        assert r.exit_code == 0, (args, r.output)
        assert f"{label}" in r.stderr and "%|" in r.stderr, (label, r.stderr[-300:])
        assert "%|" not in r.stdout  # the bar never mixes into the result
