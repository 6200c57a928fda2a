"""Each vehicle's planned route around the fleet plan's keep-out zones, from what it reports: the
one route computation that the station's 3D view (groundstation/plan_routes.py) and Foxglove
(recording/foxglove_channels.py) draw.

The routes come from each vehicle's reported position and goal (`VehicleState.pos_ned_m` /
`goal_ned_m`) and the plan, with the planner the agents use (groundstation/target_check.py
`router_for`: policy/routes.py `zones_for`, the zones inflated for the fleet's separation and the
filter's default margin). So the state carries no route (no wire change, no extra bytes per
tick), and what is drawn is the route a vehicle with that separation flies from where it is now:
the agent re-plans from its position every tick (`Router.next_waypoint`), so the route from the
reported position is the one it is on, widened as its agent widens it for the position 1-sigma
it reports (sigma_k x it more from the zones: policy/routes.py `Router.widened`, the filter's
default sigma_k). A vehicle configured with another separation, margin or sigma_k keeps a
slightly different distance from the zones.

No viser, no Foxglove: the recorder's worker imports it too.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol

import numpy as np

from comms.schema import Mode, StateFlag
from policy.safety import SIGMA_K

ROUTED_MODES = (Mode.GOTO, Mode.RETURNING, Mode.MISSION)
"""Modes whose goal the agents route around the zones (agent/flight_core.py: the guided rows
that do not hold; a mission's goal is its current item)."""
MAX_ROUTES = 64
"""Vehicles whose routes are computed at most (the lowest ids): a route costs a planner query."""


class ReportedState(Protocol):
    """What a route is made from: a VehicleState, or the recorder's StateRow of one."""

    @property
    def vehicle_id(self) -> int: ...
    @property
    def mode(self) -> Mode: ...
    @property
    def flags(self) -> int: ...
    @property
    def pos_ned_m(self) -> tuple[float, float, float]: ...
    @property
    def goal_ned_m(self) -> tuple[float, float, float]: ...
    @property
    def pos_sigma_m(self) -> float: ...


def is_routed(s: ReportedState) -> bool:
    """Whether the agents route this vehicle's goal around the zones (a goto, a return or a
    mission item, with a goal)."""
    return s.mode in ROUTED_MODES and bool(s.flags & StateFlag.HAS_GOAL)


def planned_routes(router, states: Iterable[ReportedState], bands=None) -> dict[int, np.ndarray]:
    """Vehicle id -> (M+1, 3) NED points of its route (its position first, then each waypoint,
    the goal last, at the goal's altitude), for routed vehicles with a goal (`is_routed`), the
    MAX_ROUTES lowest ids; none where the planner refuses the goal or finds no way (the
    vehicle's own refusal is in its ack). `router`: `router_for`'s (None: no routes); `bands`:
    `bands_for`'s (policy.zone_bands.ZoneBands, None: every zone at every altitude): each
    vehicle's route then goes round the zones its altitudes reach, as its guidance groups it."""
    out: dict[int, np.ndarray] = {}
    if router is None:
        return out
    for s in sorted(states, key=lambda s: s.vehicle_id):
        if len(out) >= MAX_ROUTES:
            break
        if not is_routed(s):
            continue
        pos, goal = np.asarray(s.pos_ned_m, float), np.asarray(s.goal_ned_m, float)
        if not (np.isfinite(pos).all() and np.isfinite(goal).all()):
            continue
        # the routes each agent flies keep its filter's padding for its position 1-sigma more
        sigma = float(s.pos_sigma_m) if np.isfinite(s.pos_sigma_m) else 0.0
        own = router
        if bands is not None:  # the zones this vehicle's altitudes reach (one group of one)
            _, ((_, _, own),) = bands.groups(pos[None], goal[None], np.array([SIGMA_K * sigma]))
            if own is None:
                continue  # no zone in its way: it flies straight at its goal
        route = own.plan(pos[:2], goal[:2], SIGMA_K * sigma)
        if route.reason or not np.isfinite(route.length_m):
            continue
        way = np.asarray(route.waypoints_m, float).reshape(-1, 2)
        pts = np.empty((len(way) + 1, 3))
        pts[0] = pos
        pts[1:, :2] = way
        pts[1:, 2] = goal[2]
        out[s.vehicle_id] = pts
    return out
