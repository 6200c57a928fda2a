"""FLOPs formula, safety filter, the simulator and an eval smoke run."""

import json

import numpy as np
import pytest

from policy import evalsim, safety, scenarios
from policy.eval import EvalConfig, flops, main, merge


def test_flops_match_the_paper():
    assert flops(2) - flops(1) == 34_902
    assert flops(1) == 17_160
    assert flops(20) == 19 * 34_902 + 17_160 == 680_298
    assert flops(21) / 1e6 == pytest.approx(0.7152, abs=1e-4)


def test_orca_filter_keeps_separation_head_on():
    """Two straight-line vehicles head-on: the filter alone keeps them >= 3 m apart."""
    cfg = safety.SafetyConfig(radius_m=3.0, dt_s=0.1)
    pos = np.array([[0.0, 0.0], [40.0, 0.3]])
    goal = pos[::-1].copy()
    vel = np.zeros((2, 2))
    min_d = np.inf
    for _ in range(600):
        pref = evalsim.straight_line(None, 0.0, pos, vel, None, goal)
        v = safety.filter_batch(pos, vel, pref, np.array([[1], [0]]), cfg)
        pos, vel = pos + 0.1 * v, v
        min_d = min(min_d, np.hypot(*(pos[0] - pos[1])))
    assert min_d >= 3.0
    assert np.hypot(*(pos[0] - goal[0])) < 2.0  # and they get past each other


def test_filter_does_not_touch_a_safe_velocity():
    cfg = safety.SafetyConfig()
    v = safety.filter_velocity(np.zeros(2), [1, 0], [1, 0], [[0, 50.0]], [[0, 0]], cfg)
    np.testing.assert_allclose(v, [1, 0])


def test_lp_projects_onto_one_half_plane():
    # allowed: det(d, p - v) <= 0 with d = (1, 0), p = (0, 0.5)  ->  v_y >= 0.5
    v = safety.solve(np.array([[0.0, 0.5]]), np.array([[1.0, 0.0]]), np.array([0.2, 0.0]), 2.0)
    np.testing.assert_allclose(v, [0.2, 0.5], atol=1e-12)


def test_straight_line_collides_on_the_circle():
    s, g = scenarios.antipodal_circle(4)
    r = evalsim.run(
        s,
        g,
        evalsim.straight_line,
        evalsim.PERFECT,
        evalsim.EvalSimConfig(),
        np.random.default_rng(0),
    )
    assert r["collisions"] == 4 and not r["success"]


def test_degraded_link_still_delivers():
    s, g = scenarios.antipodal_circle(4)
    r = evalsim.run(
        s,
        g,
        evalsim.straight_line,
        evalsim.DEGRADED,
        evalsim.EvalSimConfig(),
        np.random.default_rng(0),
    )
    assert r["collisions"] == 4


def test_eval_smoke(tmp_path):
    res = main(
        EvalConfig(
            out=str(tmp_path), quick=True, suites=("circle",), links=("perfect",), progress=False
        )
    )
    names = {s["controller"] for s in res["summary"]}
    assert {"policy", "policy+filter", "orca", "straight"} <= names
    assert (tmp_path / "results.md").read_text().startswith("| suite")
    assert json.loads((tmp_path / "results.json").read_text())["flops_20"] == 680_298
    assert (tmp_path / "fig5_heading_change.png").stat().st_size > 1000
    straight = [s for s in res["summary"] if s["controller"] == "straight"][0]
    assert straight["collisions"] > 0
    merged = merge([tmp_path / "results.json", tmp_path / "results.json"], tmp_path / "merged")
    assert len(merged["runs"]) == 2 * len(res["runs"])


def test_degraded_link_receivers_dead_reckon_like_the_agents():
    """On a 3 Hz, lossy, 100 ms link a receiver extrapolates the last state it got, as
    agent/neighbours.py does: its view lags by the latency (0.1 m at 1 m/s), not by the age
    of the state (up to 0.43 m and more after losses)."""
    starts = np.array([[0.0, 0.0], [0.0, 50.0]])
    goals = starts + [40.0, 0.0]  # side by side, far apart: both fly straight at 1 m/s
    worst = {}
    for dead_reckon in (True, False):
        errors = []

        def ctrl(ids, t_s, pos, vel, heading, goal, nbr_pos, *_, errors=errors):
            if len(ids) == 2 and t_s > 2.0:  # vehicle 0's view of vehicle 1, once at speed
                errors.append(float(np.linalg.norm(nbr_pos[0, 1] - pos[1])))
            return evalsim.straight_line(ids, t_s, pos, vel, heading, goal)

        cfg = evalsim.EvalSimConfig(dead_reckon=dead_reckon)
        evalsim.run(starts, goals, ctrl, evalsim.DEGRADED, cfg, np.random.default_rng(0))
        worst[dead_reckon] = max(errors)
    assert worst[True] <= 0.1 + 1e-9 and worst[False] >= 0.8, worst  # measured 0.1, 1.1
