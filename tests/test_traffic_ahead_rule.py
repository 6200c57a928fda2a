"""The ahead rule (issue 35): a vehicle already within r of traffic that does not cooperate,
closing, and ahead of it on its track escapes sideways (the escape rule) and never comes back
along that track towards it, v . t >= 0 (policy/traffic_rules.py ahead_track, escape_lines;
firmware/covey_safety.c). Without it, fresh seed 42's `intruder-1x-conflict-8-s2` (realistic
vehicles, 3 Hz link, policy+filter) ended 2.97 m from a 1x intruder on true positions: the
escape line's velocity nearest the goal also flew back along the intruder's track. numpy's
three paths and C agree."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from policy import safety, traffic_rules
from tests.traffic_scenes import (
    ISSUE16_WEIGHTS,
    c_and_reference,
    c_filter,
    intruder_run,
    three_paths,
    without_kept_side,
)

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")
CFG = safety.SafetyConfig()  # 3 m, 1 m/s
SKY = {"pos_sigma_m": 0.5}


def _inside_ahead(rng: np.random.Generator, k: int):
    """A vehicle 4-6 m ahead of an intruder (1-2x cruise, so within its 6.4 m berth) and a
    little to one side, wanting to fly back past it (its goal behind the intruder), among `k`
    covey neighbours."""
    speed = rng.uniform(1.0, 2.0)
    ang = rng.uniform(0.0, 2.0 * np.pi)
    t = np.array([np.cos(ang), np.sin(ang)])
    n = np.array([-t[1], t[0]])
    pos = np.zeros(2)
    ip = pos - rng.uniform(4.0, 6.0) * t + rng.uniform(-2.0, 2.0) * n
    iv = speed * t
    vel = rng.uniform(0.3, 1.0) * t + rng.normal(0.0, 0.2, 2)
    pref = -t + rng.uniform(-0.5, 0.5) * n
    pref = pref / np.hypot(*pref)
    nbr_p = rng.uniform(-9.0, 9.0, (k, 2))
    nbr_p = nbr_p[np.hypot(*(nbr_p - pos).T) > 4.0]
    nbr_v = rng.normal(0.0, 0.5, (len(nbr_p), 2))
    nbr_p, nbr_v = np.vstack([nbr_p, ip]), np.vstack([nbr_v, iv])
    coop = np.ones(len(nbr_p), bool)
    coop[-1] = False
    return pos, vel, pref, nbr_p, nbr_v, coop, t


def test_ahead_track_picks_the_nearest_escaping_one_ahead() -> None:
    own = np.array([0.0, 0.0])
    # p = p_j - p_i; v = v_i - v_j. Three intruders at 1x: behind us (we are ahead), nearer
    # and behind us, and ahead of us (we are behind it, it flies away)
    p = np.array([[-5.0, 0.0], [-4.0, 0.5], [4.0, 0.0]])
    vj = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    v = own - vj
    active = np.array([True, True, True])
    t = traffic_rules.ahead_track(p[:, 0], p[:, 1], v[:, 0], v[:, 1], own, 1.0, active)
    # the second: nearest, but we are beside its track (p . v_j = 0.5 > 0); the third: we are
    # behind it
    assert np.allclose(t, [1.0, 0.0])
    # none escaping (the caller's test: within r and closing), or slower than cruise: NaN
    none = np.zeros(3, bool)
    assert np.isnan(
        traffic_rules.ahead_track(p[:, 0], p[:, 1], v[:, 0], v[:, 1], own, 1.0, none)
    ).all()
    slow = own - 0.5 * vj
    assert np.isnan(
        traffic_rules.ahead_track(p[:, 0], p[:, 1], slow[:, 0], slow[:, 1], own, 1.0, active)
    ).all()
    one = traffic_rules.ahead_one(-5.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0)
    assert one is not None and np.allclose(one[1], [1.0, 0.0]) and one[0] == 25.0
    assert traffic_rules.ahead_one(5.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0) is None  # behind it


def test_the_vehicle_never_flies_back_along_the_track_and_the_paths_agree(monkeypatch) -> None:
    rng = np.random.default_rng(3511)
    held = 0
    for _ in range(200):
        pos, vel, pref, nbr_p, nbr_v, coop, t = _inside_ahead(rng, int(rng.integers(0, 5)))
        a, b, c = three_paths(CFG, pos, vel, pref, nbr_p, nbr_v, coop)
        assert np.allclose(a, b, atol=1e-12) and np.allclose(a, c, atol=1e-12)
        assert float(a @ t) >= -1e-9, (a, t)
        held += 1
    assert held == 200
    # the rule is what holds it: without the ahead line the same encounters fly back
    monkeypatch.setattr(safety, "ahead_one", lambda *a: None)
    rng = np.random.default_rng(3511)
    back = 0
    for _ in range(200):
        pos, vel, pref, nbr_p, nbr_v, coop, t = _inside_ahead(rng, int(rng.integers(0, 5)))
        v = safety.filter_one(
            pos, vel, pref, nbr_p, nbr_v, CFG, nbr_cooperative=coop, **SKY,
            nbr_pos_sigma_m=np.full(len(nbr_p), 0.5),
        )  # fmt: skip
        back += bool(float(v @ t) < -0.05)
    assert back > 50


@needs_cc
def test_c_keeps_the_ahead_line_as_numpy_does() -> None:
    f = c_filter(CFG)
    rng = np.random.default_rng(3512)
    for _ in range(200):
        pos, vel, pref, nbr_p, nbr_v, coop, t = _inside_ahead(rng, int(rng.integers(0, 5)))
        r, ref = c_and_reference(f, CFG, pos, vel, pref, nbr_p, nbr_v, coop)
        assert r.status == "ok" and np.abs(r.vel_m_s - ref).max() <= 1e-4, (r.vel_m_s, ref)
        assert float(r.vel_m_s @ t) >= -1e-4


def test_seed_42_keeps_3_m_from_a_1x_intruder(monkeypatch) -> None:
    """The case that came within 2.97 m on fresh seed 42 (3 Hz link, policy+filter, realistic
    vehicles): with the ahead rule it keeps 3 m on true positions; without it, it does not.
    Traffic's speed margin (NC_SPEED_MARGIN), the escape's clear speed (`clear_speed`), the
    kept side (`kept_offset`) and the parting rule for pairs inside their padding
    (policy.safety.RECOVER_SPEED_SHARE; 5.62 m with it), each of which alone also keeps this
    case clear, are off here, so that the ahead rule is what is measured. The case was found
    with issue 16's weights, which fly it here: the weights trained on drifting estimates take
    another path through this conflict (5.05 m either way)."""

    def closest() -> float:
        r = intruder_run(
            42,
            "intruder-1x-conflict-8-s2",
            "policy+filter",
            "degraded",
            recover_speed_share=0.0,
            weights=str(ISSUE16_WEIGHTS),
        )
        return float(r["intruder_min_sep"])

    monkeypatch.setattr(traffic_rules, "NC_SPEED_MARGIN", 0.0)
    monkeypatch.setattr(
        traffic_rules, "clear_speed", lambda *a: traffic_rules.NC_ESCAPE_SHARE * a[4]
    )
    without_kept_side(monkeypatch)
    kept = closest()
    nan2 = np.full(2, np.nan)
    monkeypatch.setattr(
        safety, "ahead_track", lambda *a, **k: np.broadcast_to(nan2, a[4].shape).copy()
    )
    without = closest()
    assert kept >= 3.0 > without, (kept, without)
