"""The innovation record in flat buffers (estcal.estimate.innovation) against a plain
list-of-arrays computation of the same tests, the journal's binary layout round trip,
and the bounded-memory readers used on large files (header-only CSV read, streamed lines)."""
import numpy as np
import pytest
from scipy import stats

from estcal.estimate.checkpoint import Journal, parse_journal
from estcal.estimate.innovation import GrowingArray, InnovationMonitor, ljung_box


def _steps(seed=0, n=300):
    """Innovations of mixed sizes (3 and 6 rows, as position and pose rows in one stream)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        m = 3 if rng.random() < 0.3 else 6
        A = rng.normal(size=(m, m))
        S = A @ A.T + m * np.eye(m)
        y = np.linalg.cholesky(S) @ rng.normal(size=m) + (0.3 if k % 17 == 0 else 0.0)
        out.append((y, S))
    return out


def _reference_tests(steps, burn, lags=10, alpha=0.05):
    """The tests of the module docstring written directly on a list of whitened vectors."""
    white = [np.linalg.solve(np.linalg.cholesky(S), y) for y, S in steps][burn:]
    nis = np.array([w @ w for w in white])
    dims = np.array([w.size for w in white])
    tot, dof = nis.sum(), dims.sum()
    cdf = stats.chi2.cdf(tot, dof)
    lo = np.array([stats.chi2.ppf(0.025, d) for d in dims])
    hi = np.array([stats.chi2.ppf(0.975, d) for d in dims])
    comp = [np.array([w[j] for w in white if w.size > j]) for j in range(dims.max())]
    L = int(min(lags, max(1, len(nis) // 4)))
    return {"nis_total": tot, "nis_dof": dof, "nis_p_value": 2 * min(cdf, 1 - cdf),
            "nis_outside_95": np.mean((nis < lo) | (nis > hi)),
            "mean_chi2": sum(c.size * c.mean() ** 2 for c in comp),
            "ljung_box": sum(ljung_box(c, L) for c in comp if c.size > L + 1)}


@pytest.mark.parametrize("burn", [0, 5, 120])
def test_monitor_matches_the_list_computation(burn):
    steps = _steps()
    mon = InnovationMonitor()
    for y, S in steps:
        mon.add(y, S)
    got = mon.tests(burn_in=burn).to_dict()
    ref = _reference_tests(steps, burn)
    for k, v in ref.items():
        assert got[k] == pytest.approx(v, rel=1e-12, abs=1e-12), k
    # running summary in O(1) equals the direct mean over the tail
    r = mon.running(burn)
    assert r["nis_per_row"] == pytest.approx(mon.nis[burn:].sum() / mon.dims[burn:].sum(), rel=1e-13)
    assert r["steps"] == len(steps) and r["last_dim"] == steps[-1][0].size
    assert np.isnan(mon.running(len(steps))["nis_per_row"])
    # the list view splits the flat buffer at the right places
    assert all(np.allclose(w, np.linalg.solve(np.linalg.cholesky(S), y)) for w, (y, S) in zip(mon.white, steps))


def test_from_record_and_journal_round_trip_bit_for_bit(tmp_path):
    steps = _steps(seed=3, n=90)
    mon = InnovationMonitor()
    history = []
    j = Journal.start(tmp_path / "s.json")
    for k, (y, S) in enumerate(steps, start=1):
        mon.add(y, S)
        if k % 4 == 0:
            history.append({"row": k, "line": k + 1, "nis": float(mon.nis[-1]),
                            "nis_per_row": mon.running(2)["nis_per_row"], "trace_P": 1.0 / k,
                            "estimate": [0.1 * k, -3.0, float("nan")], "std": [1e-3, 2e-3, 3e-3]})
        if k % 7 == 0:
            j.append(mon, history)
    ptr = j.append(mon, history)
    assert ptr["steps"] == len(steps) and ptr["history"] == len(history)
    nis, dims, white, hist = parse_journal((tmp_path / "s.json.journal").read_bytes(), 3)
    back = InnovationMonitor.from_record(nis, dims, white)
    assert np.array_equal(back.nis, mon.nis) and np.array_equal(back.dims, mon.dims)
    assert np.array_equal(back.white_flat, mon.white_flat)
    # the rebuilt prefix sums give the same running figures, bit for bit
    assert back.running(2) == mon.running(2)
    assert back.tests(burn_in=3).to_dict() == mon.tests(burn_in=3).to_dict()
    assert len(hist) == len(history)
    for a, b in zip(hist, history):
        assert a.keys() == b.keys()
        assert np.array_equal(np.array(a["estimate"]), np.array(b["estimate"]), equal_nan=True)
        assert all(a[k] == b[k] and type(a[k]) is type(b[k]) for k in ("row", "line", "nis", "trace_P"))
    with pytest.raises(ValueError, match="do not match"):
        InnovationMonitor.from_record(nis, dims[:-1], white)


def test_growing_array_keeps_every_value():
    g = GrowingArray(float, capacity=2)
    ref = []
    rng = np.random.default_rng(1)
    for k in range(500):
        v = rng.normal(size=int(rng.integers(0, 4)))
        g.extend(v)
        ref.extend(v)
        g.append(float(k))
        ref.append(float(k))
    assert np.array_equal(g.values, np.array(ref)) and len(g) == len(ref)
    w = GrowingArray(float, width=3, capacity=1)
    for k in range(10):
        w.append(np.full(3, k))
    assert w.values.shape == (10, 3) and np.array_equal(w.values[:, 1], np.arange(10))


@pytest.mark.parametrize("prefix,enc,newline", [(b"", "utf-8", "\n"), (b"\xef\xbb\xbf", "utf-8", "\r\n"),
                                                (b"", "utf-8", "\r"), (b"", "utf-16", "\n")])
def test_header_read_and_streamed_lines_match_the_whole_file_readers(tmp_path, prefix, enc, newline):
    """``read_csv_header`` (used to count point columns) gives the header ``read_csv`` gives, and
    the streamed lines of ``estcal online`` are ``splitlines(keepends=True)`` of the whole text,
    even with a block size that cuts lines and ``\\r\\n`` pairs."""
    from estcal.io.stream import _lines
    from estcal.base.textinput import read_csv, read_csv_header, read_text

    body = newline.join(["", "", "j1;j2; x ;y;z", *[f"{k};{k / 3};1;2;{k}" for k in range(40)], ""])
    raw = body.encode(enc) if enc == "utf-16" else prefix + body.encode(enc)
    f = tmp_path / "d.csv"
    f.write_bytes(raw)
    assert read_csv_header(f) == read_csv(f).header == ["j1", "j2", "x", "y", "z"]
    whole = read_text(f).splitlines(keepends=True)
    for block in (1, 2, 3, 7, 1 << 20):
        assert list(_lines(str(f), block=block)) == whole


def test_header_read_does_not_read_the_rest_of_the_file(tmp_path):
    """Only the header is read: a bad byte further down is left to the dataset loader, which
    names it (the header reader's errors are the loader's errors for the first lines)."""
    from estcal.io import load_dataset
    from estcal.io.dataset import DatasetError
    from estcal.base.textinput import read_csv_header

    f = tmp_path / "d.csv"
    f.write_bytes(b"j1,x,y,z\n0.1,1,2,3\n0.2,1,\x00,3\n")
    assert read_csv_header(f, "dataset", DatasetError) == ["j1", "x", "y", "z"]
    with pytest.raises(DatasetError, match="line 3"):
        load_dataset(f)
    g = tmp_path / "bin.csv"
    g.write_bytes(b"j1,\x00x\n")
    with pytest.raises(DatasetError, match="binary file"):
        read_csv_header(g, "dataset", DatasetError)
