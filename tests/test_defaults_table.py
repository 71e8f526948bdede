"""One set of defaults across the command line and the Python API (docs/conventions.md, "Defaults: one
table").

The table is read from the docs page. For every row: the command has the option and the Python object
the keyword; then each command and each object is *built with its defaults* on one file — the command
run with ``--json`` (online: and ``--state``, whose checkpoint records the options it used), the object
called / fed with no option — and what each actually used is read back and compared with the first
backquoted words of the row's *default* column. A row without a reader below fails: adding a concept
(the diagnosis's rows) means saying how to read it from both faces.
"""
from __future__ import annotations

import inspect
import json
import re

import pytest
from typer.testing import CliRunner

from estcal.cli.main import app

from conftest import REPO

runner = CliRunner()
PAGE = REPO / "docs" / "conventions.md"


def table_rows() -> list[dict]:
    """The rows of the "Defaults: one table" table of docs/conventions.md."""
    text = PAGE.read_text()
    block = text[text.index("### Defaults: one table"):].splitlines()
    start = next(i for i, ln in enumerate(block) if ln.startswith("|"))
    lines = []
    for ln in block[start:]:  # the table: the lines from its header to the first that is not a row
        if not ln.startswith("|"):
            break
        lines.append(ln)
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = []
    for ln in lines[2:]:
        cells = dict(zip(head, (c.strip() for c in ln.strip().strip("|").split("|"))))
        tick = lambda c: re.findall(r"`([^`]+)`", c)  # noqa: E731
        rows.append({"concept": cells["concept"], "command": tick(cells["command"])[0],
                     "options": tick(cells["option"]), "python": tick(cells["Python"])[0],
                     "keyword": tick(cells["keyword"])[0], "default": tick(cells["default"])[0]})
    return rows


ROWS = table_rows()


def _cli_options(command: str) -> set:
    for c in app.registered_commands:
        if c.name == command:
            out = set()
            for p in inspect.signature(c.callback).parameters.values():
                for d in getattr(p.default, "param_decls", None) or ():
                    out |= {s for s in d.split("/") if s.startswith("--")}
            return out
    raise AssertionError(f"no command {command!r}")


def _python(name: str):
    import estcal

    obj = getattr(estcal, name.split(".", 1)[1])
    return obj.__init__ if inspect.isclass(obj) else obj


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Each command and object of the table, built with its defaults on one PUMA 560 pose file."""
    import estcal
    from estcal.simulate import simulate

    d = tmp_path_factory.mktemp("defaults")
    f = d / "pose.csv"
    simulate("puma560", 80, measure="pose", errors="random", noise={"position": 5e-5, "orientation": 5e-4},
             seed=11).write(f)
    r = runner.invoke(app, ["calibrate", str(f), "-r", "puma560", "--json", str(d / "cal.json")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["online", str(f), "-r", "puma560", "--every", "1000", "--json", str(d / "on.json"),
                            "--state", str(d / "state.json")])
    assert r.exit_code == 0, r.output
    on = json.loads((d / "on.json").read_text())
    cal = estcal.OnlineCalibrator("puma560")
    cal.update(str(f))
    r = runner.invoke(app, ["diagnose", str(f), "-r", "puma560", "--json", str(d / "diag.json")])
    assert r.exit_code == 0, r.output
    robot = estcal.load_robot("puma560")
    return {"file": f, "robot": robot, "data": estcal.load_dataset(f, robot),
            ("calibrate", "cli"): json.loads((d / "cal.json").read_text()),
            ("calibrate", "api"): estcal.calibrate("puma560", str(f)).to_dict(),
            ("online", "cli"): {"names": list(on["parameters"]), "filter": on["filter"],
                                "options": json.loads((d / "state.json").read_text())["options"]},
            ("online", "api"): {"names": list(cal.names), "filter": cal.flt.kind, "options": cal.options,
                                "noise": cal.noise},
            ("diagnose", "cli"): json.loads((d / "diag.json").read_text()),
            ("diagnose", "api"): estcal.diagnose("puma560", str(f)).to_dict()}


def _calibrate_free(b, got):
    from estcal.estimate import register_base
    from estcal.estimate.levels import select_free
    from estcal.methods import NoiseModel, Problem

    prob = Problem(b["robot"], [(None, b["data"], NoiseModel())])
    prob = prob.with_values(register_base(prob.robot, b["data"], prob.params.values.copy()))
    want = select_free(prob, "full").identifiable
    return "identifiable set of the level" if list(got["selection"]["identifiable"]) == list(want) else \
        f"another set: {got['selection']['identifiable']} (expected {want})"


def _online_free(b, got):
    from estcal.workflows.online import default_free_set

    want = default_free_set(b["robot"], b["data"])
    return "identifiable set of the measurement" if got["names"] == want else f"another set: {got['names']}"


def _noise_mm(pos, rot):
    return f"{pos * 1e3:g} mm, {rot * 1e3:g} mrad"


def _online_option(key, fmt):
    return lambda b, got: fmt(got["options"][key])


#: (concept, command) → reader(built, what the face used) → the words of the default column
READERS = {
    ("free set", "calibrate"): _calibrate_free,
    ("level (geometric model)", "calibrate"): lambda b, got: got["selection"]["level"],
    ("selection", "calibrate"): lambda b, got: got["selection"]["criterion"],
    ("estimator", "calibrate"): lambda b, got: got["estimator"],
    ("noise", "calibrate"): lambda b, got: _noise_mm(got["noise"]["position"], got["noise"]["orientation"]),
    ("noise known", "calibrate"): lambda b, got: str(got["noise"]["known"]),
    ("free set", "online"): _online_free,
    ("noise", "online"): lambda b, got: _noise_mm(got["options"]["noise-pos (m)"], got["options"]["noise-rot (rad)"]),
    ("prior width", "online"): _online_option("prior-std (SI)", lambda v: f"{v:g} SI"),
    ("process noise", "online"): _online_option("q (SI)", lambda v: f"{v:g} SI"),
    ("filter", "online"): lambda b, got: got["filter"],
    ("geometric model", "diagnose"): lambda b, got: got["model"]["geometric_level"],
    ("link frames' prior width", "diagnose"): lambda b, got: "auto" if got["model"]["geometric_width_choice"]
    else "unbounded" if got["model"]["geometric_width"] is None
    else "{0:g} mm, {0:g} mrad".format(got["model"]["geometric_width"] * 1e3),
    ("folds", "diagnose"): lambda b, got: str(got["data"]["k_folds"]),
    ("error budget", "diagnose"): lambda b, got: str(got["budget"] is not None),
    ("noise", "diagnose"): lambda b, got: _noise_mm(got["noise"]["position"], got["noise"]["orientation"]),
    ("rows the screening flags", "diagnose"): lambda b, got: "left out" if got["data"]["drop_flagged"] else "kept",
    ("validation registration", "diagnose"): lambda b, got: got["data"]["validation_registers"],
    ("approach directions", "diagnose"): lambda b, got: "from the acquisition order"
    if got["model"]["data_preparation"]["approach_from_order"] else "none",
}


def test_the_table_covers_the_concepts():
    assert {r["concept"].split(" (")[0] for r in ROWS} >= {"free set", "noise", "level", "estimator"}
    assert len(ROWS) >= 11


@pytest.mark.parametrize("row", ROWS, ids=[f"{r['command']}-{r['concept']}" for r in ROWS])
def test_defaults_agree_with_the_table(built, row):
    missing = [o for o in row["options"] if o not in _cli_options(row["command"])]
    assert not missing, f"`estcal {row['command']}` has no option {missing}"
    params = inspect.signature(_python(row["python"])).parameters
    assert row["keyword"] in params, f"{row['python']} has no keyword {row['keyword']!r}"
    reader = READERS.get((row["concept"], row["command"]))
    assert reader is not None, f"no reader for the row {row['concept']!r} of {row['command']!r}"
    cli = reader(built, built[(row["command"], "cli")])
    api = reader(built, built[(row["command"], "api")])
    assert cli == row["default"], f"estcal {row['command']}: {cli!r}, the table says {row['default']!r}"
    assert api == row["default"], f"{row['python']}: {api!r}, the table says {row['default']!r}"
