"""Would this vehicle take this target, and where would it fly: the station's copy of the check
a vehicle's flight core makes on a goto (agent/flight_core.py `check_target`), asked before
anything is sent.

Two parts, both the vehicles' own code: comms/plan.py `plan_refusal` (inside a keep-out zone,
outside the fence, above the ceiling, below the floor), then the goal rule (policy/goal_rule.py:
a goal nearer a zone or the fence than the filter keeps, 1.8 m + sigma_k x the vehicle's
position 1-sigma at 3 m separation, is moved to the nearest point outside that if within the
1 m arrival radius, else refused). The router is the one the agents build (policy/routes.py
`zones_for`, `router_for` here: the station's separation, the filter's default margin and
sigma_k), built once per plan and separation (`TargetCheck`); each vehicle is checked at the
position sigma its states report (`VehicleState.pos_sigma_m`: the one its core uses, the assumed
0.5 m where its autopilot reports none).

Home and rally points (`landing_problems`) are checked against the same clearance at
ASSUMED_POS_SIGMA_M: a plan is not made for one vehicle, and a vehicle on plain GNSS cannot
arrive nearer a zone than that. So is every landing pad a return puts around them (comms/plan.py
`PadLayout`, by default the 5 x 5 grid 5 m apart that agent/returning.py flies): inside the
fence, in no keep-out zone at any altitude (the vehicle comes down through all of them, and
guidance keeps every zone closed), and as far from both as the point itself. What the station cannot know, a vehicle configured with another
separation, arrival radius or margin than the station's, its own ack still says.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from comms.plan import (
    HOME,
    FleetPlan,
    PadLayout,
    RallyPoint,
    plan_refusal,
    point_in_polygon,
)
from policy.goal_rule import ARRIVE_RADIUS_M, ASSUMED_POS_SIGMA_M, goal_rule

if TYPE_CHECKING:  # shapely and scipy load only with a plan
    from comms.plan_io import PlanGeometry
    from policy.routes import Router
    from policy.zone_bands import ZoneBands


def router_for(plan: FleetPlan | None, separation_m: float) -> Router | None:
    """The route planner the agents use for `plan` (policy.routes.Router), None without zones
    or a fence: the one router construction of the station (routes drawn, targets checked)."""
    if plan is None or (not plan.keep_out and plan.fence is None):
        return None
    from policy.routes import zones_for  # shapely and scipy: only with a plan
    from policy.safety import SafetyConfig

    fence = plan.fence.vertices_ne_m if plan.fence is not None else None
    _, router = zones_for(SafetyConfig(radius_m=separation_m), plan.keep_out_polygons_ne_m(), fence)
    return router


def bands_for(
    plan: FleetPlan | None, separation_m: float, router: Router | None
) -> ZoneBands | None:
    """The plan's zones with their floors and ceilings as guidance reads them
    (policy/zone_bands.py), over `router` (`router_for`'s, the full set), or None when no zone
    has a floor or ceiling (or there is no router): the one construction of the station's
    (targets checked, routes drawn)."""
    if router is None or plan is None:
        return None
    from policy.safety import SafetyConfig
    from policy.zone_bands import ZoneBands

    return ZoneBands.of(
        SafetyConfig(radius_m=separation_m),
        plan.keep_out_polygons_ne_m(),
        None if plan.fence is None else plan.fence.vertices_ne_m,
        [(z.floor_alt_m, z.ceiling_alt_m) for z in plan.keep_out],
        (None, router),  # only routers are asked of the full set here (`goal_router`, `groups`)
    )


@dataclass(frozen=True)
class TargetVerdict:
    """What a vehicle would do with a goto target."""

    target_ned_m: tuple[float, float, float]
    """Where it would fly: the target, or the target moved out of a zone's clearance."""
    moved: str
    """What was moved, in the words of the vehicle's ack ("" when nothing was)."""
    refused: str
    """Why it would refuse the goto, in the words of its ack ("" when it would not)."""


class TargetCheck:
    """The flight core's target check for one plan and the fleet's separation: the router is
    built once (0.01-1 s by the plan's size), then each target costs a distance query."""

    def __init__(
        self,
        plan: FleetPlan | None,
        separation_m: float,
        *,
        arrive_radius_m: float = ARRIVE_RADIUS_M,
    ) -> None:
        from policy.safety import SafetyConfig

        self.plan = plan
        self.separation_m = separation_m
        self.sigma_k = SafetyConfig(radius_m=separation_m).sigma_k
        """The filter's sigma factor the agents fly (the default: the station cannot read it)."""
        self.arrive_radius_m = arrive_radius_m
        self.router = router_for(plan, separation_m)
        self.names = [] if plan is None else [z.name for z in plan.keep_out]
        """The plan's keep-out zones' names, as refusals name them."""
        self.bands = bands_for(plan, separation_m, self.router)
        """The zones' floors and ceilings, None when no zone has one: a guided vehicle's goal
        rule takes the zones active at the target's altitude, so the station does too."""

    def check(self, target_ned_m, pos_sigma_m: float) -> TargetVerdict:
        """A goto to `target_ned_m` (NED, m) of a vehicle whose position 1-sigma is
        `pos_sigma_m`: refused as its flight core would (the plan, then the goal rule), or where
        it would fly."""
        n_m, e_m, down_m = (float(c) for c in target_ned_m)
        why = plan_refusal(self.plan, (n_m, e_m), -down_m)
        if why:
            return TargetVerdict((n_m, e_m, down_m), "", f"target {why}")
        router, names = self.router, self.names
        if self.bands is not None:  # the zones active at the target's altitude, as a vehicle's
            router, names = self.bands.goal_router(-down_m, self.names)
        if router is None:
            return TargetVerdict((n_m, e_m, down_m), "", "")
        rule = goal_rule(
            router,
            (n_m, e_m),
            pos_sigma_m,
            self.sigma_k,
            self.arrive_radius_m,
            names,
        )
        if rule.refused:
            return TargetVerdict((n_m, e_m, down_m), "", f"target: {rule.refused}")
        g = rule.goal_ne_m
        return TargetVerdict((float(g[0]), float(g[1]), down_m), rule.moved, "")


def landing_what(r: RallyPoint) -> str:
    """How a refusal names home or a rally point (comms/plan_io.py words them alike)."""
    return "home" if r.name == HOME else f"rally point {r.name!r}" if r.name else "a rally point"


class LandingProblem(NamedTuple):
    """Why a return could not come down at home or a rally point, or on one of its pads."""

    point: RallyPoint
    """Home or the rally point."""
    pad_no: int
    """0: the point itself; else its landing pad's number (comms/plan.py `PadLayout`)."""
    why: str
    """One line, naming the point, the pad and the zone."""


def landing_problems(
    geometry: PlanGeometry,
    separation_m: float,
    pos_sigma_m: float = ASSUMED_POS_SIGMA_M,
    only: Iterable[RallyPoint] | None = None,
    pads: PadLayout = PadLayout(),
) -> list[LandingProblem]:
    """Each home or rally point of `geometry` (of `only`, when given) nearer a keep-out zone or
    the fence than the filter keeps at `pos_sigma_m`, and each of its landing `pads` (as
    agent/returning.py lays them out) that is inside a zone, outside the fence or nearer either
    than that: a vehicle returning there could not arrive. The point
    comes before its pads. A point inside a zone or outside the fence is comms/plan_io.py
    `check_geometry`'s to refuse (a zone with a floor may lie above one)."""
    points = list(geometry.rally if only is None else only)
    if not points:
        return []
    plan = FleetPlan("check", 1, 0, geometry.fence, geometry.keep_out, geometry.rally)
    check = TargetCheck(plan, separation_m)
    router = check.router
    if router is None:
        return []
    out = []
    for r in points:
        what = landing_what(r)
        rule = goal_rule(router, (r.n_m, r.e_m), pos_sigma_m, check.sigma_k, zone_names=check.names)
        inside = router.refusal(np.array([r.n_m, r.e_m]))
        if not inside and rule.distance_m < rule.clearance_m:
            out.append(
                LandingProblem(
                    r,
                    0,
                    f"{what} ({r.n_m:.1f}, {r.e_m:.1f}) m is {rule.distance_m:.1f} m from "
                    f"{rule.zone}, nearer than the {rule.clearance_m:.1f} m the vehicles' filter "
                    f"keeps from it at a {pos_sigma_m:g} m position sigma: a vehicle returning "
                    "there could not arrive",
                )
            )
        for pad_no in range(1, pads.pads + 1):
            dn, de = pads.offset_ne_m(pad_no)
            n_m, e_m = r.n_m + dn, r.e_m + de
            why = _pad_problem(check, n_m, e_m, pos_sigma_m)
            if why:
                where = f"landing pad {pad_no} (N {n_m:.1f}, E {e_m:.1f} m)"
                out.append(LandingProblem(r, pad_no, f"{what}: {where} {why}"))
    return out


def _pad_problem(check: TargetCheck, n_m: float, e_m: float, pos_sigma_m: float) -> str:
    """Why a vehicle could not land on a pad at (n_m, e_m) ("" when it could)."""
    assert check.plan is not None and check.router is not None
    for z in check.plan.keep_out:  # at every altitude: it comes down through them all
        if point_in_polygon(n_m, e_m, z.vertices_ne_m):
            return f"is inside keep-out zone {z.name!r}" if z.name else "is inside a keep-out zone"
    fence = check.plan.fence
    if fence is not None and not point_in_polygon(n_m, e_m, fence.vertices_ne_m):
        return "is outside the fence"
    rule = goal_rule(check.router, (n_m, e_m), pos_sigma_m, check.sigma_k, zone_names=check.names)
    if rule.distance_m >= rule.clearance_m:
        return ""
    return (
        f"is {rule.distance_m:.1f} m from {rule.zone}, nearer than the {rule.clearance_m:.1f} m "
        f"clearance the vehicles' filter keeps from it at a {pos_sigma_m:g} m position sigma: a "
        "vehicle sent to that pad could not arrive"
    )


__all__ = [
    "LandingProblem",
    "TargetCheck",
    "TargetVerdict",
    "landing_problems",
    "landing_what",
    "router_for",
]
