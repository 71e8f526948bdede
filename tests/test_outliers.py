"""Outliers named (docs/reliability.md): with 5 % injected gross errors kept in the fit (``--keep-all``)
every robust estimator names exactly the injected CSV lines, with weight and residual in σ, and reports σ0 / χ² with
and without them; estimators without a robust form refuse --robust with a message."""
import json

import numpy as np
import pytest
from scipy import stats
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.estimate.robust import kernel_threshold, kernel_weight

runner = CliRunner()
N = 80
NOISE = ["--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("out")
    clean = d / "clean.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", str(N), "--measure", "pose",
                            "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--seed", "7", "-o", str(clean)])
    assert r.exit_code == 0, r.output
    lines = clean.read_text().splitlines()
    head = lines[0].split(",")
    ix = [head.index(c) for c in "xyz"]
    rng = np.random.default_rng(3)
    bad = np.sort(rng.choice(N, 4, replace=False))  # 5 % of the poses
    for i in bad:
        vals = lines[i + 1].split(",")
        v = rng.standard_normal(3)
        v *= rng.uniform(1e-3, 4e-3) / np.linalg.norm(v)  # 1-4 mm: 20-80 σ
        for j, dv in zip(ix, v):
            vals[j] = repr(float(vals[j]) + float(dv))
        lines[i + 1] = ",".join(vals)
    path = d / "outliers.csv"
    path.write_text("\n".join(lines) + "\n")
    return path, sorted(int(i) + 2 for i in bad)  # CSV line numbers (header = line 1)


CASES = [("lm", "cauchy", []), ("lm", "huber", []), ("gtsam", "cauchy", []),
         ("kalman", "cauchy", []), ("gtsam-timevarying", "cauchy", ["--option", "q=0.000001"])]


@pytest.mark.parametrize("estimator, kernel, extra", CASES)
def test_named_rows_are_the_injected_ones(data, tmp_path, estimator, kernel, extra):
    path, injected = data
    out = tmp_path / "r.json"
    # --keep-all: the kernel on every row (by default the screening leaves these rows out before the fit)
    r = runner.invoke(app, ["calibrate", str(path), "--robot", "puma560", "--estimator", estimator, "--robust", kernel,
                            "--keep-all", *NOISE, *extra, "--json", str(out)])
    assert r.exit_code == 0, r.output
    rep = json.loads(out.read_text())["robust_report"]
    named = sorted(d["line"] for d in rep["rows"])
    assert named == injected, (named, injected)
    for d in rep["rows"]:
        assert f"line {d['line']}: weight" in r.output
        # independent: the kernel at the 6-row pose threshold, from the reported residual
        assert np.isclose(d["weight"], kernel_weight(kernel, d["residual_sigma"], kernel_threshold(kernel, 6)))
        assert d["residual_sigma"] > 15
    # σ0 without the outliers is at the noise level; with them it is not
    assert 0.8 < rep["sigma0_without_named"] < 1.2 and rep["sigma0_all"] > 3
    assert rep["dof_all"] - rep["dof_without_named"] == 6 * len(injected)


def test_irls_is_the_factor_graph_m_estimate(data):
    """Least squares by IRLS and gtsam's robust LM minimise the same objective (independent solvers)."""
    from estcal.workflows.calibrate import run_calibration
    from estcal.io import load_dataset
    from estcal.kinematics.robots import get_builtin
    from estcal.methods import NoiseModel

    rb = get_builtin("puma560")
    ds = load_dataset(data[0], rb)
    noise = NoiseModel(position=5e-5, orientation=5e-4)
    a = run_calibration(rb, ds, estimator="lm", noise=noise, options={"robust": "cauchy"})[0]
    b = run_calibration(rb, ds, estimator="gtsam", noise=noise, options={"robust": "cauchy"})[0]
    assert a.names == b.names
    assert np.all(np.abs(a.estimate - b.estimate) < 1e-3 * a.std)


def test_kernel_threshold_keeps_the_scalar_inlier_probability():
    for kernel, k in (("huber", 1.345), ("cauchy", 2.385)):
        p = stats.norm.cdf(k) - stats.norm.cdf(-k)
        for m in (1, 3, 6):
            km = kernel_threshold(kernel, m)
            # Monte Carlo: the fraction of clean m-row groups inside k_m is the scalar one
            z = np.random.default_rng(m).standard_normal((200_000, m))
            assert abs(np.mean(np.linalg.norm(z, axis=1) <= km) - p) < 4e-3
        assert kernel_threshold(kernel, 1) == k


@pytest.mark.parametrize("estimator, words", [("ukf", "UKF has no robust update"),
                                              ("mcmc", "no robust likelihood")])
def test_robust_refused_with_a_message(data, estimator, words):
    r = runner.invoke(app, ["calibrate", str(data[0]), "--robot", "puma560", "--estimator", estimator,
                            "--robust", "cauchy"])
    assert r.exit_code == 2 and words in r.output


def test_chi2_quantiles_are_scipy_stats():
    """The χ² quantile, cdf and median the robust tests use (scipy.special, no scipy.stats import)
    equal scipy.stats.chi2 over the degrees of freedom and levels in use (1–18 rows per group,
    Bonferroni levels down to 1e-9)."""
    from estcal.estimate.robust import chi2_cdf, chi2_median, chi2_ppf

    d = np.array([1, 2, 3, 6, 12, 18, 2.5])
    for p in (1e-9, 0.05, 0.5, 0.9, 1 - 1e-9):
        np.testing.assert_allclose(chi2_ppf(p, d), stats.chi2.ppf(p, d), rtol=1e-12)
    np.testing.assert_allclose(chi2_median(d), stats.chi2.median(d), rtol=1e-12)
    x = np.linspace(0.01, 40, 9)
    np.testing.assert_allclose(chi2_cdf(x[:, None], d), stats.chi2.cdf(x[:, None], d), rtol=1e-12)
