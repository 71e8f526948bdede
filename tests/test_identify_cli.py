"""``estcal identifiable``: JSON keys, dataset excitation check, errors, Gough dispatch."""
from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.io.dataset import write_dataset
from estcal.kinematics.robots import puma560
from estcal.methods.generate import link_data, measurement_data

runner = CliRunner()
KEYS = ("n_parameters", "n_identifiable", "identifiable", "no_effect", "regrouped", "condition_number")


def test_cli_random_configurations_json(tmp_path):
    out = tmp_path / "id.json"
    res = runner.invoke(app, ["identifiable", "--robot", "puma560", "--measure", "position", "--n-poses", "30",
                              "--free", "theta_*,d_*,a_*,alpha_*,beta_*,base_*,tool_*", "--json", str(out)])
    assert res.exit_code == 0, res.output
    d = json.loads(out.read_text())
    for k in KEYS:
        assert k in d
    assert d["n_identifiable"] == 25 and d["method"] == "position"
    assert "sequential" in d["qr"]
    assert "identifiable" in res.output


def test_cli_dataset_and_priority_file(tmp_path):
    r = puma560()
    ds = measurement_data(r, 40, "location", 3)
    csv = write_dataset(tmp_path / "poses.csv", ds)
    prio = tmp_path / "prio.yaml"
    prio.write_text("offset_*: 6\ngain_*: 0\n")
    out = tmp_path / "id.json"
    res = runner.invoke(app, ["identifiable", "--robot", "puma560", "--data", str(csv), "--priority", str(prio),
                              "--json", str(out)])
    assert res.exit_code == 0, res.output
    d = json.loads(out.read_text())
    assert d["method"] == "pose" and d["excitation"]["same_set"]
    assert "offset_1" in d["identifiable"] and "theta_1" not in d["identifiable"]
    assert set(d["excluded"]) == {f"gain_{j}" for j in range(1, 7)}


def test_cli_link_dataset(tmp_path):
    r = puma560()
    csv = write_dataset(tmp_path / "links.csv", link_data(r, 40, 2, "point", 4), float_format="%.17g")
    res = runner.invoke(app, ["identifiable", "--robot", "puma560", "--data", str(csv), "--measure", "point-link",
                              "--json", str(tmp_path / "o.json")])
    assert res.exit_code == 0, res.output
    d = json.loads((tmp_path / "o.json").read_text())
    assert set(d["no_effect"]) >= {f"base_{c}" for c in ("tx", "ty", "tz", "rx", "ry", "rz")}


@pytest.mark.parametrize("args,msg", [
    (["--measure", "plane-known", "--plane", "0.1,0.2"], "three numbers"),
    (["--measure", "nonsense"], "unknown measurement method"),
    ([], "give --measure"),
])
def test_cli_errors(args, msg):
    res = runner.invoke(app, ["identifiable", "--robot", "puma560", "--n-poses", "20"] + args)
    assert res.exit_code == 2
    assert msg in res.output


def test_cli_gough_dispatch(tmp_path):
    res = runner.invoke(app, ["identifiable", "--robot", "left_hand", "--n-poses", "30", "--json",
                              str(tmp_path / "g.json")])
    assert res.exit_code == 0, res.output
    d = json.loads((tmp_path / "g.json").read_text())
    assert d["n_parameters"] == 42 and np.isfinite(d["condition_number"])
