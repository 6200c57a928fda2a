"""The goal rule, worded: where a vehicle flies a goto whose goal lies nearer a keep-out zone (or
the fence) than its separation filter keeps, or why it refuses it. One rule for the flight core
(agent/flight_core.py `_clear_goal`, every goto and mission waypoint) and the ground station's
pre-checks (groundstation/target_check.py: formations, home and rally points), so that the
station refuses or moves a target in the words the vehicle's ack would use.

The geometry is policy/routes.py `Router.check_goal`: the clearance is the filter's distance
from a zone plus sigma_k x the position 1-sigma (1.8 m + 4 x 0.5 m = 3.8 m at 3 m separation);
a goal nearer than that is moved to the nearest point outside it when that point is within the
arrival radius, else refused. Pure: no shapely here (the router brings it), so the defaults below
load with the agent's config.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # shapely and scipy load only with zones
    from policy.routes import Router

ARRIVE_RADIUS_M = 1.0
"""A goto counts as arrived within this horizontal distance (agent/guidance.py
`GuidanceConfig.arrive_radius_m`'s default): the farthest a goal is moved rather than refused."""
ASSUMED_POS_SIGMA_M = 0.5
"""The position 1-sigma (m, per horizontal axis) taken for a vehicle whose autopilot reports no
horizontal accuracy: standard GNSS (agent/shell_config.py `ShellConfig.assumed_pos_sigma_m`'s
default). The station checks home and rally points at it (groundstation/target_check.py)."""


@dataclass(frozen=True)
class GoalVerdict:
    """A goal under the rule: where to fly it, what was moved, why it is refused."""

    goal_ne_m: np.ndarray
    """(2,) where to fly: the goal, or the nearest point outside the clearance."""
    moved: str
    """What was moved, as the vehicle's ack says it ("" when nothing was)."""
    refused: str
    """Why the goal is refused ("" when it is not); `goal_ne_m` is then the goal asked for."""
    distance_m: float
    """From the goal to the nearest keep-out zone or the fence (inf: none)."""
    clearance_m: float
    """What the filter keeps from them at this sigma."""
    zone: str
    """The nearest zone as the words name it ("keep-out zone 'pad'", "the fence")."""


def zone_words(zone: int, names: Sequence[str] = ()) -> str:
    """How a refusal names polygon `zone` of a router (`GoalCheck.zone`: -1 the fence)."""
    if zone < 0:
        return "the fence"
    name = names[zone] if zone < len(names) else ""
    return f"keep-out zone {name!r}" if name else "a keep-out zone"


def goal_rule(
    router: Router,
    goal_ne_m,
    pos_sigma_m: float,
    sigma_k: float,
    arrive_radius_m: float = ARRIVE_RADIUS_M,
    zone_names: Sequence[str] = (),
) -> GoalVerdict:
    """The goal rule for a vehicle with position 1-sigma `pos_sigma_m` whose filter pads zones by
    `sigma_k` of it (policy.safety.SafetyConfig.sigma_k), `router` being the plan's router for
    its filter's separation (policy/routes.py `zones_for`); `zone_names`: the plan's keep-out
    zones' names, in the router's order."""
    goal = np.asarray(goal_ne_m, dtype=np.float64).reshape(2)
    check = router.check_goal(goal, sigma_k * float(pos_sigma_m))
    what = zone_words(check.zone, zone_names)
    out = GoalVerdict(goal, "", "", check.distance_m, check.clearance_m, what)
    problem = check.problem(arrive_radius_m, what)
    if problem:
        return GoalVerdict(goal, "", problem, check.distance_m, check.clearance_m, what)
    if check.shift_m == 0.0:
        return out
    moved = (
        f"goal moved {check.shift_m:.1f} m, to {check.clearance_m:.1f} m from {what} (the "
        f"filter's clearance at a {pos_sigma_m:g} m position sigma)"
    )
    return GoalVerdict(check.goal_m, moved, "", check.distance_m, check.clearance_m, what)
