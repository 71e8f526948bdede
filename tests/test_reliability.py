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


def test_few_distinct_postures_refused_before_any_qr_of_the_data(files, tmp_path, monkeypatch):
    """5 distinct pose measurements (30 equations) repeated 400 times cannot identify the 30 parameters
    generic poses identify at the full level: refused from the generic count, before the registration
    and the selection's QR of the 2,000 rows; with --allow-ill-conditioned the later checks decide."""
    import estcal.estimate.registration as registration
    import estcal.workflows.calibrate as workflow

    rb = get_builtin("puma560")
    q = rb.random_readings(5, np.random.default_rng(6))
    path = _write(tmp_path / "five.csv", np.tile(q, (400, 1)))

    def untouched(*a, **k):
        raise AssertionError("the data were registered or factored before the refusal")

    monkeypatch.setattr(workflow, "select_free", untouched)
    monkeypatch.setattr(registration, "kabsch", untouched)
    r = _cal(path)
    assert r.exit_code == 3, r.output
    assert "only 5 distinct joint configuration(s) among 2000 poses" in r.output
    assert "at most 30 independent equations" in r.output and "identifies 30 parameters" in r.output


def test_generic_identifiable_set_is_computed_once_per_robot_structure(monkeypatch):
    """The structural reference is cached by the content of the robot and the measurement: a second
    dataset of the same robot (another registration, within the rounding) reuses it; a robot whose
    geometry differs, or another level, does not."""
    import estcal.estimate.checks as checks
    from estcal.methods import NoiseModel, Problem

    calls = []
    real = checks.select_free
    monkeypatch.setattr(checks, "select_free", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(checks, "_GENERIC_CACHE", {})
    rb = get_builtin("puma560")

    def problem(robot, seed):
        ds = simulate(robot, n_poses=20, measure="pose", noise=NOISE, seed=seed).dataset
        return Problem(robot, [(None, ds, NoiseModel(**NOISE))])

    p1, p2 = problem(rb, 1), problem(rb, 2)
    th2 = p2.params.values.copy()
    th2[p2.params.index("base_tx")] += 2e-4  # a registration 0.2 mm away rounds to the same point
    a = checks.generic_identifiable(p1, "full", p1.params.values)
    b = checks.generic_identifiable(p2, "full", th2)
    assert len(calls) == 1 and b is a and len(a.identifiable) == 30
    checks.generic_identifiable(p1, "joint_offset", p1.params.values)
    assert len(calls) == 2
    th = rb.params.values.copy()
    th[rb.params.index("d_4")] += 0.01
    other = rb.with_values(th)
    checks.generic_identifiable(problem(other, 1), "full", th)
    assert len(calls) == 3
