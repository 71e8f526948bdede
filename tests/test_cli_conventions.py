"""The conventions every subcommand shares (docs/conventions.md, "One vocabulary"; docs/reliability.md):

* commands are plain module-level functions, registered with ``estcal.cli.app.command``;
* one mapping of errors to exit codes (InputError 2, NumericalRefusal 3, MissingExtraError 2
  naming the pip extra, anything else 1) and ``EstcalWarning``s printed as ``warning:`` lines;
* ``estcal --version``, ``estcal robots``, ``--config FILE.toml``;
* ``estcal --help`` loads no numerical library (the command modules import their workflow when
  they run).
"""
from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from estcal.base.errors import EstcalWarning, InputError, MissingExtraError, NumericalRefusal
from estcal.cli.main import app

from conftest import REPO

runner = CliRunner()


def test_commands_are_module_level_functions():
    for cmd in app.registered_commands:
        fn = getattr(cmd.callback, "__wrapped__", cmd.callback)
        module = importlib.import_module(fn.__module__)
        assert getattr(module, fn.__name__) is fn, f"{cmd.name}: {fn.__qualname__} is not defined at module level"
        assert "<locals>" not in fn.__qualname__, cmd.name


def test_version_matches_the_package():
    import tomllib

    version = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.strip() == f"estcal {version}"
    p = subprocess.run([sys.executable, "-m", "estcal.cli.main", "--version"], capture_output=True, text=True)
    assert p.returncode == 0 and p.stdout.strip() == f"estcal {version}", p.stderr


def test_robots_lists_every_name_load_robot_accepts(tmp_path):
    from estcal.io.robotfile import load_robot, robot_names

    out = tmp_path / "robots.json"
    r = runner.invoke(app, ["robots", "--json", str(out)])
    assert r.exit_code == 0, r.output
    rows = {d["name"]: d for d in json.loads(out.read_text())}
    assert set(robot_names()) <= set(rows) and "left_hand" in rows
    puma = rows["puma560"]
    rb = load_robot("puma560")
    assert puma["joints"] == rb.n_joints == 6 and puma["parameters"] == len(rb.params.names)
    assert puma["joint_types"] == "RRRRRR" and rows["stanford"]["joint_types"] == "RRPRRR"
    assert rows["left_hand"]["kind"] == "parallel"
    assert "puma560 " in r.output and "Chapter 6" in r.output


def _guarded(func):
    from estcal.cli.run import guarded

    app_ = typer.Typer()
    app_.command("x")(guarded("x", func))
    app_.command("y")(lambda: None)
    return app_


@pytest.mark.parametrize("exc,code,text", [
    (InputError("bad.csv: line 3: not a number"), 2, "error: bad.csv: line 3: not a number"),
    (NumericalRefusal("4 poses for 6 parameters"), 3, "error: numerical refusal: 4 poses for 6 parameters"),
    (MissingExtraError("--scheduler local", "dask", "dask.distributed"), 2,
     "error: --scheduler local needs the optional dependency 'dask.distributed': pip install \"estcal[dask]\""),
])
def test_one_mapping_of_errors_to_exit_codes(exc, code, text):
    def x() -> None:
        raise exc

    r = runner.invoke(_guarded(x), ["x"])
    assert r.exit_code == code and r.stderr.strip() == text


def test_other_exceptions_are_internal_errors_exit_1():
    p = subprocess.run([sys.executable, "-c", "import sys\nfrom estcal.cli import main as m\nfrom estcal.cli.run import guarded\n"
                        "import typer\ndef boom():\n    raise RuntimeError('kaput')\n"
                        "m.app.command('boom')(guarded('boom', boom))\nsys.argv = ['estcal', 'boom']\nm.main()"],
                       capture_output=True, text=True)
    assert p.returncode == 1 and "internal error (RuntimeError: kaput)" in p.stderr, p.stderr


def test_estcal_warnings_are_printed_as_warning_lines():
    def x() -> None:
        warnings.warn("first", EstcalWarning)
        warnings.warn("first", EstcalWarning)  # every time, not once per place
        typer.echo("result")

    r = runner.invoke(_guarded(x), ["x"])
    assert r.exit_code == 0 and r.stdout.strip() == "result"
    assert r.stderr.splitlines() == ["warning: first", "warning: first"]


def test_a_missing_extra_is_named_not_a_bug(tmp_path):
    """fleet --scheduler local without dask: the extra to install, exit 2 (not 'internal error')."""
    fl = tmp_path / "fl"
    assert runner.invoke(app, ["simulate", "--fleet", "1", "--out", str(fl), "--n", "10"]).exit_code == 0
    code = ("import sys\nsys.modules['distributed'] = None\nsys.modules['dask'] = None\n"
            "from estcal.cli.main import main\nsys.argv = ['estcal'] + sys.argv[1:]\nmain()")
    p = subprocess.run([sys.executable, "-c", code, "fleet", str(fl), "--scheduler", "local"], capture_output=True,
                       text=True)
    assert p.returncode == 2, p.stderr
    assert "pip install \"estcal[dask]\"" in p.stderr and "bug" not in p.stderr, p.stderr


def test_config_file_holds_options_and_the_command_line_wins(tmp_path):
    cfg = tmp_path / "sim.toml"
    cfg.write_text('robot = "planar2"\nn = 7\nnoise-pos-mm = 0.05\n\n[simulate]\nseed = 3\n\n'
                   '[calibrate]\nknown-noise = true\n')
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    r = runner.invoke(app, ["simulate", "--config", str(cfg), "--json", str(a)])
    assert r.exit_code == 0, r.output
    d = json.loads(a.read_text())
    assert d["n_poses"] == 7 and d["seed"] == 3 and d["robot"] == "planar2"
    r = runner.invoke(app, ["simulate", "--config", str(cfg), "--n", "9", "--json", str(b)])
    assert r.exit_code == 0, r.output
    assert json.loads(b.read_text())["n_poses"] == 9  # the command line wins


def test_config_file_refuses_unknown_keys_naming_key_and_file(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('robot = "puma560"\nnoise-pos = 0.1\nnosuch = 1\n')
    p = subprocess.run([sys.executable, "-m", "estcal.cli.main", "design", "--config", str(cfg), "--n", "10"],
                       capture_output=True, text=True)
    assert p.returncode == 2
    assert "unknown key 'noise-pos'" in p.stderr and str(cfg) in p.stderr, p.stderr
    cfg.write_text('robot = "puma560"\nn = "ten"\n')
    p = subprocess.run([sys.executable, "-m", "estcal.cli.main", "design", "--config", str(cfg)],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "'--n'" in p.stderr and "integer" in p.stderr, p.stderr
    cfg.write_text('robot = "puma560"\nn = [1,\n')
    p = subprocess.run([sys.executable, "-m", "estcal.cli.main", "design", "--config", str(cfg)],
                       capture_output=True, text=True)
    assert p.returncode == 2 and str(cfg) in p.stderr, p.stderr


def test_help_imports_no_numerical_library():
    code = ("import sys\nimport estcal.cli.main\n"
            "heavy = [m for m in ('numpy', 'scipy', 'matplotlib', 'gtsam', 'filterpy', 'emcee', 'dask', 'yaml', "
            "'sklearn', 'rosbags') "
            "if m in sys.modules]\nprint(heavy)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0 and p.stdout.strip() == "[]", p.stdout + p.stderr


def test_commands_run_blas_single_threaded_unless_the_user_chose():
    from estcal.cli.main import single_threaded_blas_by_default

    env = {}
    single_threaded_blas_by_default(env)
    assert env["OPENBLAS_NUM_THREADS"] == "1"
    env = {"OMP_NUM_THREADS": "4"}
    single_threaded_blas_by_default(env)
    assert env == {"OMP_NUM_THREADS": "4"}
    code = ("import os, sys\nfrom estcal.cli.main import main\nsys.argv = ['estcal', 'robots']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\nprint('BLAS', os.environ.get('OPENBLAS_NUM_THREADS'))")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                           "MKL_NUM_THREADS")}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert p.returncode == 0 and "BLAS 1" in p.stdout, p.stdout + p.stderr


def test_every_number_rule_names_an_existing_option():
    """The option checks (estcal.cli.checks) have no rule for a flag no command has."""
    import inspect

    from estcal.cli.checks import NUMBER_RULES, _option_names

    options = set()
    for cmd in app.registered_commands:
        fn = getattr(cmd.callback, "__wrapped__", cmd.callback)
        options |= {o for o, _ in _option_names(inspect.signature(fn, eval_str=True)).values() if o}
    for names, _, _ in NUMBER_RULES:
        assert set(names) <= options, f"rules for options no command has: {sorted(set(names) - options)}"
