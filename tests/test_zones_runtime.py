"""The runtime API with keep-out zones: GuidancePolicy.load(keep_out_m=...) and CPolicy the
same fly a goto around a concave zone (routes + the filter's hard lines) and arrive, never
within the filter's zone radius; without zones, the same call flies as before."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import shapely

from policy.runtime import GuidancePolicy

C_SHAPE = np.array([[0, 0], [20, 0], [20, 20], [0, 20], [0, 15], [15, 15], [15, 5], [0, 5]], float)
"""A C open to the west; its pocket is x 0..15, y 5..15."""
RADIUS_M = 1.8


def _fly(pol, start, goal, others=(), n_steps=1500, dt_s=0.1):
    """One vehicle (and `others`, straight-flying non-avoiding vehicles, as (pos, vel)) on an
    ideal point mass; returns (arrived, closest distance to the zone, seconds)."""
    zone = shapely.Polygon(C_SHAPE)
    pos, vel, h = np.array(start, float), np.zeros(2), 0.0
    goal = np.array(goal, float)
    closest = np.inf
    for step in range(n_steps):
        t = step * dt_s
        nbr = np.array([p + v * t for p, v in others]).reshape(-1, 2)
        nv = np.array([v for _, v in others], float).reshape(-1, 2)
        v = pol.command(pos, vel, h, goal, nbr, nv, np.zeros(len(nbr)))
        vel, pos = v, pos + dt_s * v
        if np.hypot(*v) > 0.05:
            h = float(np.arctan2(v[1], v[0]))
        closest = min(closest, zone.distance(shapely.Point(pos)))
        if np.hypot(*(goal - pos)) < 1.0:
            return True, closest, t
    return False, closest, n_steps * dt_s


def test_numpy_runtime_flies_out_of_a_pocket_and_around():
    pol = GuidancePolicy.load(keep_out_m=[C_SHAPE])
    arrived, closest, t_s = _fly(pol, [5, 10], [30, 10])
    assert arrived and closest >= RADIUS_M - 1e-6
    assert t_s < 1.3 * 56.7  # the route is 56.7 m at 1 m/s
    # without zones the same call flies straight into the wall
    bare = GuidancePolicy.load()
    arrived, closest, _ = _fly(bare, [5, 10], [30, 10], n_steps=300)
    assert closest == 0.0


def test_numpy_runtime_goal_behind_the_zone_with_traffic():
    pol = GuidancePolicy.load(keep_out_m=[C_SHAPE])
    # a vehicle that does not avoid, crossing the route south of the zone
    others = [(np.array([10.0, -12.0]), np.array([0.0, 0.5]))]
    arrived, closest, _ = _fly(pol, [-10, 10], [10, -8], others)
    assert arrived and closest >= RADIUS_M - 1e-6


def test_bad_zone_is_one_clear_error():
    with pytest.raises(ValueError, match="crosses itself"):
        GuidancePolicy.load(keep_out_m=[np.array([[0, 0], [10, 10], [10, 0], [0, 12]], float)])
    with pytest.raises(ValueError, match="3 distinct"):
        GuidancePolicy.load(keep_out_m=[np.array([[0, 0], [1, 1]], float)])


@pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")
def test_c_policy_flies_the_same_route():
    from firmware.cpolicy import CPolicy

    cpol = CPolicy.load(keep_out_m=[C_SHAPE])
    arrived, closest, t_s = _fly(cpol, [5, 10], [30, 10])
    assert arrived and closest >= RADIUS_M - 1e-3
    assert t_s < 1.3 * 56.7
    filt = cpol.filter([-1.0, 2.0], [1.0, 0.0], [1.0, 0.0], np.zeros((0, 2)), np.zeros((0, 2)))
    assert filt[0] <= 1e-6  # at the wall 1 m away (inside the radius): not towards it
