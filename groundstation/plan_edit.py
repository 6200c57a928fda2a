"""Editing the fleet plan in the station, pure: a draft of the plan's geometry that an operator
changes one step at a time (add a keep-out zone or the fence corner by corner, move or delete a
corner, delete a zone or the fence, set the fence's floor and ceiling, set home, add, move or
delete a rally point), each step checked before it is taken. Polygons are numbered as the panel
shows them: the fence 0 (`FENCE_NO`), the zones from 1, each corner zone.corner from 1; rally
points from 1, home not counted (comms/plan.py `rally_numbers`).

A step that would make the plan invalid is refused with the reason, and the draft stays as it
was (`EditRefused`): the geometry through comms/plan_io.py `check_geometry` (shapely: a
self-crossing or degenerate polygon, fewer than 3 corners, home or a rally point inside a zone
or outside the fence, a second home),
then every vehicle's target as comms/plan.py `plan_refusal` words it (the check the flight core
makes) and every vehicle's position against the keep-out zones and the fence's polygon: a zone is
never drawn over a vehicle or over where one is flying to, a fence never leaves one outside (what
the plan already ruled out, e.g. a vehicle that drifted into a zone, blocks no edit elsewhere);
then home, every rally point and every landing pad a return lays around them (comms/plan.py
`PadLayout`) against the zones, the fence and the clearance the vehicles' filters keep from
them (`check_landing`: 3.8 m at 3 m separation and the assumed 0.5 m position sigma,
groundstation/target_check.py), so that a return can arrive there. `check_landing` is also what
`covey plan load` and the station's plan upload check a file with.
The plan's own limits (vertices, zones and rally points in all) are comms/plan.py `FleetPlan`'s.
The station signs and pushes a draft through the same path as an uploaded file
(groundstation/plan_view.py `PlanView.push_geometry`).

No viser, no Zenoh, no clock (groundstation/plan_editor.py is the panel around it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from comms.plan import (
    HOME,
    MAX_COORD_M,
    MAX_POLYGON_VERTICES,
    MAX_ZONES,
    Fence,
    FleetPlan,
    PadLayout,
    PolygonNE,
    RallyPoint,
    Zone,
    plan_refusal,
    point_in_polygon,
    rally_numbers,
)
from comms.plan_io import PlanGeometry, check_geometry
from groundstation.fleet import FleetConfig
from groundstation.target_check import landing_problems

MAX_EDITS_LISTED = 16
"""Edits a draft remembers for the command log line (more are counted)."""
FENCE_NO = 0
"""The fence's number where a step takes a zone number (the zones are numbered from 1)."""
SEPARATION_M = FleetConfig().separation_m
"""The fleet's separation a draft is checked at unless told (the station's `separation_m`)."""


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
    is now (checked against the keep-out zones and the fence's polygon only: a landed vehicle is
    below any floor)."""

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
    """Corners of the zone or fence being drawn, (north_m, east_m), in click order."""
    edits: tuple[str, ...] = ()
    """What was changed, in order, as the command log lists it."""
    separation_m: float = SEPARATION_M
    """The fleet's separation (the vehicles' filter radius): home and rally points keep the zone
    clearance that follows from it (`check_landing`)."""
    pads: PadLayout = PadLayout()
    """The landing pads the fleet's returns lay around home and each rally point (the agents'
    `--rally-pads`, `--rally-pad-spacing-m`): each keeps that clearance too."""

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


def draft_of(
    plan: FleetPlan | None, separation_m: float = SEPARATION_M, pads: PadLayout = PadLayout()
) -> Draft:
    """A draft of `plan` (None: an empty plan) with nothing changed, checked at the fleet's
    `separation_m` and landing `pads`."""
    version = None if plan is None else plan.version
    return Draft(version, geometry_of(plan), separation_m=separation_m, pads=pads)


def vehicle_refusals(geometry: PlanGeometry, v: VehiclePoint) -> list[str]:
    """Every reason `geometry` rules out where vehicle `v` is (its keep-out zones, its fence's
    polygon) or flies to (its zones and its fence, as comms/plan.py `plan_refusal` words them)."""
    out = [
        f"inside keep-out zone {z.name!r}" if z.name else "inside a keep-out zone"
        for z in geometry.keep_out
        if z.covers_alt(v.alt_m) and point_in_polygon(v.n_m, v.e_m, z.vertices_ne_m)
    ]
    if geometry.fence is None:
        return out
    if v.is_target:
        fence_only = FleetPlan("draft", 1, 0, geometry.fence)
        why = plan_refusal(fence_only, (v.n_m, v.e_m), v.alt_m)
        if why is not None:
            out.append(why)
    elif not point_in_polygon(v.n_m, v.e_m, geometry.fence.vertices_ne_m):
        out.append("outside the fence")  # plan_refusal's words; the band is for targets only
    return out


def check_landing(
    geometry: PlanGeometry,
    separation_m: float,
    before: PlanGeometry | None = None,
    pads: PadLayout = PadLayout(),
) -> None:
    """EditRefused when home or a rally point of `geometry`, or one of the landing `pads` a
    return lays around it (comms/plan.py `PadLayout`, by default the agents' 5 x 5 grid 5 m
    apart), lies inside a keep-out zone, outside the fence, or nearer either than the vehicles'
    filters keep at the fleet's `separation_m` and the assumed position sigma
    (groundstation/target_check.py `landing_problems`): a return could not arrive there. A
    point whose pads partly fail is refused, not trimmed to the pads that pass: the vehicles
    land on every pad of the grid (vehicle v on pad (v - 1) mod pads + 1), so the operator
    moves the point. `before`: the geometry it replaces; a point or pad that one already had
    too near blocks no edit elsewhere."""
    new = landing_problems(geometry, separation_m, pads=pads)
    if new and before is not None:
        kept = list(dict.fromkeys(p.point for p in new if p.point in before.rally))  # unmoved
        was = landing_problems(before, separation_m, only=kept, pads=pads) if kept else []
        old = {(p.point, p.pad_no) for p in was}
        new = [p for p in new if (p.point, p.pad_no) not in old]
    if new:
        raise EditRefused(new[0].why)


def checked(
    geometry: PlanGeometry,
    vehicles: tuple[VehiclePoint, ...] = (),
    before: PlanGeometry | None = None,
    separation_m: float = SEPARATION_M,
    pads: PadLayout = PadLayout(),
) -> PlanGeometry:
    """`geometry` if it may be pushed with these vehicles where they are, else EditRefused.
    `before`: the geometry it replaces; what that one already ruled out (a vehicle that drifted
    into a zone, home too near a zone) blocks no edit elsewhere, only one that rules it out
    anew. `separation_m`, `pads`: the fleet's, for the zone clearance of home, the rally points
    and their landing pads."""
    try:
        out = check_geometry(geometry)
        out.plan("draft", 1, 0)  # FleetPlan's own limits: vertices and zones in all
    except ValueError as exc:
        raise EditRefused(" ".join(str(exc).split())) from None
    for v in vehicles:
        old = set() if before is None else set(vehicle_refusals(before, v))
        new = [why for why in vehicle_refusals(out, v) if why not in old]
        if new:
            raise EditRefused(f"{v} would be {new[0]}")
    check_landing(out, separation_m, before, pads)
    return out


def _zone_no(draft: Draft, zone_no: int) -> int:
    """The index of zone number `zone_no` (1-based, as the panel numbers them)."""
    n = len(draft.geometry.keep_out)
    if not n:
        raise EditRefused("the plan has no keep-out zone")
    if not 1 <= zone_no <= n:
        raise EditRefused(f"zone {zone_no} does not exist (zones 1 to {n})")
    return zone_no - 1


def _polygon_no(draft: Draft, zone_no: int) -> tuple[str, str, PolygonNE]:
    """(kind, label, corners) of polygon `zone_no`: FENCE_NO the fence, else zone `zone_no`."""
    if zone_no == FENCE_NO:
        fence = draft.geometry.fence
        if fence is None:
            raise EditRefused("the plan has no fence (click its corners, then 'Close fence')")
        return "fence", "fence", fence.vertices_ne_m
    z = draft.geometry.keep_out[_zone_no(draft, zone_no)]
    return "zone", _label(z, zone_no), z.vertices_ne_m


def _corner_no(zone_no: int, vertices_ne_m: PolygonNE, corner_no: int) -> int:
    k = len(vertices_ne_m)
    if not 1 <= corner_no <= k:
        what = "fence" if zone_no == FENCE_NO else f"zone {zone_no}"
        raise EditRefused(f"{what} has no corner {corner_no} (corners 1 to {k})")
    return corner_no - 1


def _point(n_m: float, e_m: float, what: str = "corner") -> tuple[float, float]:
    if not all(math.isfinite(c) and abs(c) <= MAX_COORD_M for c in (n_m, e_m)):
        raise EditRefused(f"{what} (N {n_m}, E {e_m}) must be finite metres within {MAX_COORD_M:g}")
    return round(float(n_m), 2), round(float(e_m), 2)


def _label(zone: Zone, zone_no: int) -> str:
    return f"zone {zone_no} ({zone.name!r})" if zone.name else f"zone {zone_no}"


def _take(
    draft: Draft, geometry: PlanGeometry, edit: str, vehicles: tuple[VehiclePoint, ...]
) -> Draft:
    """`draft` with `geometry`, checked against the draft's own (EditRefused otherwise)."""
    out = checked(geometry, vehicles, draft.geometry, draft.separation_m, draft.pads)
    return replace(draft, geometry=out, edits=(*draft.edits, edit))


def _with_polygon(
    draft: Draft,
    zone_no: int,
    vertices_ne_m: PolygonNE,
    edit: str,
    vehicles: tuple[VehiclePoint, ...],
) -> Draft:
    """Polygon `zone_no` (FENCE_NO: the fence, its band kept) with these corners."""
    g = draft.geometry
    try:
        if zone_no == FENCE_NO and g.fence is not None:
            fence = replace(g.fence, vertices_ne_m=vertices_ne_m)
            geometry = PlanGeometry(fence, g.keep_out, g.rally)
        else:
            zones = list(g.keep_out)
            i = _zone_no(draft, zone_no)
            zones[i] = replace(zones[i], vertices_ne_m=vertices_ne_m)
            geometry = PlanGeometry(g.fence, tuple(zones), g.rally)
    except ValueError as exc:
        if isinstance(exc, EditRefused):
            raise
        raise EditRefused(str(exc)) from None
    return _take(draft, geometry, edit, vehicles)


def add_corner(draft: Draft, n_m: float, e_m: float) -> Draft:
    """One more corner of the zone or fence being drawn."""
    if len(draft.corners_ne_m) >= MAX_POLYGON_VERTICES:
        raise EditRefused(f"a zone or fence has at most {MAX_POLYGON_VERTICES} corners")
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
    g = draft.geometry
    zones = (*g.keep_out, zone)
    edit = f"{_label(zone, len(zones))} added ({k} corners)"
    out = _take(draft, PlanGeometry(g.fence, zones, g.rally), edit, vehicles)
    return replace(out, corners_ne_m=())


def close_fence(draft: Draft, vehicles: tuple[VehiclePoint, ...] = ()) -> Draft:
    """The corners drawn so far become the fence, replacing the plan's (its floor and ceiling
    kept) or the first one (none: set them after)."""
    k = len(draft.corners_ne_m)
    if k < 3:
        raise EditRefused(f"a fence needs at least 3 corners; {k} clicked")
    g = draft.geometry
    old = g.fence
    try:
        fence = (
            Fence(draft.corners_ne_m)
            if old is None
            else replace(old, vertices_ne_m=draft.corners_ne_m)
        )
    except ValueError as exc:
        raise EditRefused(str(exc)) from None
    edit = f"fence {'drawn' if old is None else 'replaced'} ({k} corners)"
    out = _take(draft, PlanGeometry(fence, g.keep_out, g.rally), edit, vehicles)
    return replace(out, corners_ne_m=())


def move_corner(
    draft: Draft,
    zone_no: int,
    corner_no: int,
    n_m: float,
    e_m: float,
    vehicles: tuple[VehiclePoint, ...] = (),
) -> Draft:
    """Corner `corner_no` (1-based) of zone `zone_no` (1-based; FENCE_NO: the fence) moved to
    (n_m, e_m)."""
    _, label, verts = _polygon_no(draft, zone_no)
    j = _corner_no(zone_no, verts, corner_no)
    p = _point(n_m, e_m)
    moved = (*verts[:j], p, *verts[j + 1 :])
    edit = f"{label} corner {corner_no} moved to N {p[0]:g}, E {p[1]:g}"
    return _with_polygon(draft, zone_no, moved, edit, vehicles)


def delete_corner(
    draft: Draft, zone_no: int, corner_no: int, vehicles: tuple[VehiclePoint, ...] = ()
) -> Draft:
    """Corner `corner_no` of zone `zone_no` (FENCE_NO: the fence) removed (a zone or the fence
    keeps at least 3)."""
    kind, label, verts = _polygon_no(draft, zone_no)
    j = _corner_no(zone_no, verts, corner_no)
    if len(verts) <= 3:
        raise EditRefused(f"{label} has 3 corners, the fewest a {kind} can have")
    edit = f"{label} corner {corner_no} deleted"
    return _with_polygon(draft, zone_no, verts[:j] + verts[j + 1 :], edit, vehicles)


def delete_zone(draft: Draft, zone_no: int) -> Draft:
    """Zone `zone_no` removed (nothing a vehicle does can rule that out)."""
    i = _zone_no(draft, zone_no)
    g = draft.geometry
    z = g.keep_out[i]
    zones = g.keep_out[:i] + g.keep_out[i + 1 :]
    return _take(draft, PlanGeometry(g.fence, zones, g.rally), f"{_label(z, zone_no)} deleted", ())


def delete_fence(draft: Draft) -> Draft:
    """The fence removed (the agents' circular geofence, agent/failsafe.py, holds again)."""
    g = draft.geometry
    if g.fence is None:
        raise EditRefused("the plan has no fence to delete")
    return _take(draft, PlanGeometry(None, g.keep_out, g.rally), "fence deleted", ())


def set_fence_band(
    draft: Draft,
    floor_alt_m: float | None,
    ceiling_alt_m: float | None,
    vehicles: tuple[VehiclePoint, ...] = (),
) -> Draft:
    """The fence's floor and ceiling (metres above the origin; None: none)."""
    g = draft.geometry
    if g.fence is None:
        raise EditRefused("the plan has no fence to set a floor or ceiling on (draw one first)")
    try:
        fence = Fence(g.fence.vertices_ne_m, floor_alt_m, ceiling_alt_m)
    except ValueError as exc:
        raise EditRefused(str(exc)) from None
    band = ", ".join(
        f"{what} {'none' if v is None else f'{v:g} m'}"
        for what, v in (("floor", floor_alt_m), ("ceiling", ceiling_alt_m))
    )
    return _take(draft, PlanGeometry(fence, g.keep_out, g.rally), f"fence {band}", vehicles)


# -- home and rally points -------------------------------------------------------------------------
def _rally_index(draft: Draft, rally_no: int) -> int:
    """The index in the plan's rally tuple of rally point `rally_no` (1-based, home not counted:
    comms/plan.py `rally_numbers`)."""
    numbers = rally_numbers(draft.geometry.rally)
    if not numbers:
        raise EditRefused("the plan has no rally point")
    if not 1 <= rally_no <= len(numbers):
        raise EditRefused(
            f"rally point {rally_no} does not exist (rally points 1 to {len(numbers)})"
        )
    return numbers[rally_no - 1][1]


def _rally_label(r: RallyPoint, rally_no: int) -> str:
    return f"rally point {rally_no} ({r.name!r})" if r.name else f"rally point {rally_no}"


def _placed(
    n_m: float, e_m: float, alt_m: float | None, old: RallyPoint | None, name: str, what: str
) -> RallyPoint:
    """A rally point (home: name HOME) at (n_m, e_m); `alt_m` None keeps `old`'s altitude (a
    new point: 0, the origin's)."""
    n, e = _point(n_m, e_m, what)
    alt = (old.alt_m if old is not None else 0.0) if alt_m is None else alt_m
    try:
        return RallyPoint(n, e, round(float(alt), 2), name)
    except ValueError as exc:
        raise EditRefused(str(exc)) from None


def where(r: RallyPoint) -> str:
    """Where home or a rally point is, as the edits and the draft summary say it."""
    return f"N {r.n_m:g}, E {r.e_m:g}" + (f", {r.alt_m:g} m up" if r.alt_m else "")


def _with_rally(draft: Draft, rally: tuple[RallyPoint, ...], edit: str) -> Draft:
    """`draft` with these home and rally points, checked as a file's are (inside the fence,
    outside every zone that covers their altitude, one home) and against FleetPlan's limits."""
    g = draft.geometry
    return _take(draft, PlanGeometry(g.fence, g.keep_out, rally), edit, ())


def set_home(draft: Draft, n_m: float, e_m: float, alt_m: float | None = None) -> Draft:
    """The fleet's home at (n_m, e_m), `alt_m` above the origin (None: the home's altitude
    kept, 0 for a first home); it replaces the plan's home where it stood in the list."""
    rally = draft.geometry.rally
    i = next((k for k, r in enumerate(rally) if r.name == HOME), None)
    old = None if i is None else rally[i]
    home = _placed(n_m, e_m, alt_m, old, HOME, "home")
    if i is None:
        return _with_rally(draft, (home, *rally), f"home set at {where(home)}")
    return _with_rally(draft, (*rally[:i], home, *rally[i + 1 :]), f"home moved to {where(home)}")


def add_rally(
    draft: Draft, n_m: float, e_m: float, alt_m: float | None = None, name: str = ""
) -> Draft:
    """One more rally point at (n_m, e_m), `alt_m` above the origin (None: 0), numbered after
    the plan's; `name` may be empty, never 'home' (that is `set_home`)."""
    name = name.strip()
    if name == HOME:
        raise EditRefused(f"{HOME!r} names the fleet's home: set it with 'Set home'")
    r = _placed(n_m, e_m, alt_m, None, name, "rally point")
    rally = (*draft.geometry.rally, r)
    no = len(rally_numbers(rally))
    return _with_rally(draft, rally, f"{_rally_label(r, no)} added at {where(r)}")


def move_rally(
    draft: Draft, rally_no: int, n_m: float, e_m: float, alt_m: float | None = None
) -> Draft:
    """Rally point `rally_no` (1-based, home not counted) moved to (n_m, e_m), `alt_m` above the
    origin (None: its altitude kept), its name kept."""
    i = _rally_index(draft, rally_no)
    rally = draft.geometry.rally
    r = _placed(n_m, e_m, alt_m, rally[i], rally[i].name, "rally point")
    edit = f"{_rally_label(r, rally_no)} moved to {where(r)}"
    return _with_rally(draft, (*rally[:i], r, *rally[i + 1 :]), edit)


def delete_rally(draft: Draft, rally_no: int) -> Draft:
    """Rally point `rally_no` removed (those after it move up one number)."""
    i = _rally_index(draft, rally_no)
    rally = draft.geometry.rally
    edit = f"{_rally_label(rally[i], rally_no)} deleted"
    return _with_rally(draft, rally[:i] + rally[i + 1 :], edit)
