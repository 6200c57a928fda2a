"""A fast non-cooperative intruder on a vehicle's own line (head-on or from behind): the
separation filter steps aside, on the right-hand leg of the collision cone unless the vehicle is
already off the intruder's track, with a horizon long enough to do it in time (policy/safety.py
orca_lines, pair_horizon_s; covey_safety.c orca_line). Before, ORCA's correction pointed
straight back along the line and a faster intruder caught the fleeing vehicle. Closed loops on
ideal point masses, numpy and C; the two agree on (nearly) collinear vectors."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from policy import safety

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")
DT_S = 0.1
SEPARATION_M = 3.0


@pytest.fixture(scope="module")
def c_filter():
    from firmware.cpolicy import load_library
    from firmware.csafety import CSafetyFilter

    return CSafetyFilter(load_library(), safety.SafetyConfig())


def _numpy(pos, vel, pref, nbr_p, nbr_v):
    return safety.filter_one(
        pos, vel, pref, nbr_p, nbr_v, safety.SafetyConfig(), nbr_cooperative=np.array([False])
    )


def _fly(step, own_from, own_to, intr_from, intr_vel, duration_s=40.0):
    """Closest true distance between a vehicle flying own_from -> own_to at 1 m/s (filtered by
    `step`) and an intruder flying straight at intr_vel; exact states, DT_S steps."""
    pos, vel = np.array(own_from, float), np.zeros(2)
    goal, ipos, ivel = np.array(own_to, float), np.array(intr_from, float), np.array(intr_vel)
    closest = np.inf
    for _ in range(round(duration_s / DT_S)):
        to_goal = goal - pos
        d = np.hypot(*to_goal)
        pref = to_goal / d * min(1.0, d / DT_S) if d > 1e-9 else np.zeros(2)
        vel = np.asarray(step(pos, vel, pref, ipos[None], ivel[None]), float)
        pos, ipos = pos + vel * DT_S, ipos + ivel * DT_S
        closest = min(closest, float(np.hypot(*(pos - ipos))))
    return closest


ENCOUNTERS = [
    # (name, own from, own to, intruder from, intruder velocity per unit of speed)
    ("head-on", (0.0, 0.0), (60.0, 0.0), (60.0, 0.0), (-1.0, 0.0)),
    ("overtake", (0.0, 0.0), (60.0, 0.0), (-25.0, 0.0), (1.0, 0.0)),
    ("hovering", (0.0, 0.0), (0.0, 0.0), (40.0, 0.0), (-1.0, 0.0)),
    ("head-on-0.3m-off", (0.0, 0.0), (60.0, 0.0), (60.0, 0.3), (-1.0, 0.0)),
]


@pytest.mark.parametrize("speed_ratio", [1.0, 1.5, 2.0])
@pytest.mark.parametrize(("name", "own_from", "own_to", "intr_from", "intr_dir"), ENCOUNTERS)
def test_numpy_filter_steps_aside_of_a_fast_intruder_on_its_line(
    name, own_from, own_to, intr_from, intr_dir, speed_ratio
):
    """Before: head-on and overtaking at 1.5x/2x were caught (the vehicle fled along the line)."""
    intr_vel = np.array(intr_dir) * speed_ratio
    closest = _fly(_numpy, own_from, own_to, intr_from, intr_vel)
    assert closest >= 3.5, (name, speed_ratio, closest)


@needs_cc
@pytest.mark.parametrize("speed_ratio", [1.5, 2.0])
@pytest.mark.parametrize(("name", "own_from", "own_to", "intr_from", "intr_dir"), ENCOUNTERS)
def test_c_filter_steps_aside_the_same_way(
    c_filter, name, own_from, own_to, intr_from, intr_dir, speed_ratio
):
    def step(pos, vel, pref, nbr_p, nbr_v):
        r = c_filter.evaluate(pos, vel, pref, nbr_p, nbr_v, nbr_cooperative=np.array([False]))
        assert r.status == "ok"
        return r.vel_m_s

    intr_vel = np.array(intr_dir) * speed_ratio
    assert _fly(step, own_from, own_to, intr_from, intr_vel) >= 3.5


def test_dead_on_goes_right_and_off_track_keeps_its_side():
    """Head-on dead on the line, flying north: the vehicle steps east (right), as the rules of
    the air turn; 2 m west of a fast intruder's track it steps further west, never across."""
    vel = np.array([1.0, 0.0])
    ahead = _numpy(np.zeros(2), vel, vel, np.array([[15.0, 0.0]]), np.array([[-2.0, 0.0]]))
    assert ahead[1] > 0.2
    west = _numpy(np.zeros(2), vel, vel, np.array([[15.0, 2.0]]), np.array([[-2.0, 0.0]]))
    assert west[1] < -0.2
    behind = _numpy(np.zeros(2), vel, vel, np.array([[-10.0, -2.0]]), np.array([[2.0, 0.0]]))
    assert behind[1] > 0.1  # 2 m east of a faster one's track coming from behind: further east
    # already within r (3.6 m) of a faster one closing from behind: off its track at >= 0.8 m/s
    # (fleeing ahead at 1 m/s cannot work), on the same side as the step aside (west here)
    inside = _numpy(np.zeros(2), vel, vel, np.array([[-3.0, 0.0]]), np.array([[2.0, 0.0]]))
    assert inside[1] <= -0.8 + 1e-9
    far = _numpy(np.zeros(2), vel, vel, np.array([[-12.0, 0.0]]), np.array([[2.0, 0.0]]))
    assert far[1] < 0.0  # the step aside from further out goes the same way


def test_cooperative_neighbours_are_unchanged():
    """The step-aside rule and the longer horizon are for traffic only: the same dead-on pair
    told cooperative gives today's back-projection (no lateral component)."""
    vel = np.array([1.0, 0.0])
    p, v = np.array([[12.0, 0.0]]), np.array([[-1.0, 0.0]])
    coop = safety.filter_one(np.zeros(2), vel, vel, p, v, safety.SafetyConfig())
    told = safety.filter_one(
        np.zeros(2), vel, vel, p, v, safety.SafetyConfig(), nbr_cooperative=np.array([True])
    )
    assert np.array_equal(coop, told) and abs(coop[1]) < 1e-9


def _collinear_cases(rng, n):
    """Own state, preference and 1-3 neighbours (one non-cooperative, nearly on own line)."""
    f32 = np.float32
    for _ in range(n):
        k = int(rng.integers(1, 4))
        d = rng.uniform(1.0, 30.0)  # within r too (the escape rule)
        ang = rng.uniform(0, 2 * np.pi)
        u = np.array([np.cos(ang), np.sin(ang)])
        lat = np.array([-u[1], u[0]]) * rng.choice([0.0, rng.normal(0, 0.5)])
        own_v = u * rng.uniform(0, 1.0) * rng.choice([1.0, -1.0])
        nbr_p = [u * d + lat]
        nbr_v = [-u * rng.uniform(0.5, 3.0) * rng.choice([1.0, -1.0])]
        for _ in range(k - 1):
            nbr_p.append(rng.uniform(-10, 10, 2))
            nbr_v.append(rng.uniform(-1, 1, 2))
        coop = np.ones(k, bool)
        coop[0] = False
        yield (
            np.zeros(2),
            own_v.astype(f32).astype(float),
            own_v.astype(f32).astype(float),
            np.array(nbr_p).astype(f32).astype(float),
            np.array(nbr_v).astype(f32).astype(float),
            rng.permutation(coop) if k > 1 else coop,
        )


@needs_cc
def test_c_equals_numpy_on_nearly_collinear_traffic(c_filter):
    rng = np.random.default_rng(35)
    cfg = safety.SafetyConfig()
    n_aside = 0
    for pos, vel, pref, nbr_p, nbr_v, coop in _collinear_cases(rng, 600):
        ref = safety.filter_velocity(pos, vel, pref, nbr_p, nbr_v, cfg, nbr_cooperative=coop)
        one = safety.filter_one(pos, vel, pref, nbr_p, nbr_v, cfg, nbr_cooperative=coop)
        pad = safety.filter_padded(
            pos[None],
            vel[None],
            pref[None],
            nbr_p[None],
            nbr_v[None],
            np.ones((1, len(coop)), bool),
            cfg,
            nbr_cooperative=coop[None],
        )[0]
        c = c_filter.evaluate(pos, vel, pref, nbr_p, nbr_v, nbr_cooperative=coop)
        assert c.status == "ok"
        assert np.abs(one - ref).max() <= 1e-9 and np.abs(pad - ref).max() <= 1e-9
        assert np.abs(c.vel_m_s - ref).max() <= 1e-6, (ref, c.vel_m_s)
        dv = ref - pref
        n_aside += int(abs(pref[0] * dv[1] - pref[1] * dv[0]) > 0.05)
    assert n_aside > 100  # the lateral rule is exercised
