"""The README's path — simulate, calibrate and save, compensate, export, check — runs as printed.

Every ``$`` command of the section's ```console blocks runs through bash in one temporary folder with
the venv's ``estcal`` (a real subprocess, the installed entry point), must exit 0, and every output
line the README shows must appear in the real output with the same words and the same numbers
(tests/console_runner.py). The data come from a fixed seed, so the numbers are expected to be
identical; they are compared to 1e-3 relative (the last printed digit of a 4-significant-digit
figure, in case a BLAS rounds differently), and the round-off residuals the README quotes
(≈1e-13 mm) only have to stay below 1e-6. The figures `estcal fk` prints are then recomputed from
the files with numpy, and the true robot file against the simulator's own truth.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from console_runner import console_commands, missing_lines, run, NUMBER

REPO = Path(__file__).resolve().parents[1]
SECTION = "## From measurements to corrected commands and a URDF"


def readme_section() -> str:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    return text[start:end if end > 0 else None]


@pytest.fixture(scope="module")
def readme_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("readme")
    results = []
    for c in console_commands(readme_section()):
        p = run(c.cmd, folder, timeout=120)
        results.append((c, p))
        if p.returncode != 0:
            break  # the later commands need this one's files
    return folder, results


def test_the_section_is_the_four_step_path():
    cmds = [c.cmd for c in console_commands(readme_section())]
    joined = "\n".join(cmds)
    for step in ("estcal simulate", "estcal calibrate", "--save-model puma_cal.yaml", "estcal compensate",
                 "--robot puma_cal.yaml -o commands.csv", "estcal export --robot puma_cal.yaml --urdf",
                 "--robot puma_cal.urdf --root world --tip tool"):
        assert step in joined, step
    assert len(cmds) >= 8


def test_readme_commands_run_and_print_what_the_readme_shows(readme_run):
    _, results = readme_run
    assert len(results) == len(console_commands(readme_section()))
    for c, p in results:
        assert p.returncode == 0, f"README line {c.line}: `{c.cmd}` exited {p.returncode}:\n{p.stderr[-2000:]}"
        miss = missing_lines(c.expected, p.stdout + p.stderr)
        assert not miss, (f"README line {c.line}: `{c.cmd[:80]}`: these documented lines are not in the real "
                          f"output:\n" + "\n".join(miss) + "\n--- real output:\n" + p.stdout[-3000:])


def _csv(path):
    return np.genfromtxt(path, delimiter=",", names=True)


def _pose_errors(a, b):
    """Position (mm) and orientation (mrad) distance of the x,y,z,qw..qz columns of two tables."""
    from estcal.kinematics.transforms import quat_to_matrix, so3_log

    P = lambda t: np.column_stack([t["x"], t["y"], t["z"]])
    Q = lambda t: quat_to_matrix(np.column_stack([t["qw"], t["qx"], t["qy"], t["qz"]]))
    dp = np.linalg.norm(P(a) - P(b), axis=1) * 1e3
    dr = np.linalg.norm(so3_log(Q(a) @ np.swapaxes(Q(b), 1, 2)), axis=1) * 1e3
    return dp, dr


def test_fk_check_figures_recomputed_from_the_files(readme_run):
    """The 'vs the file's x,y,z,q' figures of `estcal fk`, recomputed independently from its CSVs."""
    folder, results = readme_run
    assert all(p.returncode == 0 for _, p in results)
    printed = {c.cmd.split(" -o ")[-1].strip(): p.stdout for c, p in results if c.cmd.startswith("estcal fk ")
               and "vs the file" in p.stdout}
    pairs = {"check.csv": "commands.csv", "reached.csv": "commands.csv", "nominal_reached.csv": "targets.csv"}
    for out, ref in pairs.items():
        line = next(ln for ln in printed[out].splitlines() if ln.startswith("vs the file"))
        rms_mm, max_mm, rms_mrad, max_mrad = map(float, NUMBER.findall(line.split(":", 1)[1]))
        dp, dr = _pose_errors(_csv(folder / out), _csv(folder / ref))
        for shown, value in ((rms_mm, np.sqrt(np.mean(dp ** 2))), (max_mm, dp.max()),
                             (rms_mrad, np.sqrt(np.mean(dr ** 2))), (max_mrad, dr.max())):
            # the URDF check's figures are round-off (1e-13 mm): compared on an absolute scale
            assert shown == pytest.approx(value, rel=1e-3, abs=1e-9), (out, line)
    # the claim of the README's step 4, from the files: URDF = model at the compensated commands,
    # the compensated commands reach the targets on the true robot far better than the nominal ones
    dp_urdf, _ = _pose_errors(_csv(folder / "check.csv"), _csv(folder / "commands.csv"))
    dp_true, _ = _pose_errors(_csv(folder / "reached.csv"), _csv(folder / "commands.csv"))
    dp_nom, _ = _pose_errors(_csv(folder / "nominal_reached.csv"), _csv(folder / "targets.csv"))
    assert dp_urdf.max() < 1e-6 and dp_true.max() < 0.1 and dp_nom.min() > 10 * dp_true.max()


def test_true_model_file_is_the_simulators_truth(readme_run):
    """`estcal simulate --true-model` writes the simulator's true robot: same forward kinematics."""
    from estcal.io.robotfile import load_robot
    from estcal.simulate import NoiseModel, simulate

    folder, results = readme_run
    assert all(p.returncode == 0 for _, p in results)
    sim = simulate(load_robot("puma560"), n_poses=50, measure="pose", seed=1, errors="random",
                   noise=NoiseModel(position=5e-5, orientation=5e-4))
    saved = load_robot(folder / "puma_true.yaml")
    q = saved.random_readings(20, np.random.default_rng(3))
    a, b = sim.true_robot.kinematics(q, jacobian=False), saved.kinematics(q, jacobian=False)
    assert np.abs(a.p - b.p).max() < 1e-12 and np.abs(a.R - b.R).max() < 1e-12
    # and it is the robot that produced measured.csv: its error there is the measurement noise only
    m = _csv(folder / "measured.csv")
    q = np.column_stack([m[f"j{k}"] for k in range(1, 7)])
    k = saved.kinematics(q, jacobian=False)
    dp = np.linalg.norm(k.p - np.column_stack([m["x"], m["y"], m["z"]]), axis=1)
    assert np.sqrt(np.mean(dp ** 2)) == pytest.approx(np.sqrt(3) * 5e-5, rel=0.25)


def test_command_table_lists_every_subcommand_once_with_a_docs_link():
    """README's command table names each subcommand of `estcal --help` in exactly one row, and every
    row links to a docs page that exists (or says 'this page')."""
    import re

    from typer.main import get_command

    from estcal.cli.main import app

    names = set(get_command(app).commands)
    text = (REPO / "README.md").read_text(encoding="utf-8")
    table = text[text.index("| command | what it does | docs |"):]
    rows = []
    for ln in table.splitlines()[2:]:
        if not ln.startswith("|"):
            break
        rows.append(ln)
    seen = [n for r in rows for n in re.findall(r"`estcal ([a-z-]+)`", r.split("|")[1])]
    assert sorted(seen) == sorted(names), (sorted(set(names) - set(seen)), sorted(set(seen) - set(names)))
    for r in rows:
        docs = r.rstrip("|").split("|")[-1]
        links = re.findall(r"\]\(([^)]+)\)", docs)
        assert links or "this page" in docs, r
        for link in links:
            assert (REPO / link.split("#")[0]).exists(), link
