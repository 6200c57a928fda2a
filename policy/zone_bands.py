"""Keep-out zones with a floor or ceiling in guidance: each row flies around the zones its
altitudes reach, and is kept from climbing or descending into one it is over or under.

A zone of the fleet plan (comms/plan.py `Zone`) may start at a floor and end at a ceiling
(altitudes above the origin, up positive; NED down = -alt). Guidance (agent/guidance.py
`BatchGuidance`) reads them per row and tick:
- the row's altitude span is [min(alt now, alt of its target) - ZONE_VERTICAL_CLEARANCE_M,
  max(...) + ZONE_VERTICAL_CLEARANCE_M]; a zone is active for the row when its band overlaps that
  span (a zone without floor and ceiling always is; the fence always counts);
- rows are grouped by their active subset, and each group is routed (policy.routes) and filtered
  (policy.zone_lines) against that subset's zones alone: its (ZoneSet, Router) come from
  policy.routes `zones_for`, built once per subset and kept (`MAX_BAND_SUBSETS`);
- the vertical guard: a row above an active zone's ceiling (below its floor) that is horizontally
  within the filter's zone clearance of it (reach_m + sigma_k x its position 1-sigma, policy.routes
  RouteConfig) has its target altitude held at ceiling + ZONE_VERTICAL_CLEARANCE_M or above
  (floor - ZONE_VERTICAL_CLEARANCE_M or below) until it is horizontally clear; the zone then no
  longer counts for it horizontally (it is on its side), so a vehicle over a zone flies on over
  it and comes down once past it.

The goal rule of a guided flight core (agent/flight_core.py `_clear_goal`) takes the router of
the zones active at the target's altitude (`at_alt`). What stays conservative (every zone closed
at every altitude) is listed in docs/sky.md "Keep-out zones".
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np
import shapely

from policy.routes import RouteConfig, zones_for

ZONE_VERTICAL_CLEARANCE_M = 3.0
"""Vertical clearance kept from a zone's floor and ceiling (m): a zone counts for a row whose
altitude span comes within this of its band, and the vertical guard holds a row this far above a
ceiling (below a floor). At the 3 m separation: one separation."""
MAX_BAND_SUBSETS = 16
"""Active subsets whose (ZoneSet, Router) are kept (least recently used dropped): a fleet flies
at a few altitudes, so a few subsets at a time."""

Band = tuple[float | None, float | None]
"""(floor_alt_m, ceiling_alt_m) of one zone; None: no floor (from the ground) / no ceiling."""


class ZoneBands:
    """Keep-out polygons with their altitude bands, and the zones each row flies against."""

    def __init__(self, safety_cfg, keep_out_m, fence_m, bands_m: Sequence[Band], full) -> None:
        """safety_cfg: the filter's (policy.safety.SafetyConfig); keep_out_m: [(K, 2) north/east
        polygons]; fence_m: (K, 2) or None; bands_m: one Band per polygon; full: the
        (ZoneSet, Router) of every polygon (`zones_for`), the subset of rows that reach all."""
        self.polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in keep_out_m]
        if len(bands_m) != len(self.polys):
            raise ValueError(f"{len(bands_m)} bands for {len(self.polys)} keep-out zones")
        self.safety_cfg = safety_cfg
        self.fence_m = fence_m
        self.floor_alt_m = np.array([-math.inf if f is None else float(f) for f, _ in bands_m])
        self.ceiling_alt_m = np.array([math.inf if c is None else float(c) for _, c in bands_m])
        self.banded = np.isfinite(self.floor_alt_m) | np.isfinite(self.ceiling_alt_m)
        """(Z,) the zone has a floor or a ceiling."""
        self.reach_m = RouteConfig(float(safety_cfg.radius_m), float(safety_cfg.margin)).reach_m
        """The filter's distance from a zone edge (policy.routes RouteConfig.reach_m)."""
        self._shapes = {int(j): shapely.Polygon(self.polys[j]) for j in np.flatnonzero(self.banded)}
        self._full_key = tuple(range(len(self.polys)))
        self._full = full
        self._subsets: OrderedDict = OrderedDict()

    @classmethod
    def of(cls, safety_cfg, keep_out_m, fence_m, bands_m: Sequence[Band] | None, full):
        """The bands of these zones, None where no zone has a floor or a ceiling (bands_m None
        or all (None, None)): guidance then closes every zone at every altitude, as before."""
        if bands_m is None or all(f is None and c is None for f, c in bands_m):
            return None
        return cls(safety_cfg, keep_out_m, fence_m, bands_m, full)

    def subset(self, key: tuple[int, ...]):
        """(ZoneSet, Router) of the polygons `key` (indices, ascending) and the fence: the full
        set's own for every polygon, else built once and kept; (None, None) for no polygon and
        no fence."""
        if key == self._full_key:
            return self._full
        hit = self._subsets.get(key)
        if hit is None:
            hit = zones_for(self.safety_cfg, [self.polys[j] for j in key], self.fence_m)
            self._subsets[key] = hit
            if len(self._subsets) > MAX_BAND_SUBSETS:
                self._subsets.popitem(last=False)
        else:
            self._subsets.move_to_end(key)
        return hit

    def active(self, alt_lo_m, alt_hi_m) -> np.ndarray:
        """(k, Z) whether each zone's band overlaps each row's span [alt_lo_m, alt_hi_m] (k,)
        widened by ZONE_VERTICAL_CLEARANCE_M either side."""
        lo = np.asarray(alt_lo_m, dtype=np.float64)[:, None] - ZONE_VERTICAL_CLEARANCE_M
        hi = np.asarray(alt_hi_m, dtype=np.float64)[:, None] + ZONE_VERTICAL_CLEARANCE_M
        return (hi >= self.floor_alt_m) & (lo <= self.ceiling_alt_m)

    def at_alt(self, alt_m: float):
        """(key, Router) of the zones active at one altitude (a goal's: the goal rule): key the
        polygons' indices, in the router's order; the router None without zones or fence."""
        key = tuple(int(j) for j in np.flatnonzero(self.active([alt_m], [alt_m])[0]))
        return key, self.subset(key)[1]

    def goal_router(self, alt_m: float, names: Sequence[str]):
        """(Router, names) for the goal rule at a target's altitude: `at_alt`'s router and the
        plan's zone `names` of its zones, in its order (the flight core and the station's
        pre-checks both ask this)."""
        key, router = self.at_alt(alt_m)
        return router, [names[j] for j in key] if names else []

    def guard(self, pos_ned_m, target_ned_m, active, pad_m) -> np.ndarray:
        """The vertical guard, in place on target_ned_m: rows above an active (`active` (k, Z))
        banded zone's ceiling (below its floor) and horizontally within reach_m + pad_m (k,) of
        it get their target's altitude held at ceiling + ZONE_VERTICAL_CLEARANCE_M or above
        (floor - it or below). A row held both ways (stacked zones nearer than two clearances)
        keeps its altitude. Returns (k, Z) which zones held which rows."""
        alt_now = -pos_ned_m[:, 2]
        above = alt_now[:, None] > self.ceiling_alt_m
        below = alt_now[:, None] < self.floor_alt_m
        near = np.zeros_like(active)
        for j in np.flatnonzero((active & self.banded & (above | below)).any(axis=0)):
            rows = np.flatnonzero(active[:, j] & (above[:, j] | below[:, j]))
            d = shapely.distance(self._shapes[int(j)], shapely.points(pos_ned_m[rows, :2]))
            near[rows, j] = d < self.reach_m + pad_m[rows]
        if not near.any():
            return near
        c = ZONE_VERTICAL_CLEARANCE_M
        floor_to = np.where(near & above, self.ceiling_alt_m + c, -np.inf).max(axis=1)
        ceil_to = np.where(near & below, self.floor_alt_m - c, np.inf).min(axis=1)
        alt_to = -target_ned_m[:, 2]
        held = np.where(floor_to <= ceil_to, np.clip(alt_to, floor_to, ceil_to), alt_now)
        target_ned_m[:, 2] = -held
        return near

    def groups(self, pos_ned_m, target_ned_m, pad_m):
        """(target, groups) for k rows: the target with the vertical guard applied (a copy),
        and [(row indices, ZoneSet, Router)] per active subset (pad_m (k,): sigma_k x each
        row's position 1-sigma)."""
        target = np.array(target_ned_m, dtype=np.float64)
        alt_now, alt_to = -pos_ned_m[:, 2], -target[:, 2]
        active = self.active(np.minimum(alt_now, alt_to), np.maximum(alt_now, alt_to))
        held = self.guard(pos_ned_m, target, active, pad_m)
        if held.any():  # the span to the held target; a zone a row is kept over no longer counts
            alt_to = -target[:, 2]
            lo, hi = np.minimum(alt_now, alt_to), np.maximum(alt_now, alt_to)
            active = self.active(lo, hi) & ~held
        subsets, inverse = np.unique(active, axis=0, return_inverse=True)
        out = []
        for g, mask in enumerate(subsets):
            zones, router = self.subset(tuple(int(j) for j in np.flatnonzero(mask)))
            out.append((np.flatnonzero(inverse.reshape(-1) == g), zones, router))
        return target, out
