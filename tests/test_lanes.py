"""One-lane gaps: who goes first (policy/lanes.py), on a gate in a long wall that no route can
go round: the hold point, the tie-break both sides agree on, backing out, and who is not waited
for."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from policy.lanes import LaneConfig, hold_m, hold_short
from policy.routes import Router


def _box(n0, e0, n1, e1):
    return np.array([[n0, e0], [n1, e0], [n1, e1], [n0, e1]], float)


# a wall along north at e -4..4 with a 9 m gate at n -4.5..4.5: no way round within 1.5x
WALL = [_box(-104.5, -4, -4.5, 4), _box(4.5, -4, 104.5, 4)]
GATE = shapely.box(-4.5, -4, 4.5, 4)
PAD_M = 2.0  # sigma 0.5 m at sigma_k 4: the gate is one lane (14 m needed)
WEST, EAST = np.array([0.0, -20.0]), np.array([0.0, 20.0])


def _way(
    router, pos, goal, nbr_pos, nbr_vel, own_id=5, nbr_id=3, valid=True, pad_m=PAD_M, cfg=None
):
    """(the routed waypoint, hold_short's) of one vehicle with one neighbour."""
    way = router.next_waypoints([pos], [goal], pad_m)
    out = hold_short(
        router,
        [pos],
        [goal],
        way,
        pad_m,
        np.array([[nbr_pos]], float),
        np.array([[nbr_vel]], float),
        np.array([[valid]]),
        np.array([own_id]),
        np.array([[nbr_id]]),
        cfg,
    )
    return way[0], out[0]


def test_the_gate_is_one_lane_at_half_a_metre_and_two_way_exact():
    r = Router(WALL)
    assert r.one_lane_gaps() == ()  # sigma 0: 7.2 m needed, the gate is two-way
    gaps = r.widened(PAD_M).one_lane_gaps()
    assert len(gaps) == 1 and gaps[0].covers(GATE.buffer(-0.1))
    # no way round: the route goes through the gate
    rt = r.plan(WEST, EAST, pad_m=PAD_M)
    assert shapely.LineString(np.vstack([WEST, rt.waypoints_m])).intersects(GATE)


def test_a_vehicle_holds_short_of_one_coming_through_the_other_way():
    r = Router(WALL)
    wide = r.widened(PAD_M)
    way, held = _way(r, WEST, EAST, nbr_pos=[0.0, 1.0], nbr_vel=[0.0, -1.0])
    assert not np.allclose(way, held)
    gap = wide.one_lane_gaps()[0]
    spot = shapely.Point(held)
    # on its own side, out of the gap by about the two-way width, pulled over to its right
    assert held[1] < -4.0 and gap.distance(spot) >= 0.9 * hold_m(wide.cfg)
    assert held[0] < -1.0  # heading east, its right is south
    assert wide.in_sight_space(held)
    # the same neighbour flying with it, or not a neighbour: it goes on
    for vel, valid in (([0.0, 1.0], True), ([0.0, -1.0], False)):
        way, out = _way(r, WEST, EAST, nbr_pos=[0.0, 1.0], nbr_vel=vel, valid=valid)
        np.testing.assert_allclose(out, way)
    # stopped in the gap, or just out of it on this side and held up there: a lower id is
    # waited for, a higher one is not
    for nbr_pos in ([0.0, 1.0], [0.0, -8.0]):
        way, out = _way(r, WEST, EAST, nbr_pos=nbr_pos, nbr_vel=[0.0, 0.0], nbr_id=3)
        np.testing.assert_allclose(out, held)
        way, out = _way(r, WEST, EAST, nbr_pos=nbr_pos, nbr_vel=[0.0, 0.0], nbr_id=7)
        np.testing.assert_allclose(out, way)
    # one at its hold point on the far side (beyond the mouth) is not waited for
    way, out = _way(r, WEST, EAST, nbr_pos=[7.0, 18.0], nbr_vel=[0.0, 0.0], nbr_id=3)
    np.testing.assert_allclose(out, way)


def test_both_sides_of_the_gate_agree_on_who_goes_first():
    r = Router(WALL)
    a, b = np.array([0.0, -14.0]), np.array([0.0, 14.0])
    # a (id 3) flies east, b (id 5) west, both closing on the gate from 10 m
    _, a_out = _way(r, a, EAST, nbr_pos=b, nbr_vel=[0.0, -1.0], own_id=3, nbr_id=5)
    b_way, b_out = _way(r, b, WEST, nbr_pos=a, nbr_vel=[0.0, 1.0], own_id=5, nbr_id=3)
    a_waits = not np.allclose(a_out, r.next_waypoints([a], [EAST], PAD_M)[0])
    b_waits = not np.allclose(b_out, b_way)
    assert (a_waits, b_waits) == (False, True)  # the lower id goes first
    # a neighbour that waits itself (not closing on the gate) is not waited for
    way, out = _way(r, b, WEST, nbr_pos=a, nbr_vel=[0.0, 0.0], own_id=5, nbr_id=3)
    np.testing.assert_allclose(out, way)
    # one far from the gate is not waited for either
    way, out = _way(r, b, WEST, nbr_pos=[0.0, -40.0], nbr_vel=[0.0, 1.0], own_id=5, nbr_id=3)
    np.testing.assert_allclose(out, way)


def test_inside_the_gate_the_higher_id_backs_out():
    r = Router(WALL)
    inside = np.array([0.0, -1.0])
    # it flies east and meets id 3 coming west inside: id 5 backs out (west), id 1 goes on
    way, out = _way(r, inside, EAST, nbr_pos=[0.0, 2.5], nbr_vel=[0.0, -1.0], own_id=5)
    assert out[1] < inside[1] - 5.0 and not np.allclose(out, way)
    way, out = _way(r, inside, EAST, nbr_pos=[0.0, 2.5], nbr_vel=[0.0, -1.0], own_id=1)
    np.testing.assert_allclose(out, way)


def test_off_without_gaps_or_without_neighbours_nothing_changes():
    r = Router(WALL)
    oncoming = dict(nbr_pos=[0.0, 1.0], nbr_vel=[0.0, -1.0])
    way, off = _way(r, WEST, EAST, **oncoming, cfg=LaneConfig(enabled=False))
    np.testing.assert_allclose(off, way)
    # sigma 0: the gate is two-way, nobody waits
    way, out = _way(r, WEST, EAST, **oncoming, pad_m=None)
    np.testing.assert_allclose(out, way)
    # no router (no zones), no neighbours: the waypoints as given
    way = r.next_waypoints([WEST], [EAST])
    none = hold_short(
        None,
        [WEST],
        [EAST],
        way,
        None,
        np.zeros((1, 0, 2)),
        np.zeros((1, 0, 2)),
        np.zeros((1, 0), bool),
    )
    np.testing.assert_allclose(none, way)


@pytest.mark.parametrize("field", ["oncoming_m_s", "look_m", "mouth_share", "pull_over_share"])
def test_lane_config_is_checked(field):
    with pytest.raises(ValueError, match=f"{field} must be finite and >= 0"):
        LaneConfig(**{field: -1.0})


def test_the_agents_guidance_holds_short_as_covey_eval_does():
    """BatchGuidance (agent/guidance.py) gives a vehicle on plain GNSS the hold point while a
    neighbour comes through the gate the other way; traffic that does not cooperate is not
    waited for, and sigma 0 (a two-way gate) flies on."""
    from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews

    g = BatchGuidance(GuidanceConfig(), 1)
    g.set_zones(WALL)
    pos = np.array([[WEST[0], WEST[1], -5.0]])
    target = np.array([[EAST[0], EAST[1], -5.0]])

    def waypoint(sigma_m, cooperative=None):
        views = NeighbourViews(
            np.array([[[0.0, 1.0, -5.0]]]), np.array([[[0.0, -1.0, 0.0]]]), np.zeros((1, 1)),
            np.ones((1, 1), bool), np.zeros((1, 1), bool), np.array([[3]]), np.array([5]),
            np.array([[sigma_m]]), cooperative, np.array([sigma_m]),
        )  # fmt: skip
        g.step(
            0.0, np.arange(1), pos, np.zeros((1, 3)), np.zeros(1), target, np.zeros(1, bool), views
        )
        return g.waypoint_m[0].copy()

    pad = g.safety_cfg.sigma_k * 0.5
    router = g.router
    free = router.next_waypoints(pos[:, :2], target[:, :2], pad)[0]
    held = waypoint(0.5)
    assert not np.allclose(held, free) and held[1] < -4.0
    np.testing.assert_allclose(waypoint(0.5, cooperative=np.array([[False]])), free)
    np.testing.assert_allclose(waypoint(0.0), router.next_waypoints(pos[:, :2], target[:, :2])[0])
