"""The ``estcal online`` invocation shared by the online tests (docs/probabilistic.md, "Online calibration"):
PUMA 560, a free set of eight parameters the position stream identifies, small process noise, JSON result."""
from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from estcal.cli.main import app

FREE = "offset_1,offset_2,offset_3,a_2,d_3,alpha_3,base_tx,base_ty"
runner = CliRunner()


def run_online(path, out, *extra) -> dict:
    """``estcal online PATH --json OUT`` with the shared options (and ``extra``); the JSON result."""
    r = runner.invoke(app, ["online", str(path), "--robot", "puma560", "--free", FREE, "--q-mm", "1e-4",
                            "--json", str(out), *extra])
    assert r.exit_code == 0, r.output
    return json.loads(Path(out).read_text())
