"""The Python snippets of the documentation run (tests/docs_runner.py; docs/api.md,
"Documentation snippets"): every page with ```python blocks, blocks in order in one namespace,
one fresh process per page in an empty folder; ```text output blocks are compared."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from docs_runner import code_blocks, python_blocks

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted(p for p in [*(REPO / "docs").glob("*.md"), REPO / "README.md"] if python_blocks(p))


def test_the_runner_finds_blocks_and_outputs():
    text = "x\n```python\nprint(1)\n```\nprints\n\n```text output\n1\n```\n```python no-run\nboom\n```\n"
    assert [(b[0], b[1], b[2]) for b in code_blocks(text)] == [(2, "python", ""), (7, "text", "output"),
                                                                (10, "python", "no-run")]
    assert "api.md" in {p.name for p in PAGES}  # the API page is among the pages run


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_docs_page_snippets_run(page, tmp_path):
    code = "".join(c for _, c, _ in python_blocks(page))
    from estcal.kinematics.robots import shared_dir

    for robot, name in (("tiago", "tiago_48_schunk.urdf"), ("ur10", "ur10_robot.urdf")):
        if robot in code and not (shared_dir() / "data" / robot / name).exists():
            pytest.skip(f"this page's snippets read the {robot} files of ../shared (absent)")
    env = dict(os.environ, MPLBACKEND="Agg")
    p = subprocess.run([sys.executable, str(REPO / "tests" / "docs_runner.py"), str(page)], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300, env=env)
    assert p.returncode == 0, f"{page.name}:\n{p.stderr[-3000:]}"


def test_calibration_docs_list_every_estimator_option():
    """docs/calibration.md's table of --option keys is the registry's (estimator signatures)."""
    import re

    from estcal.estimate.registry import estimator_names, estimator_options

    text = (REPO / "docs" / "calibration.md").read_text()
    table = text[text.index("| estimator | keys |"):]
    documented = {}
    for row in table.splitlines()[2:]:
        if not row.strip().startswith("|"):
            break
        names, keys = row.strip().strip("|").split("|")
        keys = set(re.findall(r"`([^`]+)`", re.sub(r"\([^)]*\)", "", keys)))  # (value lists) dropped
        for n in re.findall(r"`([^`]+)`", names):
            documented[n] = keys
    assert set(documented) == set(estimator_names())
    for n in estimator_names():
        assert documented[n] == set(estimator_options(n)), n
