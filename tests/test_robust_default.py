"""Gross errors cannot dominate a default calibration (docs/reliability.md, "Gross errors").

100 good simulated PUMA 560 positions (CMM-like noise 0.02 mm) validated on 100 clean poses of the
same true robot; into the calibration file are written 5 blunders (x + 3–8 mm), or one wild reading
(j2 off by 1.5 rad, inside its limits, or beyond them), or one reading of j2 at 10.8 rad. The default
``estcal calibrate`` must score within 10 % of the clean file's fit on the validation poses and name
those rows first, by file and line, with their residual and the least-squares fit with them;
``--keep-all`` is plain least squares on every row (the default before: these tests failed on it).
On clean data the default estimate is the least-squares one (0.01 σ; several seeds and robots), and
the covariance stays honest (σ0² inside its χ² interval with the noise known).
"""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from scipy import stats
from typer.testing import CliRunner

import estcal
from estcal.base.errors import EstcalWarning
from estcal.cli.main import app
from estcal.workflows.calibrate import calibrate as calibrate_workflow

runner = CliRunner()
N = 100
NOISE_MM = 0.02
BLUNDER_ROWS = [6, 23, 47, 71, 90]  # 0-based rows; file line = row + 2
WILD_ROW = 58


def _invoke(*args):
    r = runner.invoke(app, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The clean calibration file, its validation file (same true robot, new poses) and the edited copies."""
    d = tmp_path_factory.mktemp("gross")
    _invoke("simulate", "--robot", "puma560", "--n", N, "--noise-pos-mm", NOISE_MM, "--seed", 11,
            "-o", d / "clean.csv", "--true-model", d / "true.yaml")
    _invoke("simulate", "--robot", d / "true.yaml", "--errors", "none", "--n", N, "--noise-pos-mm", NOISE_MM,
            "--seed", 12, "-o", d / "val.csv")
    lines = (d / "clean.csv").read_text().splitlines()
    head = lines[0].split(",")
    table = [ln.split(",") for ln in lines[1:]]

    def write(name, edit):
        rows = [list(r) for r in table]
        edit(rows)
        (d / name).write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
        return d / name

    rng = np.random.default_rng(5)
    jx, j2 = head.index("x"), head.index("j2")

    def blunders(rows):
        for i in BLUNDER_ROWS:
            rows[i][jx] = repr(float(rows[i][jx]) + rng.uniform(3e-3, 8e-3))

    def wild(rows):  # off by 1.5 rad and still inside j2's limits [-3.93, 0.785]
        q = float(rows[WILD_ROW][j2])
        rows[WILD_ROW][j2] = repr(q - 1.5 if q - 1.5 > -3.9 else q + 1.5)
        assert -3.92 < float(rows[WILD_ROW][j2]) < 0.78

    def beyond(rows):
        rows[WILD_ROW][j2] = "10.8"

    def wild_out(rows):  # off by 1.5 rad and beyond j2's upper limit 0.785
        rows[WILD_ROW][j2] = repr(float(rows[WILD_ROW][j2]) + 1.5)
        assert float(rows[WILD_ROW][j2]) > 0.8

    return {"dir": d, "clean": d / "clean.csv", "val": d / "val.csv", "blunders": write("blunders.csv", blunders),
            "wild": write("wild.csv", wild), "wild_out": write("wild_out.csv", wild_out),
            "beyond": write("beyond.csv", beyond)}


def _fit(files, name, *extra):
    out = files["dir"] / f"{name}{'_'.join(extra)}.json"
    r = _invoke("calibrate", files[name], "--robot", "puma560", "--validate", files["val"], "--json", out, *extra)
    return r.stdout, json.loads(out.read_text())


def _val(d):
    return d["rmse_mm"]["validation"][0]


@pytest.fixture(scope="module")
def clean_fit(files):
    return _fit(files, "clean")[1]


@pytest.mark.parametrize("case, lines", [("blunders", [i + 2 for i in BLUNDER_ROWS]), ("wild", [WILD_ROW + 2]),
                                         ("wild_out", [WILD_ROW + 2]), ("beyond", [WILD_ROW + 2])])
def test_gross_errors_do_not_dominate_the_default_fit(files, clean_fit, case, lines):
    out, d = _fit(files, case)
    kept_all = _fit(files, case, "--keep-all")[1]
    assert _val(d) <= 1.1 * _val(clean_fit), (case, _val(d), _val(clean_fit))
    assert _val(kept_all) > 1.5 * _val(clean_fit)  # least squares on every row: what the default was
    rep = d["left_out"]
    assert sorted(r["line"] for r in rep["rows"]) == lines
    assert rep["n_left_out"] == len(lines) and rep["n_rows"] == N
    # answer first: the report's first lines name every row by file and line with its residual, then both fits
    head = out.splitlines()[:len(lines) + 3]
    assert head[0].startswith(f"left out: {len(lines)} of {N} rows")
    for r in rep["rows"]:
        assert any(h.startswith(f"  {files[case]} line {r['line']}: residual {r['residual_mm']:.4g} mm") for h in head)
    assert head[len(lines) + 1].startswith("  without them (this fit): σ0")
    assert head[len(lines) + 2].startswith("  with them (least squares on every row): σ0")
    # the fit "with them" is the --keep-all fit (recomputed independently by the second run)
    w = rep["with"]
    assert w["sigma0"] == pytest.approx(kept_all["sigma0"], rel=1e-6)
    assert w["validation_rmse_mm"][0] == pytest.approx(_val(kept_all), rel=1e-6)
    assert rep["without"]["validation_rmse_mm"][0] == pytest.approx(_val(d), rel=1e-9)
    common = [n for n in d["parameters"] if n in kept_all["parameters"]]
    shift = max(abs(kept_all["parameters"][n]["estimate"] - d["parameters"][n]["estimate"])
                / d["parameters"][n]["std"] for n in common)
    assert w["max_shift_sigma"] == pytest.approx(shift, rel=1e-6)
    if case in ("beyond", "wild_out"):
        assert rep["rows"][0]["kind"] == "out_of_limits" and rep["rows"][0]["reason"].startswith("j2 = ")
    else:
        assert {r["kind"] for r in rep["rows"]} == {"outlier"}
    # the residual printed is the row's at the default estimate (recomputed from the estimate)
    robot = estcal.load_robot("puma560")
    data = estcal.load_dataset(files[case], robot)
    theta = robot.params.values.copy()
    for n, v in d["theta"].items():
        theta[robot.params.index(n)] = v
    from estcal.kinematics.chunked import tool_poses

    p = tool_poses(robot, data.readings, theta, data.context, fields=("p",))["p"]
    for r in rep["rows"]:
        i = list(data.lines).index(r["line"])
        assert np.linalg.norm(p[i] - data.points[i, 0]) * 1e3 == pytest.approx(r["residual_mm"], rel=1e-6)


def test_keep_all_is_plain_least_squares(files):
    """--keep-all fits every row (nothing left out) and is the estimator's plain least squares."""
    _, d = _fit(files, "blunders", "--keep-all")
    assert "left_out" not in d
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ls = estcal.calibrate("puma560", files["blunders"], checks=False)
    for n, e in zip(ls.names, ls.estimate):
        assert d["parameters"][n]["estimate"] == pytest.approx(e, rel=1e-9, abs=1e-12)


def test_api_same_default_and_keyword(files):
    with pytest.warns(EstcalWarning, match=r"5 of 100 rows left out .* --keep-all \(drop_flagged=False\)"):
        res = estcal.calibrate("puma560", files["blunders"], validate=[files["val"]])
    assert sorted(r["line"] for r in res.extra["left_out"]["rows"]) == [i + 2 for i in BLUNDER_ROWS]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ls = estcal.calibrate("puma560", files["blunders"], validate=[files["val"]], drop_flagged=False)
    assert "left_out" not in ls.extra
    assert ls.accuracy["validation"][0]["after"]["rmse_mm"] > 1.5 * res.accuracy["validation"][0]["after"]["rmse_mm"]


def _simulated(robot, measure, seed):
    from estcal.simulate.core import simulate

    return simulate(estcal.load_robot(robot), 60, measure=measure, errors="random", seed=seed,
                    noise={"position": 5e-5, "orientation": 5e-4}).dataset


@pytest.mark.parametrize("robot, measure", [("puma560", "position"), ("puma560", "pose"), ("stanford", "position"),
                                            ("5r1p", "pose")])
def test_clean_data_give_the_least_squares_estimate(robot, measure):
    """The default estimate is the least-squares one within 0.01 σ of every parameter (seeds 0–2)."""
    for seed in range(3):
        ds = _simulated(robot, measure, seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            default = estcal.calibrate(robot, ds)
            ls = estcal.calibrate(robot, ds, drop_flagged=False)
        assert "left_out" not in default.extra, (robot, measure, seed, default.extra.get("left_out"))
        assert default.names == ls.names
        assert np.max(np.abs(default.estimate - ls.estimate) / ls.std) <= 0.01
        np.testing.assert_allclose(default.std, ls.std, rtol=1e-6)


def test_covariance_stays_honest():
    """With the noise known, σ0² of the default fit is inside the 99.9 % χ²_dof/dof interval on clean data and
    on data with 5 blunders (the rows left out), where least squares on every row is far outside it."""
    from estcal.methods import NoiseModel

    noise = NoiseModel(position=5e-5, orientation=5e-4, known=True)
    ds = _simulated("puma560", "pose", 4)
    bad = ds.subset(np.arange(ds.n))
    bad.p = bad.p.copy()
    bad.p[[3, 17, 31, 44, 52], 0] += np.linspace(3e-3, 8e-3, 5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits = {"clean": calibrate_workflow("puma560", ds, noise=noise).result,
                "blunders": calibrate_workflow("puma560", bad, noise=noise).result,
                "ls": calibrate_workflow("puma560", bad, noise=noise, drop_flagged=False).result}
    for name in ("clean", "blunders"):
        r = fits[name]
        lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], r.dof) / r.dof
        assert lo < r.sigma0 ** 2 < hi, (name, r.sigma0, r.dof)
        assert r.covariance_source == "model"
    assert fits["ls"].sigma0 ** 2 > 100


def test_sessions_name_each_file_and_config_keeps_all(files):
    """Two sessions: the rows left out are named by their own file; `keep-all = true` in a --config file is
    --keep-all (the off switch of the pair --drop-flagged/--keep-all)."""
    out = files["dir"] / "two.json"
    _invoke("calibrate", files["blunders"], files["val"], "--robot", "puma560", "--json", out)
    rows = json.loads(out.read_text())["left_out"]["rows"]
    assert [(r["file"], r["line"]) for r in rows] == [(str(files["blunders"]), i + 2) for i in BLUNDER_ROWS]
    cfg = files["dir"] / "keep.toml"
    cfg.write_text("keep-all = true\n")
    _invoke("calibrate", files["blunders"], "--robot", "puma560", "--config", cfg, "--json", out)
    assert "left_out" not in json.loads(out.read_text())
