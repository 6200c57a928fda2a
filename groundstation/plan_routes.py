"""Each vehicle's planned route around the fleet plan's keep-out zones, drawn in the 3D scene.

The station computes the routes itself, from what each vehicle reports (its position and its
goal, `VehicleState.pos_ned_m` / `goal_ned_m`) and the plan it follows, with the planner and the
rule the agents use (policy/routes.py `zones_for`: the zones inflated for the fleet's separation
and the filter's default margin). So the state carries no route (no wire change, no extra bytes
per tick), and what is drawn is the route a vehicle with the station's separation flies from
where it is now: the agent re-plans from its position every tick (`Router.next_waypoint`), so
the route drawn from the reported position is the one it is on. A vehicle configured with
another separation or margin keeps a slightly different distance from the zones than drawn.

Drawn for vehicles flying a goto, a return or a mission item (`ROUTED_MODES`) with a goal while
the plan has keep-out zones or a fence; a line per vehicle at `/plan_routes/<id>`, in the goto
colour, from the vehicle through each waypoint to its goal.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
import viser

from comms.plan import FleetPlan
from comms.schema import Mode, StateFlag, VehicleState
from groundstation.palette import mode_rgb
from groundstation.scene import route_segments
from groundstation.target_check import router_for
from policy.safety import SIGMA_K

if TYPE_CHECKING:  # shapely and scipy load only with a plan
    from policy.routes import Router

ROUTED_MODES = (Mode.GOTO, Mode.RETURNING, Mode.MISSION)
"""Modes whose goal the agents route around the zones (agent/flight_core.py: the guided rows
that do not hold; a mission's goal is its current item)."""
MAX_ROUTES = 64
"""Vehicles whose routes are drawn at most (the lowest ids): a route costs a planner query."""
ROUTE_PATH = "/plan_routes"


def planned_routes(router, states: Iterable[VehicleState]) -> dict[int, np.ndarray]:
    """Vehicle id -> (M+1, 3) NED points of its route (its position first, then each waypoint,
    the goal last, at the goal's altitude), for routed vehicles with a goal; none where the
    planner refuses the goal or finds no way (the vehicle's own refusal is in its ack). Each
    route keeps sigma_k x the vehicle's reported position 1-sigma more from the zones, as its
    agent's (policy/routes.py `Router.widened`; the filter's default sigma_k)."""
    out: dict[int, np.ndarray] = {}
    if router is None:
        return out
    for s in sorted(states, key=lambda s: s.vehicle_id):
        if len(out) >= MAX_ROUTES:
            break
        if s.mode not in ROUTED_MODES or not s.flags & StateFlag.HAS_GOAL:
            continue
        pos, goal = np.asarray(s.pos_ned_m, float), np.asarray(s.goal_ned_m, float)
        if not (np.isfinite(pos).all() and np.isfinite(goal).all()):
            continue
        # the routes each agent flies keep its filter's padding for its position 1-sigma more
        sigma = float(s.pos_sigma_m) if np.isfinite(s.pos_sigma_m) else 0.0
        route = router.plan(pos[:2], goal[:2], SIGMA_K * sigma)
        if route.reason or not np.isfinite(route.length_m):
            continue
        way = np.asarray(route.waypoints_m, float).reshape(-1, 2)
        pts = np.empty((len(way) + 1, 3))
        pts[0] = pos
        pts[1:, :2] = way
        pts[1:, 2] = goal[2]
        out[s.vehicle_id] = pts
    return out


class RouteLayer:
    """The routes in the shared scene, redrawn from the latest states."""

    def __init__(self, server: viser.ViserServer, separation_m: float) -> None:
        self.server, self.separation_m = server, separation_m
        self.router: Router | None = None
        self.nodes: dict[int, viser.LineSegmentsHandle] = {}
        """Vehicle id -> its drawn route (read by tests)."""
        self.drawn: dict[int, np.ndarray] = {}
        """Vehicle id -> the NED points drawn (read by tests)."""

    def set_plan(self, plan: FleetPlan | None) -> None:
        self.router = router_for(plan, self.separation_m)

    def draw(self, states: Iterable[VehicleState]) -> None:
        routes = planned_routes(self.router, states)
        for vid in [v for v in self.nodes if v not in routes]:
            self.nodes.pop(vid).remove()
        colour = np.array(mode_rgb(Mode.GOTO), np.uint8)
        for vid, points in routes.items():
            old = self.drawn.get(vid)
            if vid in self.nodes and old is not None and np.array_equal(old, points):
                continue  # unchanged (a vehicle holding its place): nothing sent
            self.nodes[vid] = self.server.scene.add_line_segments(
                f"{ROUTE_PATH}/{vid}",
                route_segments(points),
                colour,
                thickness=2.5,
                thickness_units="screen",
            )
        self.drawn = routes
