"""bench/off_preset.py's summary of a model's runs and its --models argument, on synthetic runs
(nothing is flown here: the bench itself takes minutes)."""

from __future__ import annotations

import argparse

import pytest

from bench.off_preset import models_arg, table, total


def run(collisions: int, min_sep: float, n: int, arrived: int, extra: float, intruder=None):
    return {
        "collisions": collisions,
        "min_sep": min_sep,
        "n": n,
        "arrived": arrived,
        "extra_time": extra,
        "intruder_min_sep": intruder,
    }


def test_a_models_row_counts_collision_runs_late_vehicles_and_the_closest() -> None:
    flown = {
        "vehicles": "realistic:drift_m=0.6",
        "seed": 7,
        "runs": [
            run(0, 3.8, 10, 10, 1.2),
            run(2, 2.9, 35, 34, 1.5, intruder=4.1),  # one run with two vehicles colliding
            run(0, 3.5, 8, 7, 1.3, intruder=3.6),
        ],
    }
    row = total(flown)
    assert row["runs"] == 3
    assert row["collision_cases"] == 1  # runs, not vehicles
    assert row["min_sep_true_m"] == 2.9
    assert row["intruder_min_sep_m"] == 3.6
    assert (row["late_vehicles"], row["covey_vehicles"]) == (2, 53)
    assert row["extra_time_median"] == 1.3
    assert "realistic:drift_m=0.6" in table([row]) and "2/53" in table([row])


def test_models_are_spec_at_seed_and_a_spec_keeps_its_commas() -> None:
    got = models_arg("realistic:drift_m=0.6,gust_m_s=0.3@12; ideal@3")
    assert got == (("realistic:drift_m=0.6,gust_m_s=0.3", 12), ("ideal", 3))
    for bad in ("realistic", "realistic@x", "@4", " ; "):
        with pytest.raises(argparse.ArgumentTypeError):
            models_arg(bad)
