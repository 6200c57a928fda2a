"""Editing the fleet plan, without a browser: each step of a draft (groundstation/plan_edit.py)
is taken or refused with its reason (zones, the fence, home and rally points); the station's routes around the zones (plan_routes.py) keep
out of them and are drawn in a real viser scene; the command log lists plan versions with who
pushed them and what changed."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import viser

from comms.plan import MAX_RALLY_POINTS, Fence, FleetPlan, RallyPoint, Zone
from comms.schema import Mode, StateFlag, VehicleState
from groundstation import plan_edit as pe
from groundstation.command_log import CommandLog
from groundstation.plan_draft_view import draft_html
from groundstation.plan_editor import vehicle_points
from groundstation.plan_routes import RouteLayer
from groundstation.scene import FleetScene, SceneConfig
from groundstation.state_routes import planned_routes
from groundstation.tables import command_log_html
from groundstation.target_check import router_for

SQUARE = ((0.0, 0.0), (0.0, 10.0), (10.0, 10.0), (10.0, 0.0))
FENCE = Fence(((-100, -100), (-100, 100), (100, 100), (100, -100)), 2.0, 80.0)


def base_plan() -> FleetPlan:
    return FleetPlan("f", 7, 0, FENCE, (Zone(SQUARE, "depot"),))


def drawn(corners, name="pond", draft=None, vehicles=()) -> pe.Draft:
    d = draft or pe.draft_of(base_plan())
    for n, e in corners:
        d = pe.add_corner(d, n, e)
    return pe.close_zone(d, name, vehicles)


def state(vid, pos_ne, goal_ne=None, alt_m=10.0, mode=Mode.GOTO) -> VehicleState:
    goal = (0.0, 0.0, 0.0) if goal_ne is None else (*goal_ne, -alt_m)
    flags = StateFlag.NONE if goal_ne is None else StateFlag.HAS_GOAL
    return VehicleState(
        vid, 1, 0, (*pos_ne, -alt_m), (0.0, 0.0, 0.0), 0.0, mode, flags=flags, goal_ned_m=goal
    )


def test_a_zone_clicked_corner_by_corner_is_added_and_listed_as_an_edit() -> None:
    d = drawn([(30, 30), (30, 40), (40, 40), (40, 30)])
    assert d.base_version == 7 and d.corners_ne_m == ()
    assert [z.name for z in d.geometry.keep_out] == ["depot", "pond"]
    assert d.geometry.keep_out[1].vertices_ne_m == ((30, 30), (30, 40), (40, 40), (40, 30))
    assert d.describe_edits() == "zone 2 ('pond') added (4 corners)"


@pytest.mark.parametrize(
    ("corners", "reason"),
    [
        ([(30, 30), (30, 40)], "a zone needs at least 3 corners; 2 clicked"),
        ([(30, 30), (40, 40), (30, 40), (40, 30)], "is not a valid polygon: Self-intersection"),
        ([(30, 30), (30, 40), (30.05, 35)], "degenerate"),
        ([(-90, -90), (-90, -70), (-70, -70), (-70, -90)], "vehicle 3's target"),
        ([(45, 45), (45, 55), (55, 55), (55, 45)], "vehicle 4's position"),
    ],
)
def test_a_bad_zone_is_refused_with_its_reason_and_the_draft_is_kept(corners, reason) -> None:
    vehicles = vehicle_points([state(3, (0, 50), (-80, -80)), state(4, (50, 50))])
    d = pe.draft_of(base_plan())
    for n, e in corners:
        d = pe.add_corner(d, n, e)
    with pytest.raises(pe.EditRefused, match=reason.replace("(", r"\(").replace(")", r"\)")):
        pe.close_zone(d, "bad", vehicles)
    assert len(d.corners_ne_m) == len(corners) and len(d.geometry.keep_out) == 1


def test_a_vehicle_already_in_a_zone_blocks_no_edit_elsewhere_but_any_that_grows_it() -> None:
    inside = vehicle_points([state(5, (5.0, 5.0))])  # drifted into 'depot'
    d = drawn([(30, 30), (30, 40), (40, 40)], vehicles=inside)
    d = pe.set_fence_band(d, None, 70.0, inside)
    assert len(d.edits) == 2
    with pytest.raises(pe.EditRefused, match=r"vehicle 5's position \(N 5.0, E 5.0 m\)"):
        drawn([(3, 3), (3, 8), (8, 8)], "inner", vehicles=inside)  # a second zone over it
    with pytest.raises(pe.EditRefused, match="vehicle 5's position"):
        pe.checked(d.geometry, inside)  # without the geometry it replaces: every rule applies


def test_corners_and_zones_move_and_go_and_the_fence_band_is_checked() -> None:
    d = drawn([(30, 30), (30, 40), (40, 40), (40, 30), (35, 25)])
    d = pe.move_corner(d, 2, 5, 35, 28)
    assert d.geometry.keep_out[1].vertices_ne_m[4] == (35, 28)
    d = pe.delete_corner(d, 2, 5)
    assert len(d.geometry.keep_out[1].vertices_ne_m) == 4
    with pytest.raises(pe.EditRefused, match="Self-intersection"):
        pe.move_corner(d, 2, 2, 45, 35)  # across the opposite edge: a bow tie
    with pytest.raises(pe.EditRefused, match="zone 3 does not exist"):
        pe.delete_zone(d, 3)
    with pytest.raises(pe.EditRefused, match="zone 2 has no corner 9"):
        pe.delete_corner(d, 2, 9)
    target = vehicle_points([state(1, (60, 60), (60, 60), alt_m=50.0)])
    with pytest.raises(pe.EditRefused, match="vehicle 1's target .* above the 40 m ceiling"):
        pe.set_fence_band(d, 2.0, 40.0, target)
    with pytest.raises(pe.EditRefused, match="floor 60 m must be below its ceiling 40 m"):
        pe.set_fence_band(d, 60.0, 40.0)
    d = pe.set_fence_band(d, None, 60.0, target)
    assert d.geometry.fence.ceiling_alt_m == 60.0 and d.geometry.fence.floor_alt_m is None
    d = pe.delete_zone(d, 1)
    assert [z.name for z in d.geometry.keep_out] == ["pond"]
    with pytest.raises(pe.EditRefused, match="has 3 corners, the fewest"):
        pe.delete_corner(drawn([(30, 30), (30, 40), (40, 40)]), 2, 1)
    assert d.describe_edits().split("; ") == [
        "zone 2 ('pond') added (5 corners)",
        "zone 2 ('pond') corner 5 moved to N 35, E 28",
        "zone 2 ('pond') corner 5 deleted",
        "fence floor none, ceiling 60 m",
        "zone 1 ('depot') deleted",
    ]
    with pytest.raises(pe.EditRefused, match="no fence"):
        pe.set_fence_band(pe.draft_of(None), 1.0, 5.0)


def test_the_station_routes_a_goto_around_a_zone_and_draws_it() -> None:
    plan = base_plan()
    zone = shapely.Polygon(SQUARE)
    router = router_for(plan, 3.0)
    states = [
        state(1, (-5.0, 5.0), (15.0, 5.0)),  # behind the zone: routed around it
        state(2, (-5.0, 20.0), (15.0, 20.0)),  # clear of it: straight
        state(3, (-5.0, 5.0), (15.0, 5.0), mode=Mode.HOLDING),  # not flying a goto: none
        state(4, (-5.0, 5.0)),  # no goal: none
    ]
    routes = planned_routes(router, states)
    assert set(routes) == {1, 2}
    bent = routes[1]
    assert len(bent) >= 4 and tuple(bent[-1]) == (15.0, 5.0, -10.0)
    line = shapely.LineString(bent[:, :2])
    assert line.distance(zone) >= 2.0, line.distance(zone)  # inflated by 1.8 + 0.5 m, simplified
    assert len(routes[2]) == 2 and np.allclose(routes[2][1], (15.0, 20.0, -10.0))
    assert planned_routes(router_for(None, 3.0), states) == {}

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        layer = RouteLayer(server, 3.0)
        layer.set_plan(plan)
        layer.draw(states)
        assert set(layer.nodes) == {1, 2}
        assert server.scene.get_handle_by_name("/plan_routes/1") is not None
        segs = np.asarray(layer.nodes[1].points)  # scene frame: x east, y north
        assert np.allclose(segs[0, 0, :2], (5.0, -5.0)) and len(segs) == len(bent) - 1
        layer.draw(states[1:])
        assert set(layer.nodes) == {2} and server.scene.get_handle_by_name("/plan_routes/1") is None
    finally:
        server.stop()


def test_drawn_routes_go_round_only_the_zones_a_vehicles_altitudes_reach() -> None:
    """With a zone band (a floor or ceiling) the station draws what guidance flies
    (policy/zone_bands.py): over a zone that ends below the vehicle, straight; round it when the
    vehicle's altitudes reach it; and the fence still counts."""
    from groundstation.target_check import bands_for

    plan = FleetPlan("f", 7, 0, FENCE, (Zone(SQUARE, "depot", ceiling_alt_m=30.0),))
    router = router_for(plan, 3.0)
    bands = bands_for(plan, 3.0, router)
    assert bands is not None and bands_for(base_plan(), 3.0, router_for(base_plan(), 3.0)) is None
    high = state(1, (-5.0, 5.0), (15.0, 5.0), alt_m=50.0)  # 50 m over a zone up to 30 m
    low = state(2, (-5.0, 5.0), (15.0, 5.0), alt_m=10.0)
    routes = planned_routes(router, [high, low], bands)
    assert len(routes[1]) == 2 and np.allclose(routes[1][1], (15.0, 5.0, -50.0))  # straight
    assert len(routes[2]) >= 4  # round the zone
    np.testing.assert_allclose(routes[2], planned_routes(router, [low])[2])
    # without the bands every zone counts at every altitude: the high one goes round too
    assert len(planned_routes(router, [high])[1]) >= 4


def test_the_command_log_lists_plan_versions_with_who_pushed_them() -> None:
    log = CommandLog()
    log.mark_own_plan(9, "alice", "zone 2 ('pond') added (4 corners)")
    log.on_plan(8, 2, "fence of 4 vertices, 1 keep-out zone", 1_000_000_000)
    log.on_plan(9, 1, "fence of 4 vertices, 2 keep-out zones", 2_000_000_000)
    newest, older = log.plan_changes()
    assert newest.own and newest.operator == "alice" and not older.own
    text = command_log_html([], 3_000_000_000, plans=log.plan_changes())
    assert "this station (alice): plan v9: zone 2 (&#x27;pond&#x27;) added (4 corners)" in text
    assert "station 2: plan v8 (fence of 4 vertices, 1 keep-out zone)" in text
    assert text.index('data-plan="9"') < text.index('data-plan="8"')  # newest first


def fenced(corners, draft=None, vehicles=()) -> pe.Draft:
    d = draft or pe.draft_of(base_plan())
    for n, e in corners:
        d = pe.add_corner(d, n, e)
    return pe.close_fence(d, vehicles)


BIG = ((-150, -150), (-150, 150), (150, 150), (150, -150))


def test_a_fence_is_drawn_where_there_was_none_and_replaces_one_keeping_its_band() -> None:
    plan = FleetPlan("f", 3, 0, None, (Zone(SQUARE, "depot"),), (RallyPoint(20, 20, 0, "home"),))
    d = fenced(BIG, pe.draft_of(plan))
    assert d.geometry.fence == Fence(BIG) and d.corners_ne_m == ()
    d = pe.set_fence_band(d, 2.0, 50.0)
    d = fenced(((-50, -50), (-50, 60), (60, 60), (60, -50)), d)
    assert d.geometry.fence == Fence(((-50, -50), (-50, 60), (60, 60), (60, -50)), 2.0, 50.0)
    assert d.describe_edits().split("; ") == [
        "fence drawn (4 corners)",
        "fence floor 2 m, ceiling 50 m",
        "fence replaced (4 corners)",
    ]
    assert [z.name for z in d.geometry.keep_out] == ["depot"]  # the zones stay


@pytest.mark.parametrize(
    ("corners", "reason"),
    [
        ([(-50, -50), (-50, 50)], "a fence needs at least 3 corners; 2 clicked"),
        (
            [(-50, -50), (50, 50), (-50, 50), (50, -50)],
            "the fence is not a valid polygon: Self-intersection",
        ),
        ([(-50, -50), (50, 50), (0, 0.01)], "the fence has an area of .* degenerate"),
        ([(-50, -50), (-50, 50), (50, 50)], r"home \(30.0, -30.0\) m is outside the fence"),
        (
            [(-30, -60), (-30, 60), (60, 60), (60, -60)],
            r"rally point 'pad' \(-40.0, -40.0\) m is outside the fence",
        ),
        (
            [(-60, -60), (-60, 0), (60, 0), (60, -60)],
            r"vehicle 4's position \(N 50.0, E 50.0 m\) would be outside the fence",
        ),
        (
            [(-60, -60), (-60, 60), (60, 60), (60, -60)],
            r"vehicle 3's target \(N -80.0, E 80.0 m\) would be outside the fence",
        ),
    ],
)
def test_a_bad_fence_is_refused_with_its_reason_and_the_draft_is_kept(corners, reason) -> None:
    rally = (RallyPoint(30, -30, 0, "home"), RallyPoint(-40, -40, 0, "pad"))
    d = pe.draft_of(FleetPlan("f", 7, 0, FENCE, (Zone(SQUARE, "depot"),), rally))
    vehicles = vehicle_points([state(4, (50, 50)), state(3, (-5, -5), (-80, 80))])
    for n, e in corners:
        d = pe.add_corner(d, n, e)
    with pytest.raises(pe.EditRefused, match=reason):
        pe.close_fence(d, vehicles)
    assert len(d.corners_ne_m) == len(corners) and d.geometry.fence == FENCE


def test_a_fence_corner_moves_and_goes_as_a_zone_corner_does_numbered_zero() -> None:
    d = fenced(((-50, -50), (-50, 50), (0, 70), (50, 50), (50, -50)))
    d = pe.move_corner(d, pe.FENCE_NO, 3, 0, 80)
    assert d.geometry.fence.vertices_ne_m[2] == (0, 80)
    assert (d.geometry.fence.floor_alt_m, d.geometry.fence.ceiling_alt_m) == (2.0, 80.0)  # kept
    d = pe.delete_corner(d, pe.FENCE_NO, 3)
    assert d.geometry.fence.vertices_ne_m == ((-50, -50), (-50, 50), (50, 50), (50, -50))
    assert d.describe_edits().split("; ")[1:] == [
        "fence corner 3 moved to N 0, E 80",
        "fence corner 3 deleted",
    ]
    vehicles = vehicle_points([state(3, (-5, -5), (40, 40), alt_m=5.0), state(4, (-40, 40))])
    with pytest.raises(pe.EditRefused, match="fence is not a valid polygon: Self-intersection"):
        pe.move_corner(d, pe.FENCE_NO, 2, 60, -40)  # across the opposite edge: a bow tie
    with pytest.raises(pe.EditRefused, match=r"vehicle 3's target \(N 40.0, E 40.0 m\) would be"):
        pe.move_corner(d, pe.FENCE_NO, 3, 30, 30, vehicles)
    with pytest.raises(pe.EditRefused, match="vehicle 4's position .* outside the fence"):
        pe.delete_corner(d, pe.FENCE_NO, 2, vehicles)
    with pytest.raises(pe.EditRefused, match=r"fence has no corner 5 \(corners 1 to 4\)"):
        pe.move_corner(d, pe.FENCE_NO, 5, 0, 0)
    three = pe.delete_corner(d, pe.FENCE_NO, 4)
    with pytest.raises(pe.EditRefused, match="fence has 3 corners, the fewest a fence can have"):
        pe.delete_corner(three, pe.FENCE_NO, 1)
    # A keep-out zone wholly outside the fence is a note, as for files (check_geometry).
    out = pe.move_corner(d, 1, 1, 60, 60)
    out = pe.move_corner(out, 1, 2, 60, 70)
    out = pe.move_corner(out, 1, 3, 70, 70)
    out = pe.move_corner(out, 1, 4, 70, 60)
    assert out.geometry.notes == ("keep-out zone 'depot' lies wholly outside the fence",)
    # A vehicle already outside the fence blocks no edit that keeps it out, only one that
    # puts it out anew.
    outside = vehicle_points([state(6, (90, 0))])
    assert pe.move_corner(d, pe.FENCE_NO, 1, -55, -55, outside).geometry.fence is not None
    with pytest.raises(pe.EditRefused, match="vehicle 6's position"):
        pe.checked(d.geometry, outside)


def test_the_fence_is_deleted_and_a_missing_fence_is_named() -> None:
    d = pe.delete_fence(pe.draft_of(base_plan()))
    assert d.geometry.fence is None and d.edits == ("fence deleted",)
    assert [z.name for z in d.geometry.keep_out] == ["depot"]
    for step in (
        lambda: pe.delete_fence(d),
        lambda: pe.move_corner(d, pe.FENCE_NO, 1, 0, 0),
        lambda: pe.delete_corner(d, pe.FENCE_NO, 1),
    ):
        with pytest.raises(pe.EditRefused, match="the plan has no fence"):
            step()
    with pytest.raises(pe.EditRefused, match="zone 0 does not exist"):
        pe.delete_zone(d, pe.FENCE_NO)  # the fence goes with delete_fence only


def test_the_draft_summary_numbers_the_fence_and_zone_corners_as_the_view_does() -> None:
    d = fenced(((-50, -50), (-50, 50), (0, 70), (50, 50), (50, -50)), pe.draft_of(None))
    d = drawn([(30, 30), (30, 40), (40, 40)], draft=d)
    text = draft_html(d)
    assert "on no plan, 2 edit(s) not pushed" in text
    assert "zone 0: the fence, 5 corners (0.1 to 0.5)<br>" in text  # no band: none shown
    assert "zone 1: pond, 3 corners (1.1 to 1.3)" in text
    text = draft_html(pe.add_corner(pe.set_fence_band(d, None, 60.0), 1, 1))
    assert "zone 0: the fence, 5 corners (0.1 to 0.5) (ceiling 60 m)" in text
    assert "drawing a zone or fence: 1 corner(s)" in text


def with_points() -> pe.Draft:
    """base_plan with home and two rally points (home second in the plan's list: numbers skip it)."""
    rally = (RallyPoint(-40, -40, 0, "pad"), RallyPoint(30, -30, 4.0, "home"), RallyPoint(50, 0))
    return pe.draft_of(FleetPlan("f", 7, 0, FENCE, (Zone(SQUARE, "depot"),), rally))


def test_home_is_set_where_there_was_none_and_moved_keeping_its_altitude() -> None:
    d = pe.set_home(pe.draft_of(base_plan()), 20, 30.004)
    assert d.geometry.rally == (RallyPoint(20, 30, 0.0, "home"),)
    d = pe.set_home(d, 25, 35, 6.0)
    d = pe.set_home(d, -20, -30)
    assert d.geometry.rally == (RallyPoint(-20, -30, 6.0, "home"),)
    moved = pe.set_home(with_points(), 60, 60)
    assert [r.name for r in moved.geometry.rally] == ["pad", "home", ""]  # in its place
    assert moved.geometry.rally[1] == RallyPoint(60, 60, 4.0, "home")
    assert d.describe_edits().split("; ") == [
        "home set at N 20, E 30",
        "home moved to N 25, E 35, 6 m up",
        "home moved to N -20, E -30, 6 m up",
    ]


@pytest.mark.parametrize(
    ("step", "reason"),
    [
        (lambda d: pe.set_home(d, 5, 5), r"keep-out zone 'depot' covers home \(5.0, 5.0\) m"),
        (lambda d: pe.set_home(d, 150, 0), r"home \(150.0, 0.0\) m is outside the fence"),
        (lambda d: pe.set_home(d, float("nan"), 0), r"home \(N nan, E 0\) must be finite"),
        (lambda d: pe.set_home(d, 0, 20, float("inf")), "rally point 'home' needs finite metres"),
        (
            lambda d: pe.add_rally(d, 5, 5, name="pond"),
            r"keep-out zone 'depot' covers rally point 'pond' \(5.0, 5.0\) m",
        ),
        (lambda d: pe.add_rally(d, 5, 5), r"keep-out zone 'depot' covers a rally point \(5.0,"),
        (lambda d: pe.add_rally(d, 0, 150), r"a rally point \(0.0, 150.0\) m is outside the fence"),
        (lambda d: pe.add_rally(d, 0, 20, name=" home"), "'home' names the fleet's home"),
        (lambda d: pe.add_rally(d, 0, 20, name="x" * 65), "name must be printable text of at"),
        (lambda d: pe.add_rally(d, 0, 1e7), r"rally point \(N 0, E 10000000.0\) must be finite"),
        (
            lambda d: pe.move_rally(d, 1, 120, 0),
            r"rally point 'pad' \(120.0, 0.0\) m is outside the fence",
        ),
        (lambda d: pe.move_rally(d, 2, 9, 9), r"'depot' covers a rally point \(9.0, 9.0\) m"),
        (lambda d: pe.move_rally(d, 3, 0, 20), r"rally point 3 does not exist \(rally points 1 to"),
        (lambda d: pe.delete_rally(d, 0), r"rally point 0 does not exist \(rally points 1 to 2\)"),
    ],
)
def test_home_and_rally_points_are_refused_as_a_file_is_with_the_reason(step, reason) -> None:
    d = with_points()
    with pytest.raises(pe.EditRefused, match=reason):
        step(d)
    assert d.geometry.rally == with_points().geometry.rally and not d.edits


def test_a_rally_point_under_a_zone_with_a_floor_is_refused_for_its_pads_or_the_zone() -> None:
    """Below the floor the point itself is no file error (check_geometry), but the pads under
    the zone are: a vehicle comes down through it, and guidance keeps every zone closed."""
    high = Zone(((20, 20), (20, 40), (40, 40), (40, 20)), "wires", floor_alt_m=5.0)
    d = pe.draft_of(FleetPlan("f", 7, 0, FENCE, (high,)))
    with pytest.raises(pe.EditRefused, match=r"^a rally point: landing pad 1 \(N 20.0, E 20.0 m\) "
                       "is inside keep-out zone 'wires'$"):  # fmt: skip
        pe.add_rally(d, 30, 30, 2.0)
    with pytest.raises(pe.EditRefused, match="keep-out zone 'wires' covers a rally point"):
        pe.add_rally(d, 30, 30, 6.0)
    with pytest.raises(pe.EditRefused, match="keep-out zone 'wires' covers home"):
        pe.set_home(d, 30, 30, 5.0)


def test_every_landing_pad_of_a_rally_point_is_checked_and_the_draft_kept() -> None:
    """The 5 x 5 pads 5 m apart around a point keep the 3.8 m clearance from the depot (N and E
    0..10) and stay inside the fence (N and E -100..100); one that does not refuses the point,
    named with the pad, and the draft is kept."""
    d = pe.draft_of(base_plan())
    assert pe.add_rally(d, 23.9, 5, name="north").geometry.rally == (
        RallyPoint(23.9, 5, 0.0, "north"),
    )  # its southern pads at N 13.9: 3.9 m off the depot
    for step, reason in (
        (lambda: pe.add_rally(d, 23, 5, name="north"),
         r"^rally point 'north': landing pad 2 \(N 13.0, E 0.0 m\) is 3.0 m from keep-out zone "
         r"'depot', nearer than the 3.8 m clearance the vehicles' filter keeps from it at a 0.5 m "
         r"position sigma: a vehicle sent to that pad could not arrive$"),
        (lambda: pe.add_rally(d, 20, 5, name="north"),
         r"^rally point 'north': landing pad 2 \(N 10.0, E 0.0 m\) is inside keep-out zone "
         r"'depot'$"),
        (lambda: pe.set_home(d, 0, -92), r"^home: landing pad 1 \(N -10.0, E -102.0 m\) is "
         r"outside the fence$"),
        (lambda: pe.move_rally(pe.add_rally(d, 40, 40), 1, 40, 88),
         r"^a rally point: landing pad 5 \(N 30.0, E 98.0 m\) is 2.0 m from the fence"),
    ):  # fmt: skip
        with pytest.raises(pe.EditRefused, match=reason):
            step()
    assert d.geometry.rally == () and not d.edits


def test_rally_points_are_added_moved_and_deleted_by_number_home_not_counted() -> None:
    d = pe.add_rally(with_points(), 60, -60, name="field")
    assert [r.name for r in d.geometry.rally] == ["pad", "home", "", "field"]
    d = pe.move_rally(d, 2, 55, 5)  # the unnamed one, its altitude kept
    assert d.geometry.rally[2] == RallyPoint(55, 5, 0.0, "")
    d = pe.move_rally(d, 1, -45, -45, 3.0)
    assert d.geometry.rally[0] == RallyPoint(-45, -45, 3.0, "pad")
    d = pe.delete_rally(d, 1)
    assert [r.name for r in d.geometry.rally] == ["home", "", "field"]
    d = pe.delete_rally(d, 2)
    assert d.describe_edits().split("; ") == [
        "rally point 3 ('field') added at N 60, E -60",
        "rally point 2 moved to N 55, E 5",
        "rally point 1 ('pad') moved to N -45, E -45, 3 m up",
        "rally point 1 ('pad') deleted",
        "rally point 2 ('field') deleted",
    ]
    d = pe.delete_rally(d, 1)
    assert [r.name for r in d.geometry.rally] == ["home"]
    for step in (lambda: pe.delete_rally(d, 1), lambda: pe.move_rally(d, 1, 0, 20)):
        with pytest.raises(pe.EditRefused, match="the plan has no rally point"):
            step()


def test_a_plan_holds_at_most_max_rally_points_home_included() -> None:
    d = pe.set_home(pe.draft_of(base_plan()), 30, 20)  # its pads 10 m and more off the depot
    for k in range(MAX_RALLY_POINTS - 1):
        d = pe.add_rally(d, 30 + k, 30)
    with pytest.raises(pe.EditRefused, match=f"a plan holds at most {MAX_RALLY_POINTS} rally"):
        pe.add_rally(d, -20, 40)
    moved = pe.delete_rally(d, 1)
    assert len(pe.set_home(pe.add_rally(moved, -20, 40), 31, 21).geometry.rally) == MAX_RALLY_POINTS


def test_the_draft_summary_and_the_shared_scene_number_rally_points_home_apart() -> None:
    text = draft_html(with_points())
    assert "no home" not in text
    assert "<br>home at N 30, E -30, 4 m up<br>rally 1: pad at N -40, E -40<br>rally 2 at" in text
    assert "<br>no home" in draft_html(pe.draft_of(base_plan()))
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        scene = FleetScene(server, SceneConfig())
        scene.update_plan(with_points().geometry.plan("f", 7, 0))
        labels = [server.scene.get_handle_by_name(f"/plan/rally/{k}/label").text for k in range(3)]
        assert labels == ["pad", "home", "rally 2"]  # the number the editor moves it by
    finally:
        server.stop()
