"""The helpers of ``experiments/tiago_disjoint.py`` that summarise its halvings, on synthetic rows: no shared data
needed."""
import argparse
import importlib.util
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def td():
    spec = importlib.util.spec_from_file_location("tiago_disjoint", REPO / "experiments" / "tiago_disjoint.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_seed_sets_by_name_all_or_list_and_a_clear_error(td):
    assert td.seed_set("development") == (0, 1, 2, 3, 4, 5)
    assert td.seed_set("confirmation10") == (200, 201, 202)
    every = td.seed_set("all")
    assert len(every) == 36 and len(set(every)) == 36  # 72 halvings: both directions of each seed
    assert every[:6] == (0, 1, 2, 3, 4, 5) and every[-3:] == (200, 201, 202)
    assert td.seed_set("7, 8") == (7, 8)
    with pytest.raises(argparse.ArgumentTypeError, match="neither a seed set"):
        td.seed_set("confirmaton2")


def test_attainable_within_against_monte_carlo(td):
    """The chance that a prediction equal to the expected RMSE lands within 30 % of a measured RMSE that scatters
    normally about it with the given standard error, summed over halvings — checked by drawing the measured RMSE."""
    rows = [{"new_mm": 2.0, "new_se_mm": 0.3}, {"new_mm": 3.0, "new_se_mm": 0.9}, {"new_mm": 1.5, "new_se_mm": None}]
    rng = np.random.default_rng(0)
    mc = 1.0  # no standard error: counted as within
    for r in rows[:2]:
        a = rng.normal(r["new_mm"], r["new_se_mm"], 400_000)
        mc += np.mean(np.abs(r["new_mm"] / a - 1) <= 0.3)
    assert td.attainable_within(rows) == pytest.approx(mc, abs=3e-3)


def test_named_counts_count_each_cause_once_per_halving_and_the_most_common_list(td):
    rows = [{"named": ["a", "b"]}, {"named": ["b", "a"]}, {"named": ["a"]}, {"named": ["a", "a"]}, {"named": []},
            {"named": ["b", "a"]}]
    out = td.named_counts(rows)
    assert out["causes"] == {"a": 5, "b": 3}
    assert list(out["causes"]) == ["a", "b"]  # most often first
    assert out["most_common_list"] == ["a", "b"]  # the order within a list does not matter
    assert out["most_common_list_count"] == 3
