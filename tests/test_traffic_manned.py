"""Manned aircraft get their own berth in the separation filter: manned_radius_m (30 m by
default) instead of the separation, always with full responsibility (policy/safety.py
pair_radius_m, effective_cooperative; covey_safety.c COVEY_TRACK_MANNED). Numpy and C agree."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from policy import safety

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")
DT_S = 0.1


def test_pair_radius_of_a_manned_aircraft():
    cfg = safety.SafetyConfig()  # 3 m, margin 0.2, manned 30 m
    r, share = safety.pair_radius_m(
        cfg, 0.0, None, np.array([True, False, True]), np.array([False, False, True])
    )
    assert r.tolist() == pytest.approx([3.6, 3.6, 36.0])
    assert share.tolist() == [0.5, 1.0, 1.0]  # manned: never cooperative, whatever the flag
    none = safety.pair_radius_m(replace_manned(cfg, None), 0.0, None, None, np.array([True]))
    assert none[0].tolist() == pytest.approx([3.6]) and none[1].tolist() == [1.0]
    # no manned flags: today's values exactly
    assert safety.pair_radius_m(cfg) == (pytest.approx(3.6), 0.5)


def replace_manned(cfg, value):
    from dataclasses import replace

    return replace(cfg, manned_radius_m=value)


def _fly(step, manned, duration_s=80.0):
    """A vehicle hovering at the origin; an aircraft at 2 m/s passing 20 m to its east from 90
    m north. Closest true distance."""
    pos, vel = np.zeros(2), np.zeros(2)
    ipos, ivel = np.array([90.0, 20.0]), np.array([-2.0, 0.0])
    closest = np.inf
    for _ in range(round(duration_s / DT_S)):
        vel = np.asarray(step(pos, vel, np.zeros(2), ipos[None], ivel[None], manned), float)
        pos, ipos = pos + vel * DT_S, ipos + ivel * DT_S
        closest = min(closest, float(np.hypot(*(pos - ipos))))
    return closest


def _numpy(pos, vel, pref, nbr_p, nbr_v, manned):
    return safety.filter_one(
        pos,
        vel,
        pref,
        nbr_p,
        nbr_v,
        safety.SafetyConfig(),
        nbr_cooperative=np.array([False]),
        nbr_manned=np.array([manned]),
    )


def test_numpy_keeps_the_manned_berth():
    """Plain traffic 20 m aside needs nothing; the same aircraft flagged manned is given 30 m."""
    assert _fly(_numpy, False) == pytest.approx(np.hypot(0.0, 20.0), abs=0.01)
    assert _fly(_numpy, True) >= 30.0


def _c_step():
    """(the C filter, a `_fly` step through it: a manned or plain non-cooperative neighbour)."""
    from firmware.cpolicy import load_library
    from firmware.csafety import CSafetyFilter

    f = CSafetyFilter(load_library(), safety.SafetyConfig())

    def step(pos, vel, pref, nbr_p, nbr_v, manned):
        r = f.evaluate(
            pos,
            vel,
            pref,
            nbr_p,
            nbr_v,
            nbr_cooperative=np.array([False]),
            nbr_manned=np.array([manned]),
        )
        assert r.status == "ok"
        return r.vel_m_s

    return f, step


@needs_cc
def test_c_keeps_the_manned_berth_and_equals_numpy():
    f, step = _c_step()
    assert _fly(step, True) >= 30.0
    rng = np.random.default_rng(36)
    cfg = safety.SafetyConfig()
    f32 = np.float32
    for _ in range(300):
        k = int(rng.integers(1, 5))
        nbr_p = rng.uniform(-60, 60, (k, 2)).astype(f32).astype(float)
        nbr_v = rng.uniform(-3, 3, (k, 2)).astype(f32).astype(float)
        vel = rng.uniform(-0.7, 0.7, 2).astype(f32).astype(float)
        pref = rng.uniform(-0.7, 0.7, 2).astype(f32).astype(float)  # inside the speed disc
        coop, manned = rng.random(k) < 0.5, rng.random(k) < 0.4
        ref = safety.filter_velocity(
            np.zeros(2), vel, pref, nbr_p, nbr_v, cfg, nbr_cooperative=coop, nbr_manned=manned
        )
        pad = safety.filter_padded(
            np.zeros((1, 2)),
            vel[None],
            pref[None],
            nbr_p[None],
            nbr_v[None],
            np.ones((1, k), bool),
            cfg,
            nbr_cooperative=coop[None],
            nbr_manned=manned[None],
        )[0]
        c = f.evaluate(
            np.zeros(2), vel, pref, nbr_p, nbr_v, nbr_cooperative=coop, nbr_manned=manned
        )
        assert c.status == "ok"
        assert np.abs(pad - ref).max() <= 1e-9 and np.abs(c.vel_m_s - ref).max() <= 1e-6


@needs_cc
def test_c_refuses_a_bad_manned_radius():
    from dataclasses import replace

    from firmware.cpolicy import load_library
    from firmware.csafety import CSafetyFilter

    lib = load_library()
    args = ((0.0, 0.0), (0.0, 0.0), (1.0, 0.0), [[5.0, 0.0]], [[0.0, 0.0]])
    bad = replace(safety.SafetyConfig(), manned_radius_m=0.001)
    assert CSafetyFilter(lib, bad).evaluate(*args).status == "range"
    assert CSafetyFilter(lib, replace(bad, manned_radius_m=None)).evaluate(*args).status == "ok"


def _encounter(step, speed_m_s, heading_rad, goal_dir_rad, meet_s, miss_m):
    """A vehicle flying at cruise speed towards goal_dir_rad meets a manned aircraft at
    speed_m_s on heading_rad whose straight track passes miss_m from where the vehicle would be
    after meet_s. Closest true distance over the encounter."""
    pref = np.array([np.cos(goal_dir_rad), np.sin(goal_dir_rad)])
    ivel = speed_m_s * np.array([np.cos(heading_rad), np.sin(heading_rad)])
    perp = np.array([-np.sin(heading_rad), np.cos(heading_rad)])
    ipos = pref * meet_s + perp * miss_m - ivel * meet_s
    pos, vel, closest = np.zeros(2), pref.copy(), np.inf
    for _ in range(round((meet_s + 20.0) / DT_S)):
        vel = np.asarray(step(pos, vel, pref, ipos[None], ivel[None], True), float)
        pos, ipos = pos + vel * DT_S, ipos + ivel * DT_S
        closest = min(closest, float(np.hypot(*(pos - ipos))))
    return closest


def _fast_encounters(n: int, seed: int):
    """n random encounters with aircraft of 10-70 m/s (a helicopter to a light aircraft)."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield (
            rng.uniform(10, 70),
            rng.uniform(0, 2 * np.pi),
            rng.uniform(0, 2 * np.pi),
            rng.uniform(20, 45),
            rng.uniform(-30, 30),
        )


def test_a_vehicle_crossing_a_fast_aircrafts_track_keeps_the_berth():
    """A vehicle flying at a 60 m/s aircraft's track, 25 m from it when heard: with the 12 s
    horizon of small traffic it could not leave the 36 m berth in time (23.6 m); the wide
    berth's own horizon (traffic_rules.pair_horizon_s, 22 s) gives it the time. Random
    encounters alike (19 of 150 came within 30 m with 12 s)."""
    assert _encounter(_numpy, 60.0, np.pi, np.pi / 2, 33.3, -25.0) >= 30.0
    closest = [_encounter(_numpy, *e) for e in _fast_encounters(25, 7)]
    assert min(closest) >= 30.0, closest


@needs_cc
def test_c_crosses_a_fast_aircrafts_track_as_numpy_does():
    _, step = _c_step()
    assert _encounter(step, 60.0, np.pi, np.pi / 2, 33.3, -25.0) >= 30.0
    closest = [_encounter(step, *e) for e in _fast_encounters(10, 8)]
    assert min(closest) >= 30.0, closest


def test_a_realistic_vehicle_keeps_the_berth_from_fast_aircraft():
    """The same encounters flown by a realistic vehicle (lag, acceleration limit, gusts, its
    estimate 0.5 m off and the filter told so), judged on its true position."""
    from policy.pointmass import VehicleModel, Vehicles

    rng = np.random.default_rng(11)
    cfg = safety.SafetyConfig()
    closest = []
    for speed, heading, goal_dir, meet_s, miss_m in _fast_encounters(12, 12):
        pref = np.array([np.cos(goal_dir), np.sin(goal_dir)])
        ivel = speed * np.array([np.cos(heading), np.sin(heading)])
        ipos = pref * meet_s + np.array([-np.sin(heading), np.cos(heading)]) * miss_m
        ipos = ipos - ivel * meet_s
        veh = Vehicles(np.zeros((1, 2)), VehicleModel.realistic(), rng, vel_m_s=pref[None])
        best = np.inf
        for _ in range(round((meet_s + 20.0) / DT_S)):
            want = safety.filter_one(
                veh.est_pos_m[0],
                veh.ground_vel_m_s[0],
                pref,
                ipos[None],
                ivel[None],
                cfg,
                pos_sigma_m=veh.pos_sigma_m,
                nbr_cooperative=np.array([False]),
                nbr_manned=np.array([True]),
            )
            veh.step(np.asarray(want, float)[None], DT_S)
            ipos = ipos + ivel * DT_S
            best = min(best, float(np.hypot(*(veh.pos_m[0] - ipos))))
        closest.append(best)
    assert min(closest) >= 30.0, closest
