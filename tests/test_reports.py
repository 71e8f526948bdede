"""``--report DIR`` of calibrate, online, design, next-pose and diagnose, and the MCMC terminal summary.

Each report is produced through the CLI on a small simulated dataset. Checks: index.html
references every PNG of the folder (and only existing ones), the PNGs are valid images,
the HTML tables hold the JSON's numbers, and each figure shows the right data — the
figures are captured while the CLI saves them and their artists are compared with the
JSON (or with an independent computation from the input files).
"""
from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from test_calibrate_cli import TRUE_DELTA, _simulate  # the same simulated PUMA 560 pose data

from estcal.cli.main import app
from estcal.io.dataset import write_dataset
from estcal.kinematics import puma560
from estcal.base.units import display_unit

FREE = ",".join(TRUE_DELTA)  # every perturbed parameter of the simulated truth
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------ helpers
class _Page(HTMLParser):
    """Tables (by id: list of rows of cell texts) and image sources of an index.html."""

    def __init__(self):
        super().__init__()
        self.tables, self.images, self.links = {}, [], []
        self._tab = self._row = self._cell = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table":
            self._tab = a.get("id", "").removeprefix("table-")
            self.tables[self._tab] = []
        elif tag == "tr" and self._tab is not None:
            self._row = []
        elif tag in ("td", "th") and self._row is not None:
            self._cell = ""
        elif tag == "img":
            self.images.append(a["src"])
        elif tag == "a":
            self.links.append(a["href"])

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._row.append(self._cell)
            self._cell = None
        elif tag == "tr" and self._row is not None:
            self.tables[self._tab].append(self._row)
            self._row = None
        elif tag == "table":
            self._tab = None


def _page(folder) -> _Page:
    p = _Page()
    p.feed((Path(folder) / "index.html").read_text())
    return p


def _body(page, key):
    """Rows of a table without its header."""
    return page.tables[key][1:]


def _num(text):
    return float("nan") if text == "—" else float(text)


def _check_folder(folder):
    """index.html shows every PNG of the folder and nothing else; each is a valid, non-empty PNG."""
    import matplotlib.image as mpimg

    page = _page(folder)
    pngs = sorted(p.name for p in Path(folder).glob("*.png"))
    assert pngs, "no figure written"
    assert sorted(page.images) == pngs
    for name in pngs:
        raw = (Path(folder) / name).read_bytes()
        assert raw[:8] == PNG_MAGIC and len(raw) > 1000, name
        img = mpimg.imread(Path(folder) / name)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100, name
    assert not list(Path(folder).glob(".*.tmp")), "temporary files left behind"
    return page


@pytest.fixture(scope="module")
def captured():
    """Record every figure the report code saves ({file name: Figure}) while the CLI runs."""
    import estcal.report.diagnose as rdiag
    import estcal.report.figures as figures
    import estcal.report.html as rhtml

    figs = {}
    orig = figures.save_figure

    def record(fig, path, dpi=90):
        figs[Path(path).name] = fig
        return orig(fig, path, dpi)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(figures, "save_figure", record)
        mp.setattr(rhtml, "save_figure", record)
        mp.setattr(rdiag, "save_figure", record)
        yield figs


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("reports")
    return d, _simulate(d, 30, 1, "train.csv")[0], _simulate(d, 15, 2, "val.csv")[0]


def _invoke(args):
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    return r


def _units(names):
    robot = puma560()
    return np.array([display_unit(n, robot)[1] for n in names])


# ------------------------------------------------------------------ calibrate
@pytest.fixture(scope="module")
def calib(data, captured):
    d, train, val = data
    folder = d / "rep_lm"
    r = _invoke(["calibrate", str(train), "-r", "puma560", "--free", FREE, "--validate", str(val),
                 "--noise-pos-mm", "0.01", "--noise-rot-mrad", "0.1", "--json", str(d / "lm.json"),
                 "--report", str(folder)])
    figs = {k: captured[k] for k in ("pose_errors.png", "pose_errors_rotation.png", "residual_vs_joints.png",
                                     "parameters.png", "correlation.png")}
    return folder, json.loads((d / "lm.json").read_text()), figs, r.output


def test_calibrate_report_files_and_tables(calib):
    folder, js, _, out = calib
    page = _check_folder(folder)
    assert "result.json" in page.links
    assert json.loads((folder / "result.json").read_text())["parameters"] == js["parameters"]
    names = list(js["parameters"])
    f = _units(names)
    rows = _body(page, "parameters")
    assert [r[0] for r in rows] == names
    for r, n, k in zip(rows, names, f):
        p = js["parameters"][n]
        np.testing.assert_allclose([_num(r[1]), _num(r[2]), _num(r[3])],
                                   [p["nominal"] * k, p["estimate"] * k, p["std"] * k], rtol=1e-5)
    acc = _body(page, "accuracy")
    sets = [js["accuracy"]["train"]] + js["accuracy"]["validation"]
    assert len(acc) == 2 and acc[0][0].startswith("calibration:") and acc[1][0].startswith("validation:")
    for r, s in zip(acc, sets):
        assert int(r[1]) == s["after"]["n_poses"]
        np.testing.assert_allclose([_num(r[2]), _num(r[3]), _num(r[5]), _num(r[7])],
                                   [s["before"]["rmse_mm"], s["after"]["rmse_mm"], s["after"]["max_mm"],
                                    s["after"]["rmse_mrad"]], rtol=1e-5)
    assert "it/s" not in out and "calibrate (lm" not in out  # no progress bar outside a terminal


def test_calibrate_parameter_bars_are_two_sigma(calib):
    _, js, figs, _ = calib
    names = list(js["parameters"])
    f = _units(names)
    got = {}
    for ax in figs["parameters.png"].axes:
        (cont,) = ax.containers
        labels = [t.get_text() for t in ax.get_yticklabels()]
        x = cont.lines[0].get_xdata()
        segs = cont.lines[2][0].get_segments()
        for lab, xi, seg in zip(labels, x, segs):
            got[lab] = (xi, (seg[1][0] - seg[0][0]) / 2)
    assert set(got) == set(names)
    for n, k in zip(names, f):
        p = js["parameters"][n]
        np.testing.assert_allclose(got[n][0], (p["estimate"] - p["nominal"]) * k, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got[n][1], 2 * p["std"] * k, rtol=1e-9)


def test_calibrate_correlation_map_is_the_covariance_correlation(calib):
    _, js, figs, _ = calib
    C = np.array(js["covariance"])
    expect = C / np.sqrt(np.outer(np.diag(C), np.diag(C)))
    (img,) = figs["correlation.png"].axes[0].get_images()
    np.testing.assert_allclose(np.asarray(img.get_array()), expect, atol=1e-12)


def test_calibrate_error_plots_show_each_pose(calib, data):
    _, js, figs, _ = calib
    from estcal.io.dataset import load_dataset

    sets = [js["accuracy"]["train"]] + js["accuracy"]["validation"]
    for fname, key in (("pose_errors.png", "mm"), ("pose_errors_rotation.png", "mrad")):
        axes = figs[fname].axes
        assert len(axes) == 2  # validation in its own panel
        for ax, s in zip(axes, sets):
            lines = {ln.get_gid(): ln.get_ydata() for ln in ax.get_lines()}
            assert len(lines["after"]) == s["after"]["n_poses"]
            for when in ("before", "after"):  # the RMS of the plotted poses is the table's RMSE
                np.testing.assert_allclose(np.sqrt(np.mean(np.asarray(lines[when]) ** 2)), s[when][f"rmse_{key}"],
                                           rtol=1e-9)
    # residual vs joints: x = the file's joint readings in degrees, one series per dataset
    robot = puma560()
    d, train, val = data
    readings = [load_dataset(p, robot).readings for p in (train, val)]
    axes = [ax for ax in figs["residual_vs_joints.png"].axes if ax.get_lines()]
    assert len(axes) == robot.n_joints
    for j, ax in enumerate(axes):
        series = [ln for ln in ax.get_lines() if (ln.get_gid() or "").startswith("set")]
        for k, ln in enumerate(series):
            np.testing.assert_allclose(ln.get_xdata(), np.degrees(readings[k][:, j]), rtol=1e-12)
            np.testing.assert_allclose(np.sqrt(np.mean(np.asarray(ln.get_ydata()) ** 2)), sets[k]["after"]["rmse_mm"],
                                       rtol=1e-9)


# ------------------------------------------------------------------ MCMC
@pytest.fixture(scope="module")
def mcmc(data, captured):
    d, train, _ = data
    folder = d / "rep_mcmc"
    r = _invoke(["calibrate", str(train), "-r", "puma560", "--free", "offset_2,offset_3,a_2", "--estimator", "mcmc",
                 "--option", "target_ess=100", "--option", "min_steps=60", "--option", "check_every=30",
                 "--json", str(d / "mcmc.json"), "--report", str(folder)])
    return folder, json.loads((d / "mcmc.json").read_text()), captured["posterior_corner.png"], r.output


def _decimals(text):
    return len(text.split(".")[1]) if "." in text else 0


def test_mcmc_terminal_summary_equals_json(mcmc):
    _, js, _, out = mcmc
    names = list(js["parameters"])
    f = _units(names)
    assert "2.5 %" in out and "97.5 %" in out and "ESS" in out and "τ (steps)" in out
    for i, (n, k) in enumerate(zip(names, f)):
        line = next(ln for ln in out.splitlines() if re.match(rf"^│ {n}\s+│", ln) and ln.count("│") == 8)
        cells = [c.strip() for c in line.strip("│").split("│")]
        lo, med, hi, ess, tau = cells[1:6]
        expect = [js["credible_intervals"][n][0] * k, js["posterior_median"][i] * k, js["credible_intervals"][n][1] * k]
        for txt, v in zip((lo, med, hi), expect):  # printed to the shown decimals
            assert abs(float(txt) - v) <= 0.51 * 10 ** -_decimals(txt), (n, txt, v)
        assert float(ess) == pytest.approx(js["ess"][i], rel=1e-4)
        assert float(tau) == pytest.approx(js["tau"][i], rel=1e-4)
        assert float(lo) < float(med) < float(hi)


def test_mcmc_report_table_and_corner_quantiles(mcmc):
    folder, js, fig, _ = mcmc
    page = _check_folder(folder)
    names = list(js["parameters"])
    f = _units(names)
    rows = _body(page, "mcmc")
    for i, (r, n, k) in enumerate(zip(rows, names, f)):
        assert r[0] == n
        lo, hi = js["credible_intervals"][n]
        for txt, v in ((r[1], lo * k), (r[3], hi * k)):
            assert _decimals(txt) >= 4 and abs(float(txt) - v) <= 0.51 * 10 ** -_decimals(txt), (n, txt, v)
        assert _num(r[4]) == pytest.approx(js["ess"][i], rel=1e-5)
    # corner: the dashed quantile lines of each marginal are the JSON's interval and median
    # (shown as change from the initial value, display units)
    p = len(names)
    axes = np.array(fig.axes).reshape(p, p)
    for i, (n, k) in enumerate(zip(names, f)):
        nominal = js["parameters"][n]["nominal"]
        xs = sorted(ln.get_xdata()[0] for ln in axes[i, i].get_lines() if ln.get_linestyle() == "--")
        lo, hi = js["credible_intervals"][n]
        np.testing.assert_allclose(xs, [(lo - nominal) * k, (js["posterior_median"][i] - nominal) * k,
                                        (hi - nominal) * k], rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------ online
def test_online_report(data, captured):
    d, train, _ = data
    folder = d / "rep_online"
    _invoke(["online", str(train), "-r", "puma560", "--free", FREE, "--noise-pos-mm", "0.01", "--noise-rot-mrad", "0.1",
             "--json", str(d / "online.json"), "--report", str(folder)])
    js = json.loads((d / "online.json").read_text())
    page = _check_folder(folder)
    names = list(js["parameters"])
    f = _units(names)
    for r, n, k in zip(_body(page, "parameters"), names, f):
        p = js["parameters"][n]
        assert r[0] == n
        np.testing.assert_allclose([_num(r[1]), _num(r[2]), _num(r[3])],
                                   [p["nominal"] * k, p["estimate"] * k, p["std"] * k], rtol=1e-5)
    tests = dict((r[0], r[1]) for r in _body(page, "innovation"))
    assert _num(tests["NIS per measured row (expected 1)"]) == pytest.approx(js["innovation"]["nis_mean_per_row"],
                                                                             rel=1e-5)
    assert _num(tests["Ljung–Box p-value"]) == pytest.approx(js["innovation"]["ljung_box_p_value"], rel=1e-5)
    # the figure: one point per row, each estimate line ends at the final estimate
    fig = captured["online_history.png"]
    lines = {ln.get_gid(): ln for ax in fig.axes for ln in ax.get_lines() if ln.get_gid()}
    assert len(lines["nis"].get_xdata()) == js["n_rows"]
    for n, k in zip(names, f):
        p = js["parameters"][n]
        y = lines[n].get_ydata()
        assert len(y) == js["n_rows"]
        assert y[-1] == pytest.approx((p["estimate"] - p["nominal"]) * k, rel=1e-9, abs=1e-12)
    # rows outside the 95 % bounds are the circled ones (counted independently with scipy)
    from scipy import stats

    nis = np.asarray(lines["nis"].get_ydata())
    m = 6  # a pose row: 3 position + 3 orientation components
    burn = js["innovation"]["burn_in"]
    out = (nis < stats.chi2.ppf(0.025, m)) | (nis > stats.chi2.ppf(0.975, m))
    assert len(lines["nis_outside"].get_xdata()) == int(out[burn:].sum())
    # … and their fraction is the JSON's (the innovation tests count the same rows)
    assert out[burn:].mean() == pytest.approx(js["innovation"]["nis_outside_95"], rel=1e-12)


# ------------------------------------------------------------------ design / next-pose
def test_design_report(data, captured):
    d, _, _ = data
    folder = d / "rep_design"
    _invoke(["design", "-r", "puma560", "--n", "15", "--restarts", "1", "--random-plans", "100",
             "--n-candidates", "200", "--map", "150", "--json", str(d / "design.json"), "--report", str(folder)])
    js = json.loads((d / "design.json").read_text())
    page = _check_folder(folder)
    plan = np.array(js["plan"]["readings_deg"])
    np.testing.assert_allclose([[_num(c) for c in r[1:]] for r in _body(page, "plan")], plan, rtol=1e-5)
    crit = dict((r[0], _num(r[1])) for r in _body(page, "criteria"))
    for k in ("D", "A", "E", "cond"):
        assert crit[k] == pytest.approx(js["criteria"][k], rel=1e-5)
    base = dict((r[0], _num(r[1])) for r in _body(page, "baseline"))
    assert base["optimised plan"] == pytest.approx(js["plan"]["value"], rel=1e-5)
    assert base["min"] == pytest.approx(js["baseline"]["min"], rel=1e-5)
    (row,) = _body(page, "accuracy_map")
    assert _num(row[1]) == pytest.approx(js["accuracy_map"]["summary"]["mean_m"] * 1e3, rel=1e-5)
    # workspace map: positions and colours are the JSON's map (mm); the plan's poses are marked
    amap = js["accuracy_map"]
    ax = captured["accuracy_map.png"].axes[0]
    (sc,) = ax.collections
    order = np.argsort(amap["std"])
    np.testing.assert_allclose(sc.get_array(), np.array(amap["std"])[order] * 1e3, rtol=1e-12)
    np.testing.assert_allclose(sc.get_offsets(), np.array(amap["xyz"])[order][:, :2] * 1e3, rtol=1e-12)
    (marks,) = [ln for ln in ax.get_lines() if ln.get_label() == "plan poses"]
    assert len(marks.get_xdata()) == 15
    # baseline histogram: the red line is the plan's criterion value
    (hist_ax,) = captured["baseline.png"].axes
    (plan_line,) = [ln for ln in hist_ax.get_lines() if ln.get_gid() == "plan"]
    assert plan_line.get_xdata()[0] == pytest.approx(js["plan"]["value"], rel=1e-12)


def test_next_pose_report(data, calib, captured):
    d, _, _ = data
    folder = d / "rep_next"
    _invoke(["next-pose", "-r", "puma560", "--state", str(d / "lm.json"), "--n-candidates", "200", "--no-refine",
             "--map", "120", "--json", str(d / "next.json"), "--report", str(folder)])
    js = json.loads((d / "next.json").read_text())
    page = _check_folder(folder)
    (row,) = _body(page, "next")
    np.testing.assert_allclose([_num(c) for c in row[1:]], js["next"]["readings_deg"], rtol=1e-5)
    lm = json.loads((d / "lm.json").read_text())["parameters"]
    f = _units(list(lm))
    for r, k in zip(_body(page, "param_std"), f):
        assert _num(r[1]) == pytest.approx(lm[r[0]]["std"] * k, rel=1e-5)
        assert _num(r[2]) == pytest.approx(js["next"]["predicted_std"][r[0]] * k, rel=1e-5)
    before, after = (np.array(js["accuracy_map"][w]["std"]) for w in ("before", "after"))
    # same poses, and one more measurement never increases the predicted error
    assert js["accuracy_map"]["before"]["xyz"] == js["accuracy_map"]["after"]["xyz"]
    assert np.all(after <= before * (1 + 1e-9))
    cols = [ax.collections[0] for ax in captured["accuracy_map.png"].axes if ax.collections]
    np.testing.assert_allclose(np.sort(cols[0].get_array()), np.sort(before) * 1e3, rtol=1e-12)
    np.testing.assert_allclose(np.sort(cols[3].get_array()), np.sort(after) * 1e3, rtol=1e-12)


# ------------------------------------------------------------------ diagnose
def test_diagnose_report(tmp_path, captured):
    from estcal.discrepancy import diagnose, partial_joint_residuals
    from estcal.discrepancy.hidden import simulate_hidden
    from estcal.io.robotfile import load_robot
    from estcal.methods import NoiseModel, Problem

    sigma = 5e-5
    sim, _ = simulate_hidden(load_robot("puma560_masses"), [("joint_compliance", ["j3"], 10.0)], sigma,
                             n_poses=30, measure="position", seed=4)
    csv = write_dataset(tmp_path / "data.csv", sim.dataset)
    folder = tmp_path / "rep"
    _invoke(["diagnose", str(csv), "-r", "puma560_masses", "--noise-pos-mm", str(sigma * 1e3), "--known-noise",
             "--effects", "joint_compliance,encoder_gain", "--folds", "3", "--json", str(tmp_path / "d.json"),
             "--report", str(folder)])
    js = json.loads((tmp_path / "d.json").read_text())
    page = _check_folder(folder)
    assert {"diagnosis.json", "summary.txt"} <= set(page.links)
    rows = _body(page, "causes")
    assert [(r[0], r[1]) for r in rows] == [("joint_compliance", "j3")]
    c = js["causes"][0]
    v = c["parameters"][rows[0][2]]
    np.testing.assert_allclose([_num(rows[0][3]), _num(rows[0][4]), _num(rows[0][6])],
                               [v["display"][0], v["display"][1], c["ln_bf"]], rtol=1e-5)
    acc = {r[0]: r for r in _body(page, "accuracy")}
    assert _num(acc["expected at new postures"][1]) == pytest.approx(js["answer"]["expected_mm"], rel=1e-5)
    assert _num(acc["95 % of points within"][1]) == pytest.approx(js["answer"]["bound95_mm"], rel=1e-5)
    # partial residuals: per joint, x = the joint readings, y = δq̂ (mrad) of the model's geometry alone (its effects
    # at zero), computed here by the analysis function on the model the same diagnosis returns
    res = diagnose(load_robot("puma560_masses"), sim.dataset, noise=sigma, effects=["joint_compliance", "encoder_gain"],
                   k_folds=3)
    rb = res.robot
    geo = np.where(np.array([k == "effect" for k in rb.params.kinds]), 0.0, rb.params.values)
    dq, _ = partial_joint_residuals(Problem(rb, [(None, res.fit_data, NoiseModel.parse(sigma, known=True))]), geo)
    axes = [ax for ax in captured["partial_residuals.png"].axes if ax.get_lines()]
    assert len(axes) == dq.shape[1]
    for j, ax in enumerate(axes):
        ln = ax.get_lines()[0]
        np.testing.assert_allclose(ln.get_xdata(), sim.dataset.readings[:, j], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ln.get_ydata(), dq[:, j] * 1e3, rtol=1e-9, atol=1e-9)
