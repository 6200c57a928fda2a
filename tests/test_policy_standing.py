"""Standing neighbours in the sparse-traffic rule (policy/sparse.py `still_speed_share`): a
covey vehicle holding its slot is passed straight when the line keeps its berth, counts as an
encounter when it does not, and never as near now; traffic always counts. The same choice on
every path (choose_one, choose_padded, C), and what it buys: a formation turned on its spot with
every vehicle keeping its slot arrives, where the policy alone circled the formation."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews
from groundstation.formation import FormationSpec, slots_ned_m
from policy import safety, sparse

CFG = sparse.SparseConfig()
OFF = sparse.SparseConfig(still_speed_share=0.0)
SAFE = safety.SafetyConfig()  # 3 m, 1 m/s: the trained period is 1 s
ASKED = np.array([0.6, -0.6])  # the "policy's" velocity, distinct from any straight line
GOAL = np.array([10.0, 0.0])
SLOT_NBRS = np.array([[10.0, -4.5], [10.0, 4.5]])  # holding their slots 4.5 m either side
STILL = np.zeros((2, 2))

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


def _choose(nbr_pos, nbr_vel, cfg=CFG, pos=(6.5, 0.0), vel=(0.8, 0.6), **sky):
    """From 3.5 m short of the goal (5.7 m from either slot neighbour, within two
    separations), flying 37 degrees off the line (not aligned with it)."""
    return sparse.choose_one(pos, vel, GOAL, ASKED, nbr_pos, nbr_vel, SAFE, cfg, 1.0, **sky)


def test_a_slot_between_two_holding_vehicles_is_flown_straight():
    v, straight = _choose(SLOT_NBRS, STILL)
    assert straight and np.allclose(v, [1.0, 0.0])
    # the rule before: both are within two separations now and we are not aligned -> policy
    v, straight = _choose(SLOT_NBRS, STILL, cfg=OFF)
    assert not straight and np.allclose(v, ASKED)
    # the same two moving at the cruise speed do not stand: near now, the policy
    _, straight = _choose(SLOT_NBRS, np.array([[0.0, 1.0], [0.0, 1.0]]))
    assert not straight
    # a slow drift (a quarter of the cruise speed) still stands
    _, straight = _choose(SLOT_NBRS, np.array([[0.2, 0.1], [-0.1, 0.2]]))
    assert straight


def test_traffic_that_does_not_cooperate_never_stands():
    coop = np.array([False, True])
    _, straight = _choose(SLOT_NBRS, STILL, nbr_cooperative=coop)
    assert not straight
    _, straight = _choose(SLOT_NBRS, STILL, nbr_manned=np.array([False, True]))
    assert not straight


def test_the_berth_grows_with_the_position_sigma():
    # 4.5 m is outside the exact berth (3.6 m) but inside 3.6 + 4 x sqrt(0.5^2 + 0.5^2) = 6.4 m:
    # then they are encounters, not near now: two, not dead-on -> straight, filter permitting
    count, nearest, now = sparse.encounters(
        [6.5, 0.0],
        [1.0, 0.0],
        SLOT_NBRS,
        STILL,
        np.ones(2, bool),
        3.5,
        6.0,
        0.25,
        sparse.standing_berth_m(SAFE, (2,), 0.5, np.full(2, 0.5)),
    )
    assert count == 2 and nearest == pytest.approx(4.5) and now == np.inf
    count, _, now = sparse.encounters(
        [6.5, 0.0], [1.0, 0.0], SLOT_NBRS, STILL, np.ones(2, bool), 3.5, 6.0, 0.25, np.full(2, 3.6)
    )
    assert count == 0 and now == np.inf


def test_a_holding_vehicle_on_the_line_is_dead_on_for_the_policy():
    v, straight = _choose(np.array([[8.5, 0.1]]), np.zeros((1, 2)))
    assert not straight and np.allclose(v, ASKED)


def test_the_float_berths_are_the_reference_berths():
    """choose_one's berths (Python floats) = standing_berth_m (numpy), bit for bit, with and
    without sigmas, cooperative and manned flags."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        k = int(rng.integers(0, 6))
        sky = {
            "pos_sigma_m": rng.choice([None, 0.0, 0.4]),
            "nbr_pos_sigma_m": None if rng.uniform() < 0.3 else rng.uniform(0, 1, k),
            "nbr_cooperative": None if rng.uniform() < 0.3 else rng.uniform(size=k) > 0.3,
            "nbr_manned": None if rng.uniform() < 0.5 else rng.uniform(size=k) > 0.7,
        }
        ref = sparse.standing_berth_m(SAFE, (k,), *sky.values()).tolist()
        assert sparse._standing_berths_one(SAFE, CFG, k, sky) == ref, sky
    assert sparse._standing_berths_one(SAFE, OFF, 3, {}) == [np.inf] * 3


def _scene(rng, k: int):
    """A random scene with standing, slow and moving neighbours, uncertainties and traffic."""
    f32 = lambda a: np.asarray(a, np.float32).astype(np.float64)  # noqa: E731
    pos, vel = f32(rng.uniform(-5, 5, 2)), f32(rng.uniform(-1, 1, 2))
    goal, asked = f32(rng.uniform(-20, 20, 2)), f32(rng.uniform(-1, 1, 2))
    nbr_pos = f32(rng.uniform(-15, 15, (k, 2)))
    speed = rng.choice([0.0, 0.1, 0.2, 0.5, 1.0], k)
    ang = rng.uniform(0, 2 * np.pi, k)
    nbr_vel = f32(np.c_[np.cos(ang), np.sin(ang)] * speed[:, None])
    sky = {
        "pos_sigma_m": float(f32(rng.choice([0.0, 0.5]))),
        "nbr_pos_sigma_m": f32(rng.choice([0.0, 0.3, 0.5], k)),
        "nbr_cooperative": rng.uniform(size=k) > 0.2,
    }
    return pos, vel, goal, asked, nbr_pos, nbr_vel, sky


def test_one_vehicle_fast_path_is_the_padded_reference_with_standing_neighbours():
    rng = np.random.default_rng(5)
    n_standing_straight = 0
    for _ in range(400):
        k = int(rng.integers(1, 6))
        pos, vel, goal, asked, nbr_pos, nbr_vel, sky = _scene(rng, k)
        one, s1 = sparse.choose_one(pos, vel, goal, asked, nbr_pos, nbr_vel, SAFE, CFG, 1.0, **sky)
        many, s2 = sparse.choose_padded(
            pos[None],
            vel[None],
            goal[None],
            asked[None],
            nbr_pos[None],
            nbr_vel[None],
            np.ones((1, k), bool),
            SAFE,
            CFG,
            1.0,
            pos_sigma_m=np.array([sky["pos_sigma_m"]]),
            nbr_pos_sigma_m=sky["nbr_pos_sigma_m"][None],
            nbr_cooperative=sky["nbr_cooperative"][None],
        )
        assert s1 == bool(s2[0])
        np.testing.assert_allclose(one, many[0], atol=1e-12)
        off = sparse.choose_one(pos, vel, goal, asked, nbr_pos, nbr_vel, SAFE, OFF, 1.0, **sky)[1]
        n_standing_straight += s1 and not off
    assert n_standing_straight >= 10  # the scenes exercise the rule


@needs_cc
def test_c_rule_is_the_numpy_rule_with_standing_neighbours():
    """covey_sparse_choose = choose_one on the same scenes (float32-exact inputs): the same
    choice but within float32 rounding of a threshold, the same velocity."""
    from firmware.cpolicy import CPolicy

    cpol = CPolicy.load(sparse_rule=True)
    filt = cpol._filter
    rng = np.random.default_rng(9)
    agree = near = 0
    for _ in range(1500):
        k = int(rng.integers(1, 6))
        pos, vel, goal, asked, nbr_pos, nbr_vel, sky = _scene(rng, k)
        c = filt.sparse(pos, vel, goal, asked, nbr_pos, nbr_vel, **sky)
        assert c.status == "ok"
        ref, straight = sparse.choose_one(
            pos, vel, goal, asked, nbr_pos, nbr_vel, cpol.safety_cfg, CFG, 1.0, **sky
        )
        if c.straight != straight:
            near += 1
            continue
        agree += 1
        np.testing.assert_allclose(c.vel_m_s, ref, atol=1e-5)
    assert near <= 4 and agree >= 1490


def _turn_the_circle(seed: int, c_core: bool, lag_s: float, limit_s: float = 120.0):
    """Eight point masses (10 Hz, velocity lag `lag_s`) in a 5 m circle at (20, 9) fly to the
    same circle moved 6 m and turned 90 degrees, each keeping its slot (as `covey cmd formation`
    sends a moved formation), and hold there on arrival. As the multi-vehicle host flies them
    (one BatchGuidance of 8 rows) or, with `c_core`, as 8 agents (a row each, the C core).
    (seconds until all hold, closest pair in m), None when one has not arrived by limit_s."""
    rng = np.random.default_rng(seed)
    start = slots_ned_m(FormationSpec("circle", 5.0, (20.0, 9.0), 8.0), 8)
    goal = slots_ned_m(FormationSpec("circle", 5.0, (26.0, 9.0), 8.0, 90.0), 8)
    n, dt_s = 8, 0.1
    pos = start.copy()
    pos[:, :2] += rng.normal(0.0, 0.3, (n, 2))
    vel, heading = np.zeros((n, 3)), np.zeros(n)
    cfg = GuidanceConfig(cruise_speed_m_s=2.0, c_core=c_core)
    rows = [BatchGuidance(cfg, 1) for _ in range(n)] if c_core else [BatchGuidance(cfg, n)]
    ids, arrived, closest = np.arange(1, n + 1), np.zeros(n, bool), np.inf
    for step in range(int(limit_s / dt_s)):
        t_s = step * dt_s
        views = NeighbourViews.nearest(
            pos,
            np.arange(n),
            pos,
            vel,
            heading,
            np.ones(n, bool),
            np.zeros(n, bool),
            None,
            ids,
            ids,
        )
        if c_core:
            cmd = np.vstack(
                [
                    g.step(
                        t_s,
                        np.array([0]),
                        pos[i : i + 1],
                        vel[i : i + 1],
                        heading[i : i + 1],
                        goal[i : i + 1],
                        arrived[i : i + 1],
                        views.take(np.array([i])),
                    ).vel_ned_m_s
                    for i, g in enumerate(rows)
                ]
            )
        else:
            out = rows[0].step(t_s, np.arange(n), pos, vel, heading, goal, arrived, views)
            cmd = out.vel_ned_m_s
        vel = cmd if lag_s <= 0 else vel + (cmd - vel) * min(1.0, dt_s / lag_s)
        pos = pos + vel * dt_s
        heading = np.where(
            np.hypot(vel[:, 0], vel[:, 1]) > 0.05, np.arctan2(vel[:, 1], vel[:, 0]), heading
        )
        d = np.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=2)
        closest = min(closest, float(d[~np.eye(n, dtype=bool)].min()))
        arrived |= np.linalg.norm(pos[:, :2] - goal[:, :2], axis=1) < 1.0
        if arrived.all():
            return t_s, closest
    return None, closest


@pytest.mark.slow
@pytest.mark.parametrize("c_core", [False, pytest.param(True, marks=needs_cc)])
def test_a_circle_turned_on_its_spot_arrives_keeping_separation(c_core):
    """Before the rule, 12 of these 20 runs (the host's numpy rows) had a vehicle circling the
    formation after 300 s of simulated flight."""
    times = []
    for seed in range(5):
        for lag_s in (0.0, 0.3):
            t_s, closest = _turn_the_circle(seed, c_core, lag_s)
            assert t_s is not None, (seed, lag_s, "a vehicle never reached its slot")
            assert closest >= 3.0, (seed, lag_s, closest)
            times.append(t_s)
    print(f"turned circles: median {np.median(times):.1f} s, longest {max(times):.1f} s")
