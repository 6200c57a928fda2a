"""Gotos around keep-out zones as the vehicles fly them: a `covey fleet-sim` host on a real Zenoh
router gets a fleet plan with a concave zone between its vehicles and their goals; every goto
becomes waypoints around it (agent/guidance.py, policy/routes.py), the filter keeps its edges
(policy/zone_lines.py), and every vehicle arrives without its true position ever coming within
1.5 m (half the separation) of the zone. The same gotos without the plan cut straight through."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from agent.hosts import Fleet
from agent.shell_config import FleetSimConfig
from comms.mesh import Mesh
from comms.plan import FleetPlan, Zone
from comms.schema import AckResult, Command, CommandKind
from comms.session import embedded_router, free_tcp_port

FLEET = "zoneflight"
ALT_M = 5.0
ENTRY_M = 1.5
"""An entry: a true position within this distance of the zone (policy.zone_lines.ZONE_ENTRY_SHARE
of the 3 m separation)."""
# a C north of the vehicles (at n 0..10, e 0..10), its pocket (n 20..40, e 0..15) facing them
ZONE = (
    (20.0, -10.0),
    (20.0, 0.0),
    (40.0, 0.0),
    (40.0, 15.0),
    (20.0, 15.0),
    (20.0, 25.0),
    (45.0, 25.0),
    (45.0, -10.0),
)


def _cmd(kind: CommandKind, *params: float, nonce: int) -> Command:
    return Command(kind, nonce, 0, params=(*params, 0.0, 0.0, 0.0)[:3])


def _fly(with_plan: bool, max_s: float = 150.0):
    port = free_tcp_port()
    cfg = FleetSimConfig(vehicles=3, mesh=embedded_router(port, fleet=FLEET), spacing_m=10.0)
    clock = [0.0]
    zone = shapely.Polygon(ZONE)
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0])
        if with_plan:
            fleet.plan.push(FleetPlan(FLEET, 1, 0, keep_out=(Zone(ZONE, "yard"),)))
            assert fleet.core.guidance.router is not None
        for i in range(3):
            ack = fleet.handle_command(i, _cmd(CommandKind.TAKEOFF, ALT_M, nonce=10 + i))
            assert ack.result is AckResult.ACCEPTED, ack.reason
        while clock[0] < 20.0 and not np.all(-fleet.sim.pos_m[:, 2] > ALT_M - 0.4):
            clock[0] += 0.1
            fleet.tick(clock[0])
        start = fleet.sim.pos_m[:, :2].copy()
        # each vehicle to the far side of the zone: the straight line runs into its pocket
        goals = start + np.array([55.0, 5.0])
        for i in range(3):
            g = goals[i]
            ack = fleet.handle_command(
                i, _cmd(CommandKind.GOTO_LOCAL, g[0], g[1], -ALT_M, nonce=20 + i)
            )
            assert ack.result is AckResult.ACCEPTED, ack.reason
        closest, waypoints, t0 = np.inf, set(), clock[0]
        arrived = np.zeros(3, bool)
        while clock[0] - t0 < max_s and not arrived.all():
            clock[0] += 0.1
            fleet.tick(clock[0])
            pos = fleet.sim.pos_m[:, :2]
            closest = min(closest, float(shapely.distance(shapely.points(pos), zone).min()))
            arrived |= np.hypot(*(pos - goals).T) <= 1.0
            way = fleet.core.guidance.waypoint_m
            waypoints |= {tuple(np.round(w, 1)) for w in way if np.isfinite(w).all()}
        return arrived, closest, clock[0] - t0, waypoints, start, goals


@pytest.mark.e2e
def test_fleet_sim_gotos_go_around_a_concave_zone_and_arrive():
    arrived, closest, took_s, waypoints, start, goals = _fly(True)
    assert arrived.all(), arrived
    assert closest >= ENTRY_M, closest
    assert len(waypoints) >= 2  # corners were flown to, then the goals
    print(
        f"[zone flight] 3 vehicles: closest {closest:.2f} m to the zone, all arrived in {took_s:.0f} s"
    )


@pytest.mark.e2e
def test_without_the_plan_the_same_gotos_cut_through_the_zone():
    _, closest, _, waypoints, _, _ = _fly(False, max_s=60.0)
    assert closest == 0.0 and not waypoints
