"""Editing the fleet plan in the station, pure: a draft of the plan's geometry that an operator
changes one step at a time (add a keep-out zone corner by corner, move or delete a corner, delete
a zone, set the fence's floor and ceiling), each step checked before it is taken.

A step that would make the plan invalid is refused with the reason, and the draft stays as it
was (`EditRefused`): the geometry through comms/plan_io.py `check_geometry` (shapely: a
self-crossing or degenerate polygon, fewer than 3 corners, home or a rally point inside a zone),
then every vehicle's target as comms/plan.py `plan_refusal` words it (the check the flight core
makes) and every vehicle's position against the keep-out zones: a zone is never drawn over a
vehicle or over where one is flying to (what the plan already ruled out, e.g. a vehicle that
drifted into a zone, blocks no edit elsewhere). The station signs and pushes a draft through the same
path as an uploaded file (groundstation/plan_view.py `PlanView.push_geometry`).

No viser, no Zenoh, no clock (groundstation/plan_editor.py is the panel around it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from comms.plan import (
    MAX_COORD_M,
    MAX_POLYGON_VERTICES,
    MAX_ZONES,
    Fence,
    FleetPlan,
    Zone,
    plan_refusal,
    point_in_polygon,
)
from comms.plan_io import PlanGeometry, check_geometry

MAX_EDITS_LISTED = 16
"""Edits a draft remembers for the command log line (more are counted)."""


class EditRefused(ValueError):
    """An edit the draft did not take; the message says why, in one line."""


@dataclass(frozen=True)
class VehiclePoint:
    """Where a vehicle is, or is flying to (what a new plan must not rule out)."""

    vehicle_id: int
    n_m: float
    """North of the fleet origin, metres."""
    e_m: float
    """East of the fleet origin, metres."""
    alt_m: float
    """Altitude above the origin, metres (up)."""
    is_target: bool
    """True: where it is flying to (checked as the flight core checks a goto); False: where it
    is now (checked against the keep-out zones only: a landed vehicle is below any floor)."""

    def __str__(self) -> str:
        what = "target" if self.is_target else "position"
        return f"vehicle {self.vehicle_id}'s {what} (N {self.n_m:.1f}, E {self.e_m:.1f} m)"


@dataclass(frozen=True)
class Draft:
    """The plan as this operator is editing it; every field is what the panel shows."""

    base_version: int | None
    """The version of the fleet plan the draft started from (None: there was none)."""
    geometry: PlanGeometry
    """The plan's geometry with the edits taken so far."""
    corners_ne_m: tuple[tuple[float, float], ...] = ()
    """Corners of the zone being drawn, (north_m, east_m), in click order."""
    edits: tuple[str, ...] = ()
    """What was changed, in order, as the command log lists it."""

    @property
    def changed(self) -> bool:
        return bool(self.edits)

    def describe_edits(self) -> str:
        """The edits as one line ('zone 'depot' added; fence ceiling 80 m')."""
        shown = "; ".join(self.edits[:MAX_EDITS_LISTED])
        more = len(self.edits) - MAX_EDITS_LISTED
        return shown + (f"; +{more} more" if more > 0 else "")


def geometry_of(plan: FleetPlan | None) -> PlanGeometry:
    """A plan's geometry (None: an empty one)."""
    if plan is None:
        return PlanGeometry()
    return PlanGeometry(plan.fence, plan.keep_out, plan.rally)


def draft_of(plan: FleetPlan | None) -> Draft:
    """A draft of `plan` (None: an empty plan) with nothing changed."""
    return Draft(None if plan is None else plan.version, geometry_of(plan))


def vehicle_refusals(geometry: PlanGeometry, v: VehiclePoint) -> list[str]:
    """Every reason `geometry` rules out where vehicle `v` is (its keep-out zones) or flies to
    (its zones and its fence, as comms/plan.py `plan_refusal` words them)."""
    out = [
        f"inside keep-out zone {z.name!r}" if z.name else "inside a keep-out zone"
        for z in geometry.keep_out
        if z.covers_alt(v.alt_m) and point_in_polygon(v.n_m, v.e_m, z.vertices_ne_m)
    ]
    if v.is_target and geometry.fence is not None:
        fence_only = FleetPlan("draft", 1, 0, geometry.fence)
        why = plan_refusal(fence_only, (v.n_m, v.e_m), v.alt_m)
        if why is not None:
            out.append(why)
    return out


def checked(
    geometry: PlanGeometry,
    vehicles: tuple[VehiclePoint, ...] = (),
    before: PlanGeometry | None = None,
) -> PlanGeometry:
    """`geometry` if it may be pushed with these vehicles where they are, else EditRefused.
    `before`: the geometry it replaces; what that one already ruled out (a vehicle that drifted
    into a zone) blocks no edit elsewhere, only one that rules it out anew."""
    try:
        out = check_geometry(geometry)
    except ValueError as exc:
        raise EditRefused(" ".join(str(exc).split())) from None
    for v in vehicles:
        old = set() if before is None else set(vehicle_refusals(before, v))
        new = [why for why in vehicle_refusals(out, v) if why not in old]
        if new:
            raise EditRefused(f"{v} would be {new[0]}")
    return out


def _zone_no(draft: Draft, zone_no: int) -> int:
    """The index of zone number `zone_no` (1-based, as the panel numbers them)."""
    n = len(draft.geometry.keep_out)
    if not n:
        raise EditRefused("the plan has no keep-out zone")
    if not 1 <= zone_no <= n:
        raise EditRefused(f"zone {zone_no} does not exist (zones 1 to {n})")
    return zone_no - 1


def _corner_no(zone: Zone, zone_no: int, corner_no: int) -> int:
    k = len(zone.vertices_ne_m)
    if not 1 <= corner_no <= k:
        raise EditRefused(f"zone {zone_no} has no corner {corner_no} (corners 1 to {k})")
    return corner_no - 1


def _point(n_m: float, e_m: float) -> tuple[float, float]:
    if not all(math.isfinite(c) and abs(c) <= MAX_COORD_M for c in (n_m, e_m)):
        raise EditRefused(f"corner (N {n_m}, E {e_m}) must be finite metres within {MAX_COORD_M:g}")
    return round(float(n_m), 2), round(float(e_m), 2)


def _label(zone: Zone, zone_no: int) -> str:
    return f"zone {zone_no} ({zone.name!r})" if zone.name else f"zone {zone_no}"


def _with_zones(
    draft: Draft, zones: list[Zone], edit: str, vehicles: tuple[VehiclePoint, ...]
) -> Draft:
    g = draft.geometry
    geometry = checked(PlanGeometry(g.fence, tuple(zones), g.rally), vehicles, g)
    return replace(draft, geometry=geometry, edits=(*draft.edits, edit))


def add_corner(draft: Draft, n_m: float, e_m: float) -> Draft:
    """One more corner of the zone being drawn."""
    if len(draft.corners_ne_m) >= MAX_POLYGON_VERTICES:
        raise EditRefused(f"a zone has at most {MAX_POLYGON_VERTICES} corners")
    return replace(draft, corners_ne_m=(*draft.corners_ne_m, _point(n_m, e_m)))


def discard_corners(draft: Draft) -> Draft:
    return replace(draft, corners_ne_m=())


def close_zone(draft: Draft, name: str, vehicles: tuple[VehiclePoint, ...] = ()) -> Draft:
    """The corners drawn so far become a keep-out zone named `name` (from the ground up)."""
    k = len(draft.corners_ne_m)
    if k < 3:
        raise EditRefused(f"a zone needs at least 3 corners; {k} clicked")
    if len(draft.geometry.keep_out) >= MAX_ZONES:
        raise EditRefused(f"a plan holds at most {MAX_ZONES} keep-out zones")
    name = name.strip()
    try:
        zone = Zone(draft.corners_ne_m, name)
    except ValueError as exc:
        raise EditRefused(str(exc)) from None
    zones = [*draft.geometry.keep_out, zone]
    out = _with_zones(draft, zones, f"{_label(zone, len(zones))} added ({k} corners)", vehicles)
    return replace(out, corners_ne_m=())


def move_corner(
    draft: Draft,
    zone_no: int,
    corner_no: int,
    n_m: float,
    e_m: float,
    vehicles: tuple[VehiclePoint, ...] = (),
) -> Draft:
    """Corner `corner_no` of zone `zone_no` (both 1-based) moved to (n_m, e_m)."""
    i = _zone_no(draft, zone_no)
    zones = list(draft.geometry.keep_out)
    z = zones[i]
    j = _corner_no(z, zone_no, corner_no)
    p = _point(n_m, e_m)
    verts = list(z.vertices_ne_m)
    verts[j] = p
    zones[i] = replace(z, vertices_ne_m=tuple(verts))
    edit = f"{_label(z, zone_no)} corner {corner_no} moved to N {p[0]:g}, E {p[1]:g}"
    return _with_zones(draft, zones, edit, vehicles)


def delete_corner(
    draft: Draft, zone_no: int, corner_no: int, vehicles: tuple[VehiclePoint, ...] = ()
) -> Draft:
    """Corner `corner_no` of zone `zone_no` removed (a zone keeps at least 3)."""
    i = _zone_no(draft, zone_no)
    zones = list(draft.geometry.keep_out)
    z = zones[i]
    j = _corner_no(z, zone_no, corner_no)
    if len(z.vertices_ne_m) <= 3:
        raise EditRefused(f"{_label(z, zone_no)} has 3 corners, the fewest a zone can have")
    zones[i] = replace(z, vertices_ne_m=z.vertices_ne_m[:j] + z.vertices_ne_m[j + 1 :])
    return _with_zones(draft, zones, f"{_label(z, zone_no)} corner {corner_no} deleted", vehicles)


def delete_zone(draft: Draft, zone_no: int) -> Draft:
    """Zone `zone_no` removed (nothing a vehicle does can rule that out)."""
    i = _zone_no(draft, zone_no)
    zones = list(draft.geometry.keep_out)
    z = zones.pop(i)
    return _with_zones(draft, zones, f"{_label(z, zone_no)} deleted", ())


def set_fence_band(
    draft: Draft,
    floor_alt_m: float | None,
    ceiling_alt_m: float | None,
    vehicles: tuple[VehiclePoint, ...] = (),
) -> Draft:
    """The fence's floor and ceiling (metres above the origin; None: none)."""
    g = draft.geometry
    if g.fence is None:
        raise EditRefused("the plan has no fence to set a floor or ceiling on (load one first)")
    try:
        fence = Fence(g.fence.vertices_ne_m, floor_alt_m, ceiling_alt_m)
    except ValueError as exc:
        raise EditRefused(str(exc)) from None
    geometry = checked(PlanGeometry(fence, g.keep_out, g.rally), vehicles, g)
    band = ", ".join(
        f"{what} {'none' if v is None else f'{v:g} m'}"
        for what, v in (("floor", floor_alt_m), ("ceiling", ceiling_alt_m))
    )
    return replace(draft, geometry=geometry, edits=(*draft.edits, f"fence {band}"))
