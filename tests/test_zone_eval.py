"""`covey eval --suites zones` (policy/zone_eval.py): the scenes exist, the counts can fail (the
same scene flown without zones enters them), and routed, filtered flight keeps out and arrives."""

from __future__ import annotations

import numpy as np
import pytest

from policy import eval as policy_eval
from policy import evalsim, scenarios, zone_eval
from policy.evalsim import PERFECT, EvalSimConfig


def test_the_suite_has_convex_concave_gap_gate_and_edge_goal_scenes():
    cfg = policy_eval.EvalConfig(suites=("zones",))
    names = [c[1] for c in policy_eval.cases(cfg)]
    for want in (
        "zones-convex",
        "zones-concave",
        "zones-gap-9m",
        "zones-gate-9m",
        "zones-edge-goals",
    ):
        assert want in names
    assert all(c[0] == "zones" and "zones_m" in c[4] for c in policy_eval.cases(cfg))


@pytest.mark.slow
def test_entries_are_counted_and_routes_with_the_filter_keep_out():
    name, starts, goals, zones = scenarios.zone_scenes(np.random.default_rng(0))[0]  # convex
    sim = EvalSimConfig()
    unaware = zone_eval.run(
        "straight",
        starts,
        goals,
        zones,
        evalsim.straight_line,
        PERFECT,
        sim,
        np.random.default_rng(1),
        aware=False,
    )
    assert unaware["zone_entries"] == len(starts) and unaware["min_zone_m"] == 0.0
    cfg = policy_eval.EvalConfig(controllers=("orca",))
    orca = policy_eval.controllers(cfg)["orca"]
    r = zone_eval.run("orca", starts, goals, zones, orca, PERFECT, sim, np.random.default_rng(1))
    assert r["zone_entries"] == 0 and r["min_zone_m"] >= 1.8 - 1e-6
    assert r["success"] and r["collisions"] == 0
    assert 1.0 <= r["route_time"] < 2.0  # a swap of 6 meets at the corners


def test_a_scene_whose_every_goto_is_refused_is_reported_not_a_crash():
    """Goals nearer a keep-out zone than the clearance, too far from it to be moved within the
    arrival radius, are refused as the flight core refuses them; where every one is (a poor
    sigma's wide clearance can do it), nothing flies and the run says so (it crashed)."""
    zone = [np.array([[-5.0, -5.0], [5.0, -5.0], [5.0, 5.0], [-5.0, 5.0]])]
    starts = np.array([[-30.0, 0.0], [30.0, 0.0]])
    # both 0.3 m off its edge: the clearance's nearest point is beyond the arrival radius
    goals = np.array([[0.0, 5.3], [5.3, 0.0]])
    cfg = policy_eval.EvalConfig(controllers=("orca",))
    orca = policy_eval.controllers(cfg)["orca"]
    r = zone_eval.run(
        "orca", starts, goals, zone, orca, PERFECT, EvalSimConfig(), np.random.default_rng(2)
    )
    assert r["refused"] == 2 and r["n"] == 0 and r["min_zone_m"] is None and not r["success"]
    rows = [{"suite": "zones", "case": "all-refused", "link": "perfect", "controller": "orca", **r}]
    (s,) = policy_eval.summarise(rows)
    assert s["refused"] == 2 and s["min_zone_m"] is None and s["vehicles"] == 0
