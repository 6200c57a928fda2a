"""bench/noisy_training.py's table and --weights argument, on synthetic runs (nothing is
flown here: the bench itself takes minutes)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from bench.noisy_training import BASELINE, _weights, rows


def run(case: str, suite: str, link: str, extra: float, min_sep: float, collided=0, ok=True):
    return {
        "case": case,
        "suite": suite,
        "link": link,
        "extra_time": extra,
        "min_sep": min_sep,
        "collisions": collided,
        "success": ok,
    }


def test_ratios_are_against_the_ideal_run_of_the_same_case_link_and_seed() -> None:
    runs = {
        ("cand", "ideal", 1): {
            "runs": [
                run("c8", "circle", "perfect", 1.0, 3.6),
                run("c16", "circle", "perfect", 1.1, 3.6),
            ]
        },
        ("cand", "ideal", 2): {"runs": [run("c8", "circle", "perfect", 2.2, 3.6)]},
        (BASELINE, "ideal", 1): {
            "runs": [
                run("c8", "circle", "perfect", 1.2, 3.6),
                run("c16", "circle", "perfect", 1.0, 3.6),
            ]
        },
        (BASELINE, "ideal", 2): {"runs": [run("c8", "circle", "perfect", 2.0, 3.6)]},
        ("cand", "realistic", 1): {
            "runs": [
                run("c8", "circle", "perfect", 1.8, 2.9, collided=2, ok=False),
                run("c16", "circle", "perfect", 1.1, 4.0),
            ]
        },
        ("cand", "realistic", 2): {"runs": [run("c8", "circle", "perfect", 2.2, 3.9)]},
    }
    table = {(r["weights"], r["vehicles"]): r for r in rows(runs)}
    cand = table[("cand", "realistic")]
    assert cand["runs"] == 3 and cand["collision_cases"] == 1 and cand["failed_cases"] == 1
    assert cand["closest_true_m"] == 2.9
    assert cand["vs_base_ideal_median"] == pytest.approx(1.1)  # of 1.5, 1.1 and 1.1
    assert cand["vs_own_ideal_median"] == pytest.approx(1.0)  # of 1.8, 1.0 and 1.0
    assert table[(BASELINE, "ideal")]["vs_base_ideal_median"] == pytest.approx(1.0)
    assert table[("cand", "ideal")]["vs_own_ideal_median"] == pytest.approx(1.0)


def test_weights_are_label_path_and_an_optional_told_separation(tmp_path: Path) -> None:
    w = tmp_path / "run_a" / "final.npz"
    w.parent.mkdir()
    w.write_bytes(b"x")
    assert _weights(f"a={w}@3,{w}") == {"a": (str(w), 3.0), "run_a": (str(w), None)}
    for bad in ("", f"a={tmp_path}/none.npz", f"a={w}@x", f"a={w}@-1", f"{BASELINE}={w}"):
        with pytest.raises(argparse.ArgumentTypeError):
            _weights(bad)
