"""One NoiseModel (estcal/methods/base.py) with one parser for numbers, pairs and mappings
(docs/conventions.md, "Noise"), used by the API, the simulator and the diagnosis alike."""
from __future__ import annotations

import numpy as np
import pytest

import estcal
import estcal.simulate
from estcal.methods import NoiseModel
from estcal.methods.base import NOISE_LEVER_M


def test_one_class_everywhere():
    assert estcal.NoiseModel is NoiseModel is estcal.simulate.NoiseModel


@pytest.mark.parametrize("value, expected", [
    (None, (1e-4, 1e-3, 1e-4, False)),
    (2e-5, (2e-5, 2e-4, 2e-5, False)),
    ((2e-5, 3e-4), (2e-5, 3e-4, 2e-5, False)),
    ({"position": 2e-5}, (2e-5, 1e-3, 2e-5, False)),
    ({"orientation": 3e-4, "known": True}, (1e-4, 3e-4, 1e-4, True)),
])
def test_parse_rule(value, expected):
    n = NoiseModel.parse(value)
    assert (n.position, n.orientation, n.scalar, n.known) == pytest.approx(expected)
    assert NOISE_LEVER_M == 0.1
    assert NoiseModel.parse(value, known=True).known is (True if not isinstance(value, dict) or "known" not in value
                                                         else value["known"])


def test_parse_refuses_what_it_cannot_read():
    with pytest.raises(ValueError, match="unknown key"):
        NoiseModel.parse({"pos": 1e-4})
    with pytest.raises(ValueError, match="> 0 m"):
        NoiseModel.parse(0.0)
    with pytest.raises(ValueError, match="position m, orientation rad"):
        NoiseModel.parse((1, 2, 3))
    with pytest.raises(ValueError, match="gaussian"):
        NoiseModel(distribution="cauchy")
    given = NoiseModel(position=1.0)
    assert NoiseModel.parse(given) is given


def test_the_api_and_the_diagnosis_read_a_number_alike(monkeypatch):
    """estcal.diagnose (via the API) and estcal.discrepancy.diagnose give a bare number the same meaning."""
    from estcal.api import as_noise
    from estcal.discrepancy import diagnose as diag_mod

    seen = {}

    class Stop(Exception):
        pass

    def spy(robot, data, noise, **kw):  # the candidates of the diagnosis, its first use of the noise
        seen["noise"] = noise
        raise Stop

    import importlib

    monkeypatch.setattr(importlib.import_module("estcal.discrepancy.diagnose"), "build_terms", spy)
    sim = estcal.simulate.simulate("puma560", n_poses=20, measure="pose", noise=(5e-5, 5e-4), seed=3)
    with pytest.raises(Stop):
        diag_mod(sim.nominal_robot, sim.dataset, noise=5e-5)
    assert seen["noise"] == as_noise(5e-5, known=True) == NoiseModel.parse(5e-5, known=True)
    assert seen["noise"].orientation == pytest.approx(5e-4)


def test_simulation_noise_draws_and_truth():
    none = estcal.simulate.simulate("planar2", n_poses=10, measure="position", seed=1)
    assert none.summary.noise_rms_mm == 0.0 and none.truth["noise"]["position"] == 0.0
    sim = estcal.simulate.simulate("planar2", n_poses=2000, measure="position", seed=1,
                                   noise={"position": 1e-4, "joint": 1e-5})
    t = sim.truth["noise"]
    assert (t["position"], t["joint"], t["distribution"], t["units"]["position"]) == (1e-4, 1e-5, "gaussian", "m")
    assert sim.summary.noise_rms_mm == pytest.approx(0.1, rel=0.05)
    u = NoiseModel(position=1e-3, distribution="uniform")
    x = u.draw(u.position, 100000, np.random.default_rng(0))
    assert np.abs(x).max() <= 1e-3 and u.std(u.position) == pytest.approx(x.std(), rel=0.02)
