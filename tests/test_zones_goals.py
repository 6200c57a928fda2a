"""A goal next to a keep-out zone: the filter keeps 1.8 m + sigma_k x the position 1-sigma from
every zone, so a goal nearer than that is flown to the nearest point outside it when that point
is within the arrival radius, and refused at once, naming the zone and the distances, when it is
not (policy.routes `Router.check_goal`, agent/flight_core.py `_clear_goal`); the same where the
autopilot guides itself (relay: the core builds the router guidance would), and for mission
waypoints at upload and at start. And the sigma of an autopilot that reports no accuracy
(`--assumed-pos-sigma-m`, agent/autopilots.py)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from agent.autopilots import Autopilots
from agent.backends.base import Telemetry
from agent.failsafe import FailsafeConfig
from agent.flight_core import CoreConfig, FlightCore, Observed
from agent.modes import Mode
from comms.plan import FleetPlan, Zone
from comms.schema import AckResult, Command, CommandKind, Mission, MissionItem, MissionItemKind
from policy.routes import Router
from policy.safety import SIGMA_K

SQUARE = ((-8.0, -8.0), (-8.0, 8.0), (8.0, 8.0), (8.0, -8.0))
REACH_M = 1.8
"""The filter's zone radius at the default 3 m separation (policy.routes RouteConfig.reach_m)."""


def _dist(pt) -> float:
    return float(shapely.Polygon(SQUARE).distance(shapely.Point(*pt)))


@pytest.mark.parametrize(
    ("off_m", "sigma_m", "moved"),
    [(2.0, 0.0, False), (3.1, 0.5, True), (2.0, 0.5, True), (5.0, 0.5, False)],
)
def test_a_goal_inside_the_clearance_moves_to_its_edge(off_m, sigma_m, moved) -> None:
    router = Router([np.array(SQUARE)])
    goal = np.array([8.0 + off_m, 1.0])
    c = router.check_goal(goal, SIGMA_K * sigma_m)
    clearance = REACH_M + SIGMA_K * sigma_m
    assert c.clearance_m == pytest.approx(clearance)
    assert c.distance_m == pytest.approx(off_m) and c.zone == 0
    if not moved:
        assert np.array_equal(c.goal_m, goal) and c.shift_m == 0.0 and c.problem(0.0) == ""
        return
    assert clearance <= _dist(c.goal_m) <= clearance + 0.1  # just outside the clearance
    assert c.shift_m == pytest.approx(clearance - off_m, abs=0.1)
    assert (c.problem(1.0) == "") == (c.shift_m <= 1.0)


def test_the_core_flies_a_near_goal_to_the_clearance_or_refuses_it_naming_the_zone() -> None:
    core = FlightCore(CoreConfig(failsafe=FailsafeConfig(require_gcs=False)), 1, now_s=0.0)
    core.set_plan(FleetPlan("f", 1, 0, keep_out=(Zone(SQUARE, "pad"),)))
    here = np.array([30.0, 0.0, -10.0])
    sigma = 0.5
    obs = Observed(
        here[None], np.zeros((1, 3)), np.ones(1, bool), np.ones(1, bool), np.full(1, 90.0),
        np.ones(1, bool), np.full(1, sigma),
    )  # fmt: skip
    core.observe(0.0, obs, gcs_alive=True)
    core.mode[0] = int(Mode.HOLDING)  # flying
    clearance = REACH_M + SIGMA_K * sigma

    def goto(n_m: float):
        return core.command(0, Command(CommandKind.GOTO_LOCAL, 1, 0, (n_m, 0.0, -10.0)), here)

    near = goto(8.0 + clearance - 0.7)  # the edge of the clearance within the 1 m arrival radius
    assert near.result is AckResult.ACCEPTED, near.reason
    assert near.reason.startswith("goal moved 0.") and "'pad'" in near.reason
    assert clearance <= _dist(core.goal_m[0, :2]) <= clearance + 0.1
    far = goto(8.0 + clearance - 1.3)
    assert far.result is AckResult.REJECTED
    assert "keep-out zone 'pad'" in far.reason and f"{clearance:.1f} m" in far.reason
    assert "1 m arrival radius" in far.reason
    clear = goto(8.0 + clearance + 1.0)
    assert clear.result is AckResult.ACCEPTED and clear.reason == ""
    assert core.goal_m[0, 0] == 8.0 + clearance + 1.0


class _Autopilot:
    """An autopilot backend that reports `h_acc_m` (0: no accuracy), as the MAVSDK and relay
    backends do through pos_sigma_of."""

    capabilities = frozenset()

    def __init__(self, h_acc_m: float) -> None:
        self.h_acc_m = h_acc_m

    def telemetry(self) -> Telemetry:
        return Telemetry(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, True, True, 80.0,
                         pos_sigma_m=self.h_acc_m)  # fmt: skip


def test_an_autopilot_without_accuracy_is_assumed_standard_gnss_from_the_flag() -> None:
    from agent import agent_cli

    p = agent_cli.parser()
    default = agent_cli.config_from_args(p.parse_args(["--id", "3"]), p)
    none = agent_cli.config_from_args(p.parse_args(["--id", "3", "--assumed-pos-sigma-m", "0"]), p)
    assert default.assumed_pos_sigma_m == 0.5 and none.assumed_pos_sigma_m == 0.0
    for cfg in (default, none):
        rows = Autopilots([_Autopilot(0.0), _Autopilot(1.2)], cfg.assumed_pos_sigma_m)  # type: ignore[list-item]
        obs = rows.read()
        assert obs is not None and obs.pos_sigma_m is not None
        np.testing.assert_array_equal(obs.pos_sigma_m, [cfg.assumed_pos_sigma_m, 1.2])
    with pytest.raises(ValueError, match="assumed_pos_sigma_m must be finite and >= 0"):
        agent_cli.config_from_args(p.parse_args(["--id", "3", "--assumed-pos-sigma-m", "-1"]), p)


# -- where the autopilot guides itself (relay: the PX4 module's filter keeps the zones) -----------
SIGMA_M = 0.5
CLEARANCE_M = REACH_M + SIGMA_K * SIGMA_M
"""What the filter keeps from the square's edges at SIGMA_M (3.8 m)."""
PLAN = FleetPlan("f", 1, 0, keep_out=(Zone(SQUARE, "pad"),))
HERE = np.array([30.0, 0.0, -10.0])


def _core(velocity_mode: bool, sigma_m: float = SIGMA_M) -> FlightCore:
    """A core of one vehicle flying (holding) at HERE with position 1-sigma `sigma_m` and PLAN;
    velocity_mode False: the relay's core, which has no guidance."""
    core = FlightCore(
        CoreConfig(failsafe=FailsafeConfig(require_gcs=False)), 1, now_s=0.0,
        velocity_mode=velocity_mode,
    )  # fmt: skip
    core.set_plan(PLAN)
    _observe(core, sigma_m)
    core.mode[0] = int(Mode.HOLDING)
    return core


def _observe(core: FlightCore, sigma_m: float) -> None:
    obs = Observed(
        HERE[None], np.zeros((1, 3)), np.ones(1, bool), np.ones(1, bool), np.full(1, 90.0),
        np.ones(1, bool), np.full(1, sigma_m),
    )  # fmt: skip
    core.observe(0.0, obs, gcs_alive=True)


def _goto(core: FlightCore, n_m: float, nonce: int = 1):
    return core.command(0, Command(CommandKind.GOTO_LOCAL, nonce, 0, (n_m, 1.0, -10.0)), HERE)


def test_a_relay_core_refuses_moves_and_accepts_goals_as_a_guided_one_does() -> None:
    relay, guided = _core(velocity_mode=False), _core(velocity_mode=True)
    assert relay.guidance is None and relay.router is not None
    near = _goto(relay, 8.0 + 0.3)  # 0.3 m off the edge: 3.5 m to the clearance
    assert near.result is AckResult.REJECTED and not near.actions
    assert near.reason.startswith("target: ") and "keep-out zone 'pad'" in near.reason
    assert f"{CLEARANCE_M:.1f} m" in near.reason and "1 m arrival radius" in near.reason
    edge = _goto(relay, 8.0 + 1.9 + SIGMA_K * SIGMA_M - 0.4)  # 0.3 m inside the clearance
    assert edge.result is AckResult.ACCEPTED, edge.reason
    assert edge.reason.startswith("goal moved 0.")
    assert f"to {CLEARANCE_M:.1f} m from keep-out zone 'pad'" in edge.reason
    (action,) = edge.actions  # the autopilot is sent the moved goal, not the one asked
    assert action.target_ned_m is not None
    assert CLEARANCE_M <= _dist(action.target_ned_m[:2]) <= CLEARANCE_M + 0.1
    np.testing.assert_array_equal(action.target_ned_m, relay.goal_m[0])
    assert action.target_ned_m[2] == -10.0
    far = _goto(relay, 8.0 + CLEARANCE_M + 1.0)
    assert far.result is AckResult.ACCEPTED and far.reason == ""
    assert far.actions[0].target_ned_m == (8.0 + CLEARANCE_M + 1.0, 1.0, -10.0)
    # one rule: the guided core (its guidance's router) answers each goal alike
    for k, n_m in enumerate((8.3, 8.0 + 1.9 + SIGMA_K * SIGMA_M - 0.4, 8.0 + CLEARANCE_M + 1.0)):
        a, b = _goto(relay, n_m, 10 + k), _goto(guided, n_m, 10 + k)
        assert (a.result, a.reason) == (b.result, b.reason)
        if a.result is AckResult.ACCEPTED:
            np.testing.assert_array_equal(relay.goal_m, guided.goal_m)


def test_a_relay_core_builds_its_router_once_per_plan_and_drops_it_with_the_zones() -> None:
    core = _core(velocity_mode=False)
    router = core.router
    core.set_plan(FleetPlan("f", 2, 0, keep_out=(Zone(SQUARE, "pad"),)))  # same zones
    assert core.router is router
    core.set_plan(FleetPlan("f", 3, 0, keep_out=(Zone(SQUARE[::-1], "pad"),)))
    assert core.router is not None and core.router is not router
    core.set_plan(None)
    assert core.router is None
    assert _goto(core, 8.3).result is AckResult.ACCEPTED  # no zones: no rule (and no zone)


def test_a_relay_core_keeps_the_clearance_of_the_separation_its_autopilot_reports() -> None:
    """The relay reads the PX4 module's CVY_SEP_M (agent/backends/relay.py); the goal rule then
    keeps the clearance of that separation, not of the configured one, and says so once."""
    core = _core(velocity_mode=False)
    n_m = 8.0 + CLEARANCE_M + 0.5  # clear at 3 m: 4.3 m from the edge
    assert _goto(core, n_m, 1).reason == ""
    obs = Observed(
        HERE[None], np.zeros((1, 3)), np.ones(1, bool), np.ones(1, bool), np.full(1, 90.0),
        np.ones(1, bool), np.full(1, SIGMA_M), np.full(1, 5.0),
    )  # fmt: skip
    core.observe(0.1, obs, gcs_alive=True)
    assert core.safety_cfg.radius_m == 5.0 and core.onboard_separation_m == 5.0
    (note,) = [n for n in core.drain_notes() if "CVY_SEP_M" in n.text]
    assert "keeps 5 m (CVY_SEP_M), not the configured --separation-m 3 m" in note.text
    wide = REACH_M * 5.0 / 3.0 + SIGMA_K * SIGMA_M  # the zone clearance at 5 m: 5.0 m
    moved = _goto(core, n_m, 2)
    assert moved.result is AckResult.ACCEPTED and moved.reason.startswith("goal moved")
    assert f"to {wide:.1f} m from keep-out zone 'pad'" in moved.reason
    core.observe(0.2, obs, gcs_alive=True)  # the same again: no second note
    assert not [n for n in core.drain_notes() if "CVY_SEP_M" in n.text]


def _upload(core: FlightCore, *n_m: float):
    items = tuple(MissionItem(MissionItemKind.WAYPOINT, x=n, y=1.0, alt_m=10.0) for n in n_m)
    return core.load_mission(0, Mission(5, 1, items, mission_id=4))


def _start(core: FlightCore):
    return core.command(0, Command(CommandKind.MISSION_START, 9, 0, ()), HERE)


@pytest.mark.parametrize("velocity_mode", [False, True])
def test_a_mission_waypoint_within_the_clearance_is_moved_or_refused(velocity_mode) -> None:
    core = _core(velocity_mode)
    moved_n_m = 8.0 + CLEARANCE_M - 0.4
    refused = _upload(core, 20.0, 8.0 + 0.3)
    assert refused.result is AckResult.REJECTED and core.missions[0] is None
    assert refused.reason.startswith("item 2 (waypoint): target: ")
    assert "keep-out zone 'pad'" in refused.reason
    loaded = _upload(core, 20.0, moved_n_m)
    assert loaded.result is AckResult.ACCEPTED, loaded.reason
    assert loaded.reason.startswith("2 items; item 2: goal moved 0.")
    assert f"to {CLEARANCE_M:.1f} m from keep-out zone 'pad'" in loaded.reason
    run = core.missions[0]
    assert run is not None and run.asked[1].target_ned_m == (moved_n_m, 1.0, -10.0)
    flown = run.items[1].target_ned_m
    assert flown is not None and CLEARANCE_M <= _dist(flown[:2]) <= CLEARANCE_M + 0.1
    assert run.items[0] == run.asked[0]  # a waypoint clear of the zone is flown as asked
    started = _start(core)
    assert started.result is AckResult.ACCEPTED and "item 2: goal moved 0." in started.reason
    assert core.mode_of(0) is Mode.MISSION
    if not velocity_mode:  # the autopilot flies item 1 as asked
        assert started.actions[0].target_ned_m == (20.0, 1.0, -10.0)


def test_a_mission_start_checks_its_items_again_at_the_sigma_of_now() -> None:
    """Uploaded on a 0 sigma, a waypoint 2 m off the zone is clear (1.8 m); at 0.5 m it is 1.8 m
    inside the 3.8 m clearance, beyond the arrival radius: the start is refused naming it."""
    core = _core(velocity_mode=False, sigma_m=0.0)
    loaded = _upload(core, 20.0, 8.0 + 2.0)
    assert loaded.result is AckResult.ACCEPTED and loaded.reason == "2 items"
    _observe(core, SIGMA_M)
    refused = _start(core)
    assert refused.result is AckResult.REJECTED and not refused.actions
    assert refused.reason.startswith("item 2 (waypoint): target: the goal is 2.0 m from")
    assert core.mode_of(0) is Mode.HOLDING
    _observe(core, 0.0)
    assert _start(core).result is AckResult.ACCEPTED
