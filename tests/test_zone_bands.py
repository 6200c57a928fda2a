"""Keep-out zones with a floor or ceiling in guidance (policy/zone_bands.py): a row counts a zone
only where its altitudes reach the zone's band, a row over a zone is kept over it until it is
clear, and a guided core's goal rule reads the zones at the target's altitude."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
import shapely

from agent.failsafe import FailsafeConfig
from agent.flight_core import CoreConfig, FlightCore, Observed
from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews
from agent.modes import Mode
from comms.plan import FleetPlan, Zone
from comms.schema import AckResult, Command, CommandKind
from policy.zone_bands import ZONE_VERTICAL_CLEARANCE_M

SQUARE_NE = ((5.0, -5.0), (5.0, 5.0), (15.0, 5.0), (15.0, -5.0))
SQUARE = np.array(SQUARE_NE)
PAD_NE = tuple((n, e + 30.0) for n, e in SQUARE_NE)
"""'pad': the square 30 m east."""
LOW = [(None, 30.0)]
"""SQUARE's band: from the ground to 30 m."""


def _views(k: int, n_nbrs: int = 0, rng=None) -> NeighbourViews:
    if rng is None:
        none = np.zeros((k, 0))
        return NeighbourViews(
            np.zeros((k, 0, 3)), np.zeros((k, 0, 3)), none, none.astype(bool), none.astype(bool)
        )
    return NeighbourViews(
        rng.uniform(-20, 20, (k, n_nbrs, 3)),
        rng.uniform(-1, 1, (k, n_nbrs, 3)),
        rng.uniform(-3, 3, (k, n_nbrs)),
        rng.random((k, n_nbrs)) < 0.7,
        rng.random((k, n_nbrs)) < 0.2,
        rng.integers(1, 50, (k, n_nbrs)),
        np.arange(100, 100 + k),
        rng.uniform(0, 1, (k, n_nbrs)),
        rng.random((k, n_nbrs)) < 0.8,
        rng.uniform(0, 1, k),
        rng.random((k, n_nbrs)) < 0.1,
    )


def _step(g: BatchGuidance, pos, target, views=None, now_s=None):
    k = len(pos)
    return g.step(
        now_s,
        np.arange(k),
        pos,
        np.zeros((k, 3)),
        np.zeros(k),
        target,
        np.zeros(k, bool),
        _views(k) if views is None else views,
    )


def test_a_row_above_a_zones_ceiling_flies_over_it_and_a_row_below_goes_round() -> None:
    g = BatchGuidance(GuidanceConfig(), 2)
    g.set_zones([SQUARE], None, LOW)
    seen = []  # (rows, zones) of each filter call
    real = g._filter

    def spy(pos_m, vel_m_s, pref_m_s, views, zones):
        seen.append((len(pos_m), zones))
        return real(pos_m, vel_m_s, pref_m_s, views, zones)

    g._filter = spy  # type: ignore[method-assign]
    pos = np.array([[-5.0, 0.0, -50.0], [-5.0, 0.0, -10.0]])  # 50 m and 10 m
    target = np.array([[25.0, 0.0, -50.0], [25.0, 0.0, -10.0]])
    out = _step(g, pos, target)
    assert out.waypoint_m is not None
    np.testing.assert_array_equal(out.waypoint_m[0], target[0, :2])  # straight over
    assert np.hypot(*(out.waypoint_m[1] - target[1, :2])) > 1.0  # round the zone
    assert abs(out.waypoint_m[1, 1]) > 5.0  # a corner beside the square
    assert sorted((n, z is None) for n, z in seen) == [(1, False), (1, True)]
    assert any(z is g.zones for _, z in seen)


def test_without_bands_and_with_bands_every_row_reaches_guidance_is_unchanged() -> None:
    """No bands, all (None, None), or bands every row's span reaches: the same output, exactly,
    as guidance without bands, on random rows and neighbours."""
    rng = np.random.default_rng(4)
    other = SQUARE + np.array([-30.0, 10.0])
    fence = np.array([[-60.0, -60.0], [-60.0, 60.0], [60.0, 60.0], [60.0, -60.0]])
    k = 7
    ref = BatchGuidance(GuidanceConfig(), k)
    ref.set_zones([SQUARE, other], fence)
    for bands in ([(None, None), (None, None)], [(-500.0, 500.0), (None, 900.0)]):
        g = BatchGuidance(GuidanceConfig(), k, ref.policy)
        g.set_zones([SQUARE, other], fence, bands)
        assert (g.bands is None) == (bands[0][0] is None)
        for _ in range(5):
            pos = np.column_stack([rng.uniform(-40, 40, (k, 2)), rng.uniform(-60, -5, k)])
            target = np.column_stack([rng.uniform(-40, 40, (k, 2)), rng.uniform(-60, -5, k)])
            views = _views(k, 4, rng)
            a, b = _step(ref, pos, target, views), _step(g, pos, target, views)
            for f in fields(a):
                np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name))


def test_a_row_over_a_zone_stays_above_its_ceiling_until_clear_then_comes_down() -> None:
    g = BatchGuidance(GuidanceConfig(), 1)
    g.set_zones([SQUARE], None, LOW)
    assert g.bands is not None
    reach_m = g.bands.reach_m
    floor_m = 30.0 + ZONE_VERTICAL_CLEARANCE_M
    pos = np.array([[10.0, 0.0, -40.0]])  # over the middle of the square at 40 m
    target = np.array([[30.0, 0.0, -10.0]])  # 10 m, beyond the zone
    square = shapely.Polygon(SQUARE)
    dt_s, lowest_near_m, was_held = 0.2, np.inf, False
    for t in range(300):
        out = _step(g, pos, target, now_s=t * dt_s)
        pos = pos + out.vel_ned_m_s * dt_s
        alt_m = -pos[0, 2]
        if square.distance(shapely.Point(pos[0, :2])) < reach_m:
            lowest_near_m = min(lowest_near_m, alt_m)
            was_held |= alt_m < floor_m + 0.5
    assert was_held  # it came down to the guard, not held where it started
    assert lowest_near_m >= floor_m - 1e-6
    assert -pos[0, 2] < 12.0 and pos[0, 0] > 25.0  # clear, it came down to its target


def _guided(zone: Zone, velocity_mode: bool = True) -> FlightCore:
    """A core flying at 10 m beside `zone`, with 'pad' 30 m east of SQUARE; velocity_mode
    False: the relay's (no guidance)."""
    core = FlightCore(
        CoreConfig(failsafe=FailsafeConfig(require_gcs=False)), 1, now_s=0.0,
        velocity_mode=velocity_mode,
    )  # fmt: skip
    core.set_plan(FleetPlan("f", 1, 0, keep_out=(zone, Zone(PAD_NE, "pad"))))
    here = np.array([-10.0, 0.0, -10.0])
    obs = Observed(
        here[None], np.zeros((1, 3)), np.ones(1, bool), np.ones(1, bool), np.full(1, 90.0),
        np.ones(1, bool), np.zeros(1),
    )  # fmt: skip
    core.observe(0.0, obs, gcs_alive=True)
    core.mode[0] = int(Mode.HOLDING)
    return core


def _goto(core: FlightCore, ne_m, nonce: int):
    cmd = Command(CommandKind.GOTO_LOCAL, nonce, 0, (ne_m[0], ne_m[1], -10.0))
    return core.command(0, cmd, np.array([-10.0, 0.0, -10.0]))


NEAR = (15.5, 0.0)
"""0.5 m off the square's north edge: inside the filter's 1.8 m clearance (sigma 0), whose edge
lies 1.3 m away, beyond the 1 m arrival radius: the goal rule refuses it where the zone counts."""


def test_a_guided_core_flies_a_goal_under_an_overhang_and_refuses_it_beside_a_closed_zone() -> None:
    overhang = _guided(Zone(SQUARE_NE, "roof", floor_alt_m=30.0))
    beside = _goto(overhang, NEAR, 1)
    assert beside.result is AckResult.ACCEPTED and beside.reason == "", beside.reason
    under = _goto(overhang, (10.0, 0.0), 2)  # inside the polygon, under its floor
    assert under.result is AckResult.ACCEPTED, under.reason
    closed = _goto(_guided(Zone(SQUARE_NE, "roof")), NEAR, 1)
    assert closed.result is AckResult.REJECTED and "'roof'" in closed.reason
    assert "arrival radius" in closed.reason
    # the zones at the goal's altitude are named in the router's order: 'pad', not 'roof'
    near_pad = _goto(overhang, (NEAR[0], 30.0), 3)
    assert near_pad.result is AckResult.REJECTED and "'pad'" in near_pad.reason


@pytest.mark.parametrize("floor_alt_m", [30.0, None])
@pytest.mark.parametrize(
    "goal_ne_m", [NEAR, (10.0, 0.0), (NEAR[0], 30.0), (17.0, 0.0), (40.0, 40.0)]
)
def test_the_stations_pre_check_says_what_a_guided_core_would(floor_alt_m, goal_ne_m) -> None:
    """groundstation/target_check.py takes the zones at the target's altitude, as a guided
    vehicle's goal rule does: the same verdict, moved target and words, overhang or not."""
    from groundstation.target_check import TargetCheck

    roof = Zone(SQUARE_NE, "roof", floor_alt_m=floor_alt_m)
    plan = FleetPlan("f", 1, 0, keep_out=(roof, Zone(PAD_NE, "pad")))
    target = np.array([goal_ne_m[0], goal_ne_m[1], -10.0])
    want_target, want_moved, want_refused = _guided(roof).check_target(0, target.copy())
    got = TargetCheck(plan, 3.0).check(target, 0.0)
    assert (got.refused, got.moved) == (want_refused, want_moved)
    np.testing.assert_allclose(got.target_ned_m, want_target, atol=1e-9)


def test_a_relay_core_keeps_every_zone_closed_at_every_altitude() -> None:
    core = _guided(Zone(SQUARE_NE, "roof", floor_alt_m=30.0), velocity_mode=False)
    assert core.guidance is None
    refused = _goto(core, NEAR, 1)
    assert refused.result is AckResult.REJECTED and "'roof'" in refused.reason


def test_neighbour_views_take_is_row_slicing() -> None:
    rng = np.random.default_rng(1)
    views = _views(5, 3, rng)
    rows = np.array([3, 0, 3])
    cut = views.take(rows)
    for f in fields(views):
        np.testing.assert_array_equal(getattr(cut, f.name), getattr(views, f.name)[rows])
    bare = _views(4).take(np.array([1]))
    assert bare.ids is None and bare.pos_m.shape == (1, 0, 3)


def test_each_subset_of_zones_is_built_once_and_the_cache_is_bounded() -> None:
    from policy.zone_bands import MAX_BAND_SUBSETS

    g = BatchGuidance(GuidanceConfig(), 1)
    squares = [SQUARE + [0.0, 20.0 * j] for j in range(5)]
    g.set_zones(squares, None, [(None, 30.0)] * 5)
    bands = g.bands
    assert bands is not None
    assert bands.subset(tuple(range(5))) == (g.zones, g.router)  # the full set: the one built
    assert bands.subset((1, 3)) is bands.subset((1, 3))
    assert bands.subset(()) == (None, None)  # no zone, no fence
    for mask in range(1, 2**5 - 1):  # every proper subset but the empty one: 30 > the bound
        bands.subset(tuple(j for j in range(5) if mask >> j & 1))
    assert len(bands._subsets) == MAX_BAND_SUBSETS
    key, router = bands.at_alt(50.0)  # above every ceiling (+3 m): none counts
    assert key == () and router is None
