"""Each vehicle's planned route around the fleet plan's keep-out zones, drawn in the 3D scene.

The routes are groundstation/state_routes.py `planned_routes` (computed by the station from each
vehicle's reported position and goal, with the agents' planner; Foxglove draws the same ones),
for vehicles flying a goto, a return or a mission item with a goal while the plan has keep-out
zones or a fence; a line per vehicle at `/plan_routes/<id>`, in the goto colour, from the
vehicle through each waypoint to its goal.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
import viser

from comms.plan import FleetPlan
from comms.schema import Mode, VehicleState
from groundstation.palette import mode_rgb
from groundstation.scene import route_segments
from groundstation.state_routes import planned_routes
from groundstation.target_check import bands_for, router_for

if TYPE_CHECKING:  # shapely and scipy load only with a plan
    from policy.routes import Router
    from policy.zone_bands import ZoneBands

ROUTE_PATH = "/plan_routes"


class RouteLayer:
    """The routes in the shared scene, redrawn from the latest states."""

    def __init__(self, server: viser.ViserServer, separation_m: float) -> None:
        self.server, self.separation_m = server, separation_m
        self.router: Router | None = None
        self.bands: ZoneBands | None = None
        self.nodes: dict[int, viser.LineSegmentsHandle] = {}
        """Vehicle id -> its drawn route (read by tests)."""
        self.drawn: dict[int, np.ndarray] = {}
        """Vehicle id -> the NED points drawn (read by tests)."""

    def set_plan(self, plan: FleetPlan | None) -> None:
        self.router = router_for(plan, self.separation_m)
        self.bands = bands_for(plan, self.separation_m, self.router)

    def draw(self, states: Iterable[VehicleState]) -> None:
        routes = planned_routes(self.router, states, self.bands)
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
