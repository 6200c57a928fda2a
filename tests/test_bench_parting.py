"""bench/parting_circles.py: its summary and table on synthetic runs (nothing is flown)."""

from __future__ import annotations

import argparse

import pytest

from bench import parting_circles as pc


def _row(regime, rule, seed, n, min_sep, collisions=0, timeouts=0, extra=2.0):
    share = pc.RULES[rule]
    return {
        "regime": regime,
        "rule": rule,
        "recover_speed_share": share,
        "seed": seed,
        "n": n,
        "link": "perfect",
        "collisions": collisions,
        "timeouts": timeouts,
        "min_sep": min_sep,
        "est_min_sep": min_sep + 0.5,
        "extra_time": extra,
    }


ROWS = [
    _row("gusty", "old", 21, 16, 4.0, extra=2.0),
    _row("gusty", "old", 21, 32, 3.5, timeouts=2, extra=None),
    _row("gusty", "old", 22, 50, 3.1, extra=3.0),
    _row("gusty", "shipped", 21, 16, 4.4, extra=2.5),
    _row("gusty", "shipped", 21, 32, 2.97, collisions=2, extra=2.5),
    _row("gusty", "shipped", 22, 50, 3.6, timeouts=1, extra=2.2),
    _row("drift-1.0", "old", 21, 16, 2.9, collisions=1),
]


def test_summary_counts_runs_not_vehicles_and_skips_missing_times() -> None:
    s = {(r["regime"], r["rule"]): r for r in pc.summarise(ROWS)}
    assert [k for k in s] == [("gusty", "old"), ("gusty", "shipped"), ("drift-1.0", "old")]
    old, shipped = s["gusty", "old"], s["gusty", "shipped"]
    assert old["runs"] == 3 and old["collision_runs"] == 0 and old["vehicles_late"] == 2
    assert old["closest_true_m"] == 3.1 and old["median_closest_true_m"] == 3.5
    assert old["mean_extra_time"] == pytest.approx(2.5)  # the run with no arrival is left out
    assert shipped["collision_runs"] == 1  # two vehicles of one run: one run
    assert shipped["closest_true_m"] == 2.97 and shipped["median_closest_true_m"] == 3.6
    assert shipped["mean_extra_time"] == pytest.approx(2.4) and shipped["vehicles_late"] == 1
    assert shipped["recover_speed_share"] == pc.RULES["shipped"]
    assert s["drift-1.0", "old"]["collision_runs"] == 1


def test_table_has_one_line_per_regime_and_rule() -> None:
    text = pc.table(pc.summarise(ROWS))
    lines = text.splitlines()
    assert len(lines) == 4 and "collision runs" in lines[0]
    shipped = next(x for x in lines if x.startswith("gusty") and "shipped" in x)
    assert "1 of 3" in shipped and "2.97" in shipped and "3.60" in shipped and "2.400" in shipped
    no_time = pc.summarise([_row("gusty", "old", 21, 16, 4.0, extra=None)])
    assert pc.table(no_time).splitlines()[1].rstrip().endswith("-")


def test_config_and_seeds_refuse_what_they_cannot_fly() -> None:
    with pytest.raises(ValueError, match="regimes windy"):
        pc.PartingConfig(regimes=("windy",))
    with pytest.raises(ValueError, match="rules"):
        pc.PartingConfig(rules=())
    assert pc.seed_list("21-23,30") == (21, 22, 23, 30)
    with pytest.raises(argparse.ArgumentTypeError, match="backwards"):
        pc.seed_list("27-21")
    with pytest.raises(argparse.ArgumentTypeError, match="not a seed"):
        pc.seed_list("21,x")
