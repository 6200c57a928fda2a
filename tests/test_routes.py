"""Route planner around keep-out zones (policy/routes.py): legs never cut an inflated zone,
concave zones, narrow gaps closed, fences, refusals; and the stateless next waypoint."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from policy.routes import RouteConfig, Router

SQ = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
# a C open to the west: its pocket is x 0..15, y 5..15
C_SHAPE = np.array([[0, 0], [20, 0], [20, 20], [0, 20], [0, 15], [15, 15], [15, 5], [0, 5]], float)


def _clear_of(route_pts, zones, dist_m) -> bool:
    """The polyline keeps at least dist_m (less a hair) from every zone."""
    line = shapely.LineString(route_pts)
    grown = shapely.union_all([shapely.Polygon(z).buffer(dist_m - 1e-3) for z in zones])
    return not line.intersects(grown)


def test_convex_zone_is_rounded_and_legs_keep_the_inflation():
    r = Router([SQ])
    rt = r.plan([-10, 5], [20, 5])
    assert rt.reason == ""
    assert len(rt.waypoints_m) >= 2
    np.testing.assert_allclose(rt.waypoints_m[-1], [20, 5])
    assert _clear_of(np.vstack([[-10, 5], rt.waypoints_m]), [SQ], RouteConfig().inflate_m)
    # a straight line would cut through the zone: the route is longer, but not by much
    assert 30.0 < rt.length_m < 40.0


def test_concave_zone_start_in_its_pocket():
    r = Router([C_SHAPE])
    rt = r.plan([5, 10], [30, 10])
    assert rt.reason == ""
    pts = np.vstack([[5, 10], rt.waypoints_m])
    assert _clear_of(pts, [C_SHAPE], RouteConfig().inflate_m - 0.5 * RouteConfig().route_margin_m)
    assert shapely.LineString(pts).intersects(shapely.Point(-2.0, 10).buffer(3.0))  # out the mouth


def test_gap_of_three_separations_is_open_and_a_narrow_one_closed():
    a = SQ
    wide = Router([a, a + [0, 19]])  # a 9 m gap: 3 separations
    rt = wide.plan([-10, 14.5], [20, 14.5])
    assert len(rt.waypoints_m) == 1 and rt.length_m == pytest.approx(30.0)
    narrow = Router([a, a + [0, 14]])  # 4 m < 2 x 2.3 m: closed
    rt = narrow.plan([-10, 12], [20, 12])
    pts = np.vstack([[-10, 12], rt.waypoints_m])
    assert not shapely.LineString(pts).intersects(shapely.box(0, 10, 10, 14))
    assert _clear_of(pts, [a, a + [0, 14]], RouteConfig().sight_m)


def test_refusals_and_walled_off_goal():
    r = Router([SQ])
    assert r.plan([-10, 5], [5, 5]).reason == "the goal is inside a keep-out zone"
    fence = np.array([[-30, -30], [30, -30], [30, 30], [-30, 30]], float)
    rf = Router([SQ], fence_m=fence)
    assert rf.plan([-10, 5], [40, 5]).reason == "the goal is outside the fence"
    # a ring of zones around the goal: no way in
    ring = [
        np.array([[-10, -10], [10, -10], [10, -6], [-10, -6]], float),
        np.array([[-10, 6], [10, 6], [10, 10], [-10, 10]], float),
        np.array([[-10, -10], [-6, -10], [-6, 10], [-10, 10]], float),
        np.array([[6, -10], [10, -10], [10, 10], [6, 10]], float),
    ]
    rw = Router(ring)
    rt = rw.plan([-30, 0], [0, 0])
    assert rt.reason.startswith("no route")
    np.testing.assert_allclose(rw.next_waypoint([-30, 0], [0, 0]), [0, 0])


def test_fence_keeps_routes_inside():
    fence = np.array([[-15, -15], [25, -15], [25, 25], [-15, 25]], float)
    r = Router([SQ], fence_m=fence)
    rt = r.plan([-10, 5], [20, 5])
    pts = np.vstack([[-10, 5], rt.waypoints_m])
    inner = shapely.Polygon(fence).buffer(-RouteConfig().inflate_m + 1e-3)
    assert inner.covers(shapely.LineString(pts[:-1]))


def test_next_waypoint_advances_when_the_next_is_in_sight():
    r = Router([SQ])
    first = r.next_waypoint([-10, 5], [20, 5])
    assert not np.allclose(first, [20, 5])
    # past the zone's corner the goal is in sight
    np.testing.assert_allclose(r.next_waypoint([12.5, 12.5], [20, 5]), [20, 5])
    # a vehicle pushed near the zone is led out first, not through it
    out = r.next_waypoint([-0.5, 5], [20, 5])
    assert out[0] < -0.5


def test_goal_next_to_a_zone_edge_is_reached_through_its_nearest_free_point():
    r = Router([SQ])
    goal = np.array(
        [12.0, 5.0]
    )  # 2 m from the east edge: within the inflation, outside the filter's
    rt = r.plan([-10, 5], goal)
    assert rt.reason == ""
    np.testing.assert_allclose(rt.waypoints_m[-1], goal)
    assert rt.waypoints_m[-2][0] > 10 + RouteConfig().inflate_m - 0.05


def test_random_scenes_never_cut_the_inflated_zones():
    rng = np.random.default_rng(3)
    cfg = RouteConfig()
    checked = 0
    for _ in range(30):
        zones = []
        for _ in range(rng.integers(1, 4)):
            c = rng.uniform(-20, 20, 2)
            w, h = rng.uniform(3, 12, 2)
            zones.append(c + np.array([[0, 0], [w, 0], [w, h], [0, h]]))
        r = Router(zones)
        grown = shapely.union_all([shapely.Polygon(z).buffer(cfg.sight_m) for z in zones])
        for _ in range(5):
            s, g = rng.uniform(-40, 40, (2, 2))
            if grown.covers(shapely.Point(s)) or grown.covers(shapely.Point(g)):
                continue
            rt = r.plan(s, g)
            if rt.reason:
                continue
            checked += 1
            assert _clear_of(np.vstack([s, rt.waypoints_m]), zones, cfg.sight_m)
    assert checked > 50


def test_next_waypoints_equals_the_one_by_one_answer():
    rng = np.random.default_rng(11)
    r = Router([SQ, C_SHAPE + [30, 0]])
    pos = rng.uniform(-20, 60, (300, 2))
    goal = rng.uniform(-20, 60, (300, 2))
    goal[:5] = pos[:5]  # on the spot
    pos[5] = [np.nan, 0.0]  # a bad row passes through as it is
    got = r.next_waypoints(pos, goal)
    for i in range(300):
        if i == 5:
            np.testing.assert_array_equal(got[i], goal[i])
            continue
        np.testing.assert_allclose(got[i], r.next_waypoint(pos[i], goal[i]), err_msg=str(i))


def test_widened_routes_keep_the_filters_padding_more_and_are_kept_per_step():
    r = Router([SQ])
    assert r.widened(0.0) is r and r.widened(float("nan")) is r and r.widened(-1.0) is r
    wide = r.widened(1.5)
    assert wide is r.widened(1.3) and wide is not r.widened(1.51)  # one per 0.25 m step
    assert wide.cfg.inflate_m == pytest.approx(r.cfg.inflate_m + 1.5)
    rt = r.plan([-10, 5], [20, 5], pad_m=1.5)
    assert rt.reason == ""
    pts = np.vstack([[-10, 5], rt.waypoints_m])
    assert _clear_of(pts, [SQ], r.cfg.inflate_m + 1.5)
    assert not _clear_of(np.vstack([[-10, 5], r.plan([-10, 5], [20, 5]).waypoints_m]), [SQ], 3.0)
    np.testing.assert_allclose(
        r.next_waypoint([-10, 5], [20, 5], 1.5), wide.next_waypoint([-10, 5], [20, 5])
    )


def test_widened_router_falls_back_where_its_padding_walls_the_goal_off():
    # two rooms joined by a corridor 9 m wide: open at the base inflation (2.3 m a side),
    # closed at 3 m more; the widened router routes as the base one there
    fence = np.array(
        [[0, 0], [30, 0], [30, 10.5], [60, 10.5], [60, 0], [90, 0], [90, 30], [60, 30],
         [60, 19.5], [30, 19.5], [30, 30], [0, 30]],
        float,
    )  # fmt: skip
    r = Router([], fence_m=fence)
    start, goal = np.array([15.0, 8.0]), np.array([75.0, 22.0])
    assert r.plan(start, goal).reason == ""
    assert r.widened(3.0).plan(start, goal).reason == ""  # the fallback's route
    np.testing.assert_allclose(r.next_waypoint(start, goal, 3.0), r.next_waypoint(start, goal))
    np.testing.assert_allclose(
        r.next_waypoints(start[None], goal[None], 3.0)[0], r.next_waypoint(start, goal)
    )


def test_next_waypoints_with_pads_equals_the_one_by_one_answer():
    rng = np.random.default_rng(12)
    r = Router([SQ, C_SHAPE + [30, 0]])
    pos = rng.uniform(-20, 60, (200, 2))
    goal = rng.uniform(-20, 60, (200, 2))
    pad = rng.choice([0.0, 0.6, 1.5, 2.1, np.nan], 200)
    got = r.next_waypoints(pos, goal, pad)
    for i in range(200):
        want = r.next_waypoint(pos[i], goal[i], 0.0 if np.isnan(pad[i]) else pad[i])
        np.testing.assert_allclose(got[i], want, err_msg=str(i))


# --- two-way ways first (RouteConfig.two_way) ---

GAP_BLOCKS = [
    np.array([[-14.5, -4], [-4.5, -4], [-4.5, 4], [-14.5, 4]], float),
    np.array([[4.5, -4], [14.5, -4], [14.5, 4], [4.5, 4]], float),
]  # 9 m apart along north = 0, as covey eval's gap scene


def _through_gap(start, route) -> bool:
    pts = np.vstack([start, route.waypoints_m])
    return shapely.LineString(pts).intersects(shapely.box(-4.5, -4, 4.5, 4))


def test_a_one_lane_gap_is_flown_round_where_the_detour_is_short():
    r = Router(GAP_BLOCKS)
    # sigma 0: two-way needs 2 (1.8 + 1.8) = 7.2 m, the 9 m gap is two-way: straight through
    assert r.two_way() is None
    rt = r.plan([-10, -25], [10, 25])
    assert _through_gap([-10, -25], rt) and rt.length_m < 54.0
    # sigma 0.5 at k 4 (pad 2 m): two-way needs 14 m; round the blocks, 1.38x the one-lane way
    assert r.widened(2.0).two_way() is not None
    rt = r.plan([-10, -25], [10, 25], pad_m=2.0)
    assert rt.reason == "" and not _through_gap([-10, -25], rt)
    one_lane = r.widened(2.0)._plan_one_lane(np.array([-10.0, -25]), np.array([10.0, 25]))
    assert _through_gap([-10, -25], one_lane)
    assert one_lane.length_m < rt.length_m <= 1.5 * one_lane.length_m
    # every route leg keeps the zone clearance plus the route margin, as one-lane legs do
    pts = np.vstack([[-10, -25], rt.waypoints_m])
    assert _clear_of(pts, GAP_BLOCKS, r.widened(2.0).cfg.inflate_m)
    # the waypoint flown now is the plan's first, one row or many
    way = r.next_waypoint([-10, -25], [10, 25], 2.0)
    np.testing.assert_allclose(way, rt.waypoints_m[0])
    ways = r.next_waypoints([[-10, -25], [0, -30]], [[10, 25], [0, 30]], [2.0, 2.0])
    np.testing.assert_allclose(ways[0], way)
    np.testing.assert_allclose(ways[1], r.next_waypoint([0, -30], [0, 30], 2.0))


def test_a_long_detour_keeps_the_one_lane_gap():
    # two walls 200 m long with the 9 m gap between: round them is far more than 1.5x
    walls = [
        np.array([[-204.5, -4], [-4.5, -4], [-4.5, 4], [-204.5, 4]], float),
        np.array([[4.5, -4], [204.5, -4], [204.5, 4], [4.5, 4]], float),
    ]
    r = Router(walls)
    rt = r.plan([-10, -25], [10, 25], pad_m=2.0)
    assert rt.reason == "" and _through_gap([-10, -25], rt)
    assert rt.length_m < 1.5 * 54.0
    # off: the one-lane route whatever the gap
    off = Router(GAP_BLOCKS, RouteConfig(two_way=False))
    assert off.widened(2.0).two_way() is None
    assert _through_gap([-10, -25], off.plan([-10, -25], [10, 25], pad_m=2.0))


def test_two_way_keeps_a_lone_zone_and_goals_in_a_filled_gap_as_they_were():
    r = Router([SQ])
    assert r.widened(2.0).two_way() is None  # nothing to close: no second router
    # a goal inside the gap the two-way router fills is routed one-lane, to the goal
    r = Router(GAP_BLOCKS)
    rt = r.plan([0, -30], [0, 0], pad_m=2.0)
    assert rt.reason == "" and _through_gap([0, -30], rt)
    np.testing.assert_allclose(rt.waypoints_m[-1], [0, 0])


@pytest.mark.parametrize("bad", [0.99, float("nan"), float("inf")])
def test_two_way_detour_bound_is_checked(bad):
    with pytest.raises(ValueError, match="two_way_detour_max must be finite and >= 1"):
        RouteConfig(two_way_detour_max=bad)


FENCE = np.array([[-40, -40], [40, -40], [40, 40], [-40, 40]], float)
NEAR_FENCE = np.array([[-6, 21], [6, 21], [6, 31], [-6, 31]], float)  # 9 m from the y = 40 edge


def test_a_one_lane_gap_between_a_zone_and_the_fence_is_flown_round_too():
    r = Router([NEAR_FENCE], fence_m=FENCE)
    # without the fence the block stands alone: nothing to close
    assert Router([NEAR_FENCE]).widened(2.0).two_way() is None
    lane = r.widened(2.0).two_way()
    assert lane is not None
    filled = shapely.union_all([shapely.Polygon(p) for p in lane.keep_out_m])
    assert filled.covers(shapely.box(-6, 31, 6, 40))  # the gap to the fence is filled
    assert not filled.intersects(shapely.box(-39, -39, 39, 20))  # and nothing else
    gap = shapely.box(-6, 31, 6, 40)
    # sigma 0: 9 m is two-way (7.2 m needed), straight through the gap
    rt = r.plan([-25, 33], [25, 33])
    assert rt.reason == "" and shapely.LineString(
        np.vstack([[-25, 33], rt.waypoints_m])
    ).intersects(gap)
    # sigma 0.5 at k 4: round the block's far side, within 1.5x of the one-lane way
    rt = r.plan([-25, 33], [25, 33], pad_m=2.0)
    pts = np.vstack([[-25, 33], rt.waypoints_m])
    assert rt.reason == "" and not shapely.LineString(pts).intersects(gap)
    assert rt.length_m <= 1.5 * 50.5
    assert _clear_of(pts, [NEAR_FENCE], r.widened(2.0).cfg.inflate_m)
    assert (
        shapely.Polygon(FENCE)
        .buffer(-r.widened(2.0).cfg.inflate_m + 1e-3)
        .covers(shapely.LineString(pts))
    )
    # a goal inside the filled gap is still routed to, one-lane
    rt = r.plan([-25, 33], [0, 36], pad_m=2.0)
    assert rt.reason == ""
    np.testing.assert_allclose(rt.waypoints_m[-1], [0, 36], atol=0.5)


def test_a_vehicle_a_hair_off_its_corner_flies_on_to_the_next() -> None:
    """Seed 59's zones-random-s2 (every suite): vehicle 4 reached its first corner a hair off
    it, on the side from which the next leg clips the inflation; the corner kept being chosen,
    straight flight slowed onto it and the vehicle sat there until timed out (ideal vehicles,
    both links). Within CORNER_PASSED_M of the corner it chooses, a vehicle flies to the
    corner's successor, in the one-row and the batch path alike, and the scene's vehicles all
    arrive."""
    from policy import eval as ev
    from policy import evalsim, zone_eval
    from policy.routes import CORNER_PASSED_M, zones_for

    cfg = ev.EvalConfig(
        seed=59,
        suites=("circle", "conflict", "large", "intruder", "zones"),
        controllers=("policy+filter",),
    )
    case = next(c for c in ev.cases(cfg) if c[1] == "zones-random-s2")
    _, _, starts, goals, opts = case
    ctrl = ev.controllers(cfg)["policy+filter"]
    _, router = zones_for(ctrl.safety_cfg, opts["zones_m"])
    plan = router.plan(starts[4], goals[4]).waypoints_m
    corner, after = plan[0], plan[1]
    rng = np.random.default_rng(2)
    for _ in range(20):  # anywhere within the passed radius: the successor
        off = rng.normal(size=2)
        here = corner + off / np.linalg.norm(off) * rng.uniform(0, 0.9 * CORNER_PASSED_M)
        if not router._reach_ok.covers(shapely.Point(*here)):
            continue
        np.testing.assert_allclose(router.next_waypoint(here, goals[4]), after)
        np.testing.assert_allclose(router.next_waypoints(here[None], goals[4][None])[0], after)
    r = zone_eval.run(
        "policy+filter",
        starts,
        goals,
        opts["zones_m"],
        ctrl,
        evalsim.PERFECT,
        evalsim.EvalSimConfig(),
        np.random.default_rng(0),
    )
    assert r["timeouts"] == 0 and r["arrived"] == len(goals) and r["zone_entries"] == 0
