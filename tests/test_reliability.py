"""Honest results (docs/reliability.md): refusals on degenerate data, ill-conditioning and
non-convergence are errors (exit 3) unless --allow-ill-conditioned, implausible moves are named."""
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.estimate.checks import COND_MAX
from estcal.kinematics.robots import get_builtin
from estcal.simulate import simulate

runner = CliRunner()
NOISE = {"position": 5e-5, "orientation": 5e-4}


def _write(path, readings, errors="random"):
    simulate("puma560", measure="pose", readings=readings, errors=errors, noise=NOISE, seed=1).write(path)
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("rel")
    rb = get_builtin("puma560")
    q = rb.random_readings(40, np.random.default_rng(5))
    out = {"good": _write(d / "good.csv", q)}
    qs = q.copy()
    qs[:, 4] = 1e-4  # wrist 0.1 mrad from its singularity on every pose
    out["near"] = _write(d / "near.csv", qs)
    qs = q.copy()
    qs[:, 4] = 0.0  # exactly singular
    out["exact"] = _write(d / "exact.csv", qs)
    out["repeated"] = _write(d / "repeated.csv", np.repeat(q[:3], 14, axis=0))  # 3 poses, 14 times each
    out["few"] = _write(d / "few.csv", q[:4])
    out["far"] = _write(d / "far.csv", q, errors={"a_2": 0.06})  # a 60 mm error in a link length
    return out


def _cal(path, *extra):
    return runner.invoke(app, ["calibrate", str(path), "--robot", "puma560", *extra])


def test_good_data_pass_and_report_figures(files, tmp_path):
    out = tmp_path / "g.json"
    r = _cal(files["good"], "--json", str(out))
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    rel = d["reliability"]
    assert rel["refusals"] == [] and rel["warnings"] == []
    assert rel["distinct_poses"] == 40 and rel["dof"] == 40 * 6 - d["n_parameters"]
    assert rel["identifiable_here"] == rel["identifiable_generic"] == d["n_parameters"] == 30
    assert rel["condition_number"] < COND_MAX


@pytest.mark.parametrize("case, words", [
    ("near", ["generic poses identifies 30", "alpha_5"]),
    ("exact", ["generic poses identifies 30", "alpha_5"]),
    ("repeated", ["only 3 distinct joint configuration(s) among 42 poses", "repeated lines 3, 4, 5"]),
    ("few", ["24 equations for 24 free parameters", "degrees of freedom 0"]),
])
def test_degenerate_data_refused_with_exit_3(files, case, words):
    r = _cal(files[case])
    assert r.exit_code == 3, r.output
    assert "numerical refusal" in r.output and "Traceback" not in r.output
    for w in words:
        assert w in r.output, r.output


def test_near_singular_allowed_reports_conditioning(files, tmp_path):
    out = tmp_path / "n.json"
    r = _cal(files["near"], "--allow-ill-conditioned", "--json", str(out))
    assert r.exit_code == 0, r.output
    assert "warning:" in r.output and "degenerate data" in r.output
    rel = json.loads(out.read_text())["reliability"]
    assert rel["identifiable_here"] < rel["identifiable_generic"]
    assert rel["warnings"] and rel["refusals"] == []


def test_condition_number_matches_numpy(files, tmp_path):
    from estcal.io import load_dataset
    from estcal.methods import NoiseModel, Problem

    out = tmp_path / "n.json"
    r = _cal(files["near"], "--allow-ill-conditioned", "--json", str(out))
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    rb = get_builtin("puma560")
    ds = load_dataset(files["near"], rb)
    noise = NoiseModel(position=1e-4, orientation=1e-3)
    prob = Problem(rb, [(None, ds, noise)], noise)
    theta = np.array([d["theta"][n] for n in prob.params.names])
    rows = prob.evaluate(theta)
    A = rows.H[:, prob.params.indices(list(d["parameters"]))] / rows.sigma[:, None]
    A = A / np.linalg.norm(A, axis=0)
    assert np.isclose(d["reliability"]["condition_number"], np.linalg.cond(A), rtol=1e-6)
    assert d["reliability"]["condition_number"] > COND_MAX


def test_non_convergence_is_an_error_unless_allowed(files):
    r = _cal(files["good"], "--option", "max_iter=1")
    assert r.exit_code == 3 and "did not converge in 1 iterations" in r.output, r.output
    r = _cal(files["good"], "--option", "max_iter=1", "--allow-ill-conditioned")
    assert r.exit_code == 0 and "warning:" in r.output


def test_implausible_move_is_named(files):
    r = _cal(files["far"])
    assert r.exit_code == 0, r.output
    line = [ln for ln in r.output.splitlines() if "moved more than" in ln]
    assert line and "a_2 (" in line[0], r.output
    r = _cal(files["good"])
    assert "moved more than" not in r.output
