"""estcal check (estcal.intake.hygiene): hidden defects in simulated and real files are named, line by line."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.intake.hygiene import DEFECTS, check_data
from estcal.io.dataset import load_dataset, write_dataset
from estcal.io.robotfile import load_robot
from estcal.simulate.core import simulate

from conftest import REPO, SHARED

MAPS = REPO / "docs" / "maps"


def _named(report):
    """{line: kind} of the defect findings."""
    out = {}
    for f in report.findings:
        if f.kind in DEFECTS:
            for ln in f.lines:
                out[int(ln)] = f.kind
    return out


def _assert_exact(report, hidden, n_rows):
    named = _named(report)
    for ln, kind in hidden.items():
        assert named.get(ln) == kind, (ln, kind, named, report.messages())
    false = sorted(set(named) - set(hidden))
    assert len(false) <= 2 * n_rows / 100, (false, report.messages())
    return false


def _hide(P, R, rng, lines_of, hidden, swaps=(), non_rigid=(), blunders=(), limits=(), limit_values=None,
          blunder_mm=(3, 8)):
    """Defects written into arrays (row indices); ``hidden`` gets {file line: kind}."""
    for i, perm in swaps:
        P[i] = P[i][list(perm)]
        hidden[lines_of(i)] = "marker_swap"
    for i in non_rigid:
        P[i, -1] += rng.normal(size=3) / np.sqrt(3) * 0.03  # one marker 3 cm off (a ghost)
        hidden[lines_of(i)] = "non_rigid"
    for i in blunders:
        v = rng.normal(size=3)
        P[i] += v / np.linalg.norm(v) * rng.uniform(*blunder_mm) * 1e-3
        hidden[lines_of(i)] = "outlier"
    for i, (j, value) in zip(limits, limit_values or []):
        R[i, j] = value
        hidden[lines_of(i)] = "out_of_limits"


def test_simulated_points_every_kind():
    rb = load_robot("puma560")
    sim = simulate(rb, 100, measure="points", n_points=4, errors="random", seed=5,
                   noise={"position": 1e-4})
    ds = sim.dataset
    P, R = ds.points.copy(), ds.readings.copy()
    rng = np.random.default_rng(1)
    hidden = {}
    lines_of = lambda i: int(ds.lines[i])  # noqa: E731
    lim = rb.limits
    _hide(P, R, rng, lines_of, hidden, swaps=[(10, (1, 0, 2, 3)), (40, (2, 0, 1, 3))], non_rigid=[20, 70],
          blunders=[5, 33, 51, 77, 95], limits=[60, 88],
          limit_values=[(1, lim[1, 1] + 0.4), (4, lim[4, 0] - 0.3)])
    ds.points, ds.readings = P, R
    robot = load_robot("puma560", n_markers=4)
    report = check_data(robot, ds)
    false = _assert_exact(report, hidden, ds.n)
    swap = {f.lines[0]: f.details["order"] for f in report.findings if f.kind == "marker_swap"}
    assert swap[lines_of(10)] == [2, 1, 3, 4] and swap[lines_of(40)] == [2, 3, 1, 4]
    assert len(false) == 0


def test_simulated_position_blunders_and_wild_reading():
    """Five 3–8 mm blunders among 100 poses (0.1 mm noise) and one wild joint reading within the limits."""
    rb = load_robot("puma560")
    sim = simulate(rb, 100, measure="position", errors="random", seed=7, noise={"position": 1e-4})
    ds = sim.dataset
    P, R = ds.points.copy(), ds.readings.copy()
    rng = np.random.default_rng(2)
    hidden = {}
    lines_of = lambda i: int(ds.lines[i])  # noqa: E731
    _hide(P, R, rng, lines_of, hidden, blunders=[3, 17, 42, 64, 90])
    R[55, 2] += 0.5  # a wild reading, within the limits: the pose no longer fits
    hidden[lines_of(55)] = "outlier"
    ds.points, ds.readings = P, R
    _assert_exact(check_data(rb, ds), hidden, ds.n)


def test_duplicates_and_repeated_postures(tmp_path):
    rb = load_robot("puma560")
    ds = simulate(rb, 30, measure="position", seed=1, noise={"position": 1e-4}).dataset
    idx = np.r_[np.arange(30), 4, 9]  # two copies
    ds2 = ds.subset(idx)
    write_dataset(tmp_path / "d.csv", ds2)
    report = check_data(rb, load_dataset(tmp_path / "d.csv", rb))
    dup = [f for f in report.findings if f.kind == "duplicate_row"]
    assert dup and sorted(dup[0].lines) == [32, 33]
    assert "line 6 repeated at 32" in dup[0].message


def _real(folder, name):
    p = SHARED / "data" / folder / name
    if not p.exists():
        pytest.skip(f"{p} not found (real data live in ../shared next to the repository)")
    return p


def _write_like(path, src_text, rows_fn):
    """Rewrite a CSV (keeping its header and columns) with rows_fn(table) → new numeric table."""
    lines = src_text.splitlines()
    has_header = not lines[0][0].isdigit() and lines[0][0] not in "-."
    head = lines[:1] if has_header else []
    body = np.array([[float(v) for v in ln.split(",")] for ln in lines[len(head):]])
    body = rows_fn(body)
    path.write_text("\n".join(head + [",".join(repr(float(v)) for v in r) for r in body]) + "\n")
    return len(head)


def _real_robot_and_data(folder, path):
    d = SHARED / "data" / folder
    if folder == "talos":
        rb = load_robot(str(d / "talos_reduced.urdf"), root="base_link", tip="arm_left_7_link", n_markers=1)
    elif folder == "tiago":
        rb = load_robot(str(d / "tiago_48_schunk.urdf"), tip="wrist_ft_tool_link", n_markers=4)
    else:
        rb = load_robot(str(d / "ur10_robot.urdf"), root="world", tip="camera_color_optical_frame")
    return rb, load_dataset(path, rb, column_map=MAPS / f"{folder}.yaml")


def test_real_tiago_hidden_defects(tmp_path):
    src = _real("tiago", "qualisys_2021-11-26_static_postures.csv")
    rng = np.random.default_rng(3)
    hidden = {}

    def edit(M):
        P = M[:, :12].reshape(-1, 4, 3)
        R = M[:, 12:20]
        _hide(P, R, rng, lambda i: i + 2, hidden, swaps=[(7, (3, 1, 2, 0)), (30, (0, 2, 1, 3))],
              non_rigid=[15, 44], blunders=[22, 50], limits=[58], limit_values=[(0, 0.42)], blunder_mm=(25, 35))
        M[:, :12] = P.reshape(-1, 12)
        return M

    _write_like(tmp_path / "t.csv", src.read_text(), edit)
    rb, ds = _real_robot_and_data("tiago", tmp_path / "t.csv")
    _assert_exact(check_data(rb, ds), hidden, ds.n)


def _talos_hidden(tmp_path, name, seed, hidden, first_line, **defects):
    """A TALOS session (t, x1, y1, z1, 9 joints) with defects hidden by :func:`_hide`; check names them."""
    src = _real("talos", name)
    rng = np.random.default_rng(seed)

    def edit(M):
        P = M[:, None, 1:4]
        _hide(P, M[:, 4:], rng, lambda i: i + first_line, hidden, **defects)
        M[:, 1:4] = P[:, 0]
        return M

    _write_like(tmp_path / "t.csv", src.read_text(), edit)
    rb, ds = _real_robot_and_data("talos", tmp_path / "t.csv")
    _assert_exact(check_data(rb, ds), hidden, ds.n)


def test_real_talos_headerless_hidden_defects(tmp_path):
    """21 poses at the registration level (5 mm RMS of model error): a swapped-in marker 5–8 cm off."""
    _talos_hidden(tmp_path, "talos_feb_arm_2_contact.csv", 4, {}, 1, blunders=[6, 15], limits=[11],
                  limit_values=[(3, 2.9)], blunder_mm=(50, 80))


def test_real_talos_hidden_blunders_among_62(tmp_path):
    """62 poses (joint-offset level, 0.8 mm RMS): 15–25 mm blunders are named, with the published first row."""
    _talos_hidden(tmp_path, "talos_feb_arm_02_10_contact.csv", 6, {2: "outlier"}, 2, blunders=[9, 25, 40, 55],
                  blunder_mm=(15, 25))


def test_repeated_postures_give_the_repeatability(tmp_path):
    """Postures measured again (joint readings within 1 mrad) are named with their repeatability: 0.2 mm of
    measurement noise per coordinate gives √3·0.2 = 0.35 mm RMS from each posture's mean."""
    rb = load_robot("puma560")
    sim = simulate(rb, 20, measure="position", seed=3)
    ds = sim.dataset.subset(np.r_[np.arange(20), np.repeat(np.arange(5), 40)])
    rng = np.random.default_rng(0)
    ds.points = ds.points + rng.normal(0, 2e-4, ds.points.shape)
    ds.readings = ds.readings + rng.normal(0, 1e-5, ds.readings.shape)
    ds.lines = np.arange(2, 2 + ds.n)
    f = [x for x in check_data(rb, ds, outliers=False).findings if x.kind == "repeated_pose"]
    assert len(f) == 1 and len(f[0].details["groups"]) == 5
    assert abs(f[0].details["repeatability_mm"] - np.sqrt(3) * 0.2) < 0.03
