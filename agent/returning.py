"""The coordinated return: each vehicle comes home on its own altitude layer, and vehicles whose
landing spots are close land one at a time. Pure, for N vehicles as arrays; the flight core
calls it on entering RETURNING and on every arrival while returning.

Every vehicle derives its part alone, from its id and the fleet it sees, so nothing has to
reach it over a bad link, and a failsafe's return (low battery) is coordinated too:

    layer altitude  = return_base_alt_m + ((vehicle_id - 1) mod return_layers) * return_layer_m

A returning vehicle first climbs or descends to its layer where it is, then flies level to its
landing spot, so that paths which cross in plan cross `return_layer_m` apart in height (ids
that share a layer, `return_layers` apart, are kept apart by the guidance's avoidance as
always). Over its spot it comes down only when no airborne vehicle it knows of is within
`land_radius_m` of the spot and lower (or level with it and of a lower id): the lowest layer
lands first, one at a time. What it knows of the others is its own core's rows and the
neighbour table (agent/neighbours.py: dead-reckoned, forgotten past its drop_s), so a neighbour
unheard for longer than that no longer holds it back.

The landing spot is the vehicle's home (where it took off) or, with rally points in the fleet
plan, the nearest of its home and the rally points; at a rally point each vehicle has its own
pad on a square grid around the point, `rally_pad_spacing_m` apart, pad (id - 1) mod rally_pads.

On by default (layers 4 m apart from 10 m, 8 layers, landing one at a time within 8 m): a
return to all no longer sends every vehicle home at its own altitude. A layer above the fleet
plan's ceiling or the failsafe's maximum altitude is flown at that limit (less the arrival
tolerance) instead, where avoidance keeps the vehicles on it apart. `covey agent`,
`covey fleet-sim` and `covey demo --no-coordinated-return` (`return_layer_m` and
`land_radius_m` 0) fly the return of old.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from comms.plan import RALLY_PAD_SPACING_M, RALLY_PADS, PadLayout

NONE, CLIMB, CRUISE, WAIT = 0, 1, 2, 3
"""Return phases: not returning on layers, to the layer, level to the spot, over it waiting."""
AIRBORNE_ALT_M = 0.3
"""A vehicle higher than this above the origin counts as airborne when deciding who lands."""
LEVEL_M = 0.5
"""Two vehicles within this height of each other are level: the lower id lands first."""


@dataclass(frozen=True)
class ReturnConfig:
    """How returning vehicles share the sky (defaults: on, layers 4 m apart from 10 m, landing
    one at a time within 8 m; both 0 is the return of old)."""

    return_layer_m: float = 4.0
    """Height between return layers (above the 3 m separation); 0: each vehicle returns at its
    own altitude."""
    return_layers: int = 8
    """How many layers; vehicle id v flies layer (v - 1) mod return_layers."""
    return_base_alt_m: float = 10.0
    """Altitude of the lowest layer above the fleet origin."""
    land_radius_m: float = 8.0
    """Vehicles whose landing spots are within this horizontal distance land one at a time,
    lowest first; 0: each lands as it arrives."""
    rally_pad_spacing_m: float = RALLY_PAD_SPACING_M
    """Distance between landing pads around a rally point (comms/plan.py `PadLayout`: the layout
    the station checks against the zones and the fence, `GcsConfig.landing_pads`)."""
    rally_pads: int = RALLY_PADS
    """Pads around a rally point (a square grid); vehicle id v takes pad (v - 1) mod rally_pads."""

    def __post_init__(self) -> None:
        for name in ("return_layer_m", "land_radius_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")
        for name in ("return_base_alt_m", "rally_pad_spacing_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive, got {v}")
        if not (1 <= self.return_layers <= 1000 and 1 <= self.rally_pads <= 10_000):
            raise ValueError("return_layers must be within 1..1000 and pads within 1..10000")

    @property
    def coordinated(self) -> bool:
        """Layers or a landing order (or both) are on."""
        return self.return_layer_m > 0 or self.land_radius_m > 0

    def layer_alt_m(self, vehicle_id: int) -> float:
        return (
            self.return_base_alt_m + ((vehicle_id - 1) % self.return_layers) * self.return_layer_m
        )

    def pad_ne_m(self, vehicle_id: int) -> tuple[float, float]:
        """Offset of the vehicle's pad from a rally point (a centred square grid)."""
        return self.pad_layout.offset_ne_m((vehicle_id - 1) % self.rally_pads + 1)

    @property
    def pad_layout(self) -> PadLayout:
        """The pads around a rally point (what the station checks a plan's points against)."""
        return PadLayout(self.rally_pads, self.rally_pad_spacing_m)


class Returns:
    """The return phase, landing spot and layer of N vehicles (the flight core's rows)."""

    def __init__(self, cfg: ReturnConfig, vehicle_ids: np.ndarray) -> None:
        self.cfg = cfg
        self.ids = np.asarray(vehicle_ids, np.int64)
        n = len(self.ids)
        self.phase = np.zeros(n, np.int8)
        self.spot_ne_m = np.full((n, 2), np.nan)
        self.layer_alt_m = np.array([cfg.layer_alt_m(int(v)) for v in self.ids])

    def enter(
        self,
        i: int,
        pos_m: np.ndarray,
        home_m: np.ndarray,
        rally_ne_m: list[tuple[float, float]],
        min_alt_m: float,
        alt_tol_m: float,
        max_alt_m: float = math.inf,
    ) -> np.ndarray:
        """Vehicle i starts returning from `pos_m`: its landing spot, phase, and first goal.
        `max_alt_m`: the highest it may fly (the plan's ceiling, the failsafe's maximum): a
        layer above it is flown just under it."""
        home_ne = home_m[:2] if not np.isnan(home_m[0]) else np.zeros(2)
        spot = np.asarray(home_ne, float)
        if rally_ne_m:
            pts = np.array(rally_ne_m, float)
            d = np.hypot(*(pts - pos_m[:2]).T)
            k = int(np.argmin(d))
            if d[k] < float(np.hypot(*(spot - pos_m[:2]))):
                spot = pts[k] + np.array(self.cfg.pad_ne_m(int(self.ids[i])))
        self.spot_ne_m[i] = spot
        if self.cfg.return_layer_m <= 0:  # no layers: level at the current altitude, as before
            self.phase[i] = CRUISE
            return np.array([spot[0], spot[1], min(pos_m[2], -min_alt_m)])
        alt = max(min(float(self.layer_alt_m[i]), max_alt_m - alt_tol_m), min_alt_m)
        if abs(-pos_m[2] - alt) > alt_tol_m:
            self.phase[i] = CLIMB
            return np.array([pos_m[0], pos_m[1], -alt])
        self.phase[i] = CRUISE
        return np.array([spot[0], spot[1], -alt])

    def arrivals(
        self,
        returning: np.ndarray,
        arrived: np.ndarray,
        pos_m: np.ndarray,
        goal_m: np.ndarray,
        others_pos_m: np.ndarray | None = None,
        others_ids: np.ndarray | None = None,
    ) -> tuple[np.ndarray, list[int]]:
        """Which returning rows' arrivals are real (come down now), and the rows that turned: a
        row at its layer turns to its spot (its goal changes in `goal_m`), a row over its spot
        waits while someone is below it within land_radius_m. `others_*`: vehicles outside
        these rows (neighbours)."""
        out = arrived.copy()
        turned = []
        for i in np.flatnonzero(returning & arrived).tolist():
            if self.phase[i] == CLIMB:
                self.phase[i] = CRUISE
                goal_m[i] = (self.spot_ne_m[i, 0], self.spot_ne_m[i, 1], goal_m[i, 2])
                out[i] = False
                turned.append(i)
            elif self.cfg.land_radius_m > 0 and self.blocker(
                i, pos_m, others_pos_m, others_ids, returning
            ):
                self.phase[i] = WAIT
                out[i] = False
        return out, turned

    def blocker(
        self,
        i: int,
        pos_m: np.ndarray,
        others_pos_m: np.ndarray | None,
        others_ids: np.ndarray | None,
        returning: np.ndarray | None = None,
    ) -> int | None:
        """The id of a vehicle that lands before row i (airborne, lower or level with a lower
        id, and within land_radius_m of row i's spot, or one of these rows `returning` to a
        spot within it: the filter may have pushed it off its way), or None: row i may come
        down."""
        pts, ids = pos_m, self.ids
        if others_pos_m is not None and len(others_pos_m):
            pts = np.concatenate([pts, np.asarray(others_pos_m, float).reshape(-1, 3)])
            oid = others_ids if others_ids is not None else np.zeros(len(others_pos_m), np.int64)
            ids = np.concatenate([ids, np.asarray(oid, np.int64)])
        mine = -pos_m[i, 2]
        alt = -pts[:, 2]
        near = np.hypot(*(pts[:, :2] - self.spot_ne_m[i]).T) <= self.cfg.land_radius_m
        if returning is not None:  # rows of this fleet bound for a spot near row i's
            spots = np.hypot(*(self.spot_ne_m - self.spot_ne_m[i]).T) <= self.cfg.land_radius_m
            near[: len(self.ids)] |= np.asarray(returning, bool) & spots
        below = (alt < mine - LEVEL_M) | ((np.abs(alt - mine) <= LEVEL_M) & (ids < ids[i]))
        hit = near & below & (alt > AIRBORNE_ALT_M)
        hit[i] = False
        k = np.flatnonzero(hit)
        return int(ids[k[0]]) if k.size else None
