"""Fleet plan files: GeoJSON and QGroundControl `.plan` in, checked geometry out; the signed
`plan.bin` (PlanMessage wire bytes) that `covey plan load` writes and `covey plan push` sends.

GeoJSON (RFC 7946: [lon, lat] WGS-84) is a FeatureCollection of
    Polygon (or MultiPolygon) features, properties {"role": "fence" | "keep_out", "name",
        "floor_m", "ceiling_m"} (altitudes in metres above the fleet origin, up);
    Point features, properties {"role": "home" | "rally", "name", "alt_m"}.
A QGC plan's `geoFence.polygons` (`inclusion` true: the fence, false: keep-out zones),
`geoFence.circles` (as polygons: an inclusion circle by its inscribed polygon, an exclusion one by
its circumscribed polygon, so either errs on the safe side), `rallyPoints.points` and
`mission.plannedHomePosition` (home). QGC fences have no altitudes: give the floor and ceiling.

Everything is converted to local north/east metres around the fleet origin (comms/geo.py) and
checked with shapely: valid polygons (closed rings, no self-intersection, no holes), one fence,
home and rally points inside the fence and outside every keep-out zone. Every refusal is a
`BadPlanError`: one line naming the file, the feature and why.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import shapely
from shapely.validation import explain_validity

from comms.geo import GeoOrigin
from comms.plan import HOME, Fence, FleetPlan, RallyPoint, Zone
from comms.schema import MAX_PLAN_BYTES, DecodeError, PlanMessage
from kit.safe_load import BadFileError, decode_utf8, parse_json, read_bounded

MAX_PLAN_FILE_BYTES = 4_000_000
"""The largest GeoJSON or QGC plan file read (a few hundred vertices take a few KB)."""
CIRCLE_VERTICES = 32
"""A QGC fence circle becomes a polygon of this many vertices."""
PLAN_FILE = "plan.bin"
"""The signed plan `covey plan load` writes next to the roster (trust/authority.py)."""


class BadPlanError(ValueError):
    """A plan file cannot be used; the message is one line that says where and why."""


@dataclass(frozen=True)
class PlanGeometry:
    """What a plan file holds, in local metres, before it is versioned and signed."""

    fence: Fence | None = None
    keep_out: tuple[Zone, ...] = ()
    rally: tuple[RallyPoint, ...] = ()
    notes: tuple[str, ...] = field(default=(), compare=False)
    """What the operator should know (circles approximated, a zone outside the fence)."""

    def plan(
        self, fleet: str, version: int, stamp_ns: int | None = None, *, now_ns=time.time_ns
    ) -> FleetPlan:
        """An unsigned FleetPlan of this geometry."""
        return FleetPlan(
            fleet,
            version,
            now_ns() if stamp_ns is None else stamp_ns,
            self.fence,
            self.keep_out,
            self.rally,
        )


# -- reading -------------------------------------------------------------------------------------
def read_plan_file(
    path: str | Path,
    origin: GeoOrigin,
    *,
    floor_alt_m: float | None = None,
    ceiling_alt_m: float | None = None,
) -> PlanGeometry:
    """A GeoJSON or QGC `.plan` file's geometry, checked (BadPlanError otherwise).
    `floor_alt_m`, `ceiling_alt_m`: the fence's floor and ceiling above the origin; they
    replace the file's (a QGC file has none)."""
    try:
        raw = read_bounded(path, MAX_PLAN_FILE_BYTES, "plan file")
    except BadFileError as exc:
        raise BadPlanError(str(exc)) from None
    where = f"plan file {Path(path).expanduser()}"
    return parse_plan(raw, where, origin, floor_alt_m=floor_alt_m, ceiling_alt_m=ceiling_alt_m)


def parse_plan(
    raw: bytes,
    where: str,
    origin: GeoOrigin,
    *,
    floor_alt_m: float | None = None,
    ceiling_alt_m: float | None = None,
) -> PlanGeometry:
    """As `read_plan_file`, for a file's bytes (an upload in the station); `where` names it."""
    if len(raw) > MAX_PLAN_FILE_BYTES:
        raise BadPlanError(f"{where} is {len(raw)} bytes, over the {MAX_PLAN_FILE_BYTES} limit")
    try:
        doc = parse_json(decode_utf8(raw, where), where)
    except BadFileError as exc:
        raise BadPlanError(str(exc)) from None
    if not isinstance(doc, dict):
        raise BadPlanError(f"{where} is not a JSON object (GeoJSON or a QGC .plan expected)")
    try:
        if doc.get("type") == "FeatureCollection":
            geometry = _from_geojson(doc, origin)
        elif doc.get("fileType") == "Plan":
            geometry = _from_qgc(doc, origin)
        else:
            raise ValueError("neither a GeoJSON FeatureCollection nor a QGC plan (fileType 'Plan')")
        if floor_alt_m is not None or ceiling_alt_m is not None:
            if geometry.fence is None:
                raise ValueError("a floor or ceiling was given but the file has no fence")
            f = geometry.fence
            geometry = PlanGeometry(
                Fence(
                    f.vertices_ne_m,
                    f.floor_alt_m if floor_alt_m is None else floor_alt_m,
                    f.ceiling_alt_m if ceiling_alt_m is None else ceiling_alt_m,
                ),
                geometry.keep_out,
                geometry.rally,
                geometry.notes,
            )
        return check_geometry(geometry)
    except (ValueError, TypeError, KeyError, IndexError) as exc:
        raise BadPlanError(f"{where}: {_one_line(exc)}") from None


def check_geometry(g: PlanGeometry) -> PlanGeometry:
    """Refuse (ValueError) what shapely finds wrong; returns `g` with notes added."""
    notes = list(g.notes)
    fence = None
    if g.fence is not None:
        fence = _valid(g.fence.vertices_ne_m, "the fence")
    zones = []
    for z in g.keep_out:
        what = f"keep-out zone {z.name!r}" if z.name else "a keep-out zone"
        poly = _valid(z.vertices_ne_m, what)
        zones.append((z, poly, what))
        if fence is not None and not fence.intersects(poly):
            notes.append(f"{what} lies wholly outside the fence")
    for r in g.rally:
        point = shapely.Point(r.n_m, r.e_m)
        what = (
            "home" if r.name == HOME else f"rally point {r.name!r}" if r.name else "a rally point"
        )
        if fence is not None and not fence.covers(point):
            raise ValueError(f"{what} ({r.n_m:.1f}, {r.e_m:.1f}) m is outside the fence")
        for z, poly, zone in zones:
            if z.covers_alt(r.alt_m) and poly.covers(point):
                raise ValueError(f"{zone} covers {what} ({r.n_m:.1f}, {r.e_m:.1f}) m")
    if sum(r.name == HOME for r in g.rally) > 1:
        raise ValueError("more than one home point")
    return PlanGeometry(g.fence, g.keep_out, g.rally, tuple(notes))


def _valid(vertices_ne_m: Iterable[tuple[float, float]], what: str) -> shapely.Polygon:
    poly = shapely.Polygon(list(vertices_ne_m))
    if not poly.is_valid:
        raise ValueError(f"{what} is not a valid polygon: {explain_validity(poly)}")
    if poly.area < 1.0:
        raise ValueError(f"{what} has an area of {poly.area:.2f} m^2: degenerate")
    return poly


def _one_line(exc: BaseException) -> str:
    text = str(exc) if not isinstance(exc, KeyError) else f"missing {exc}"
    return " ".join(text.split())[:240]


def _number(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    return float(value)


def _opt_number(props: dict, key: str, what: str) -> float | None:
    value = props.get(key)
    return None if value is None else _number(value, f"{what} {key}")


def _ring(
    points: object, to_ne: Callable[[float, float], tuple[float, float]], what: str
) -> tuple[tuple[float, float], ...]:
    """A closed or open ring of position pairs -> open NE vertices (the closing one dropped)."""
    if not isinstance(points, list) or len(points) < 3:
        raise ValueError(f"{what} needs a list of at least 3 positions")
    out = []
    for k, p in enumerate(points):
        if not isinstance(p, list) or len(p) < 2:
            raise ValueError(f"{what} position {k} is not a coordinate pair")
        out.append(
            to_ne(_number(p[0], f"{what} position {k}"), _number(p[1], f"{what} position {k}"))
        )
    if len(out) > 3 and out[0] == out[-1]:
        out.pop()
    return tuple(out)


def _text(props: dict, key: str, what: str) -> str:
    value = props.get(key, "")
    if not isinstance(value, str):
        raise ValueError(f"{what} {key} must be text, got {value!r}")
    return value


# -- GeoJSON -------------------------------------------------------------------------------------
ROLES = {"fence": "fence", "keep_out": "keep_out", "keep-out": "keep_out", "keepout": "keep_out",
         "exclusion": "keep_out", "home": "home", "rally": "rally"}  # fmt: skip


def _from_geojson(doc: dict, origin: GeoOrigin) -> PlanGeometry:
    def to_ne(lon: float, lat: float) -> tuple[float, float]:  # GeoJSON is [lon, lat]
        n, e, _ = origin.to_local(_lat(lat), _lon(lon), origin.alt_m)
        return n, e

    features = doc.get("features")
    if not isinstance(features, list):
        raise ValueError("its 'features' is not a list")
    fence, zones, rally = None, [], []
    for k, feat in enumerate(features):
        if not isinstance(feat, dict) or not isinstance(feat.get("geometry"), dict):
            raise ValueError(f"feature {k} has no geometry object")
        props = feat.get("properties") or {}
        if not isinstance(props, dict):
            raise ValueError(f"feature {k}'s properties is not an object")
        geom = feat["geometry"]
        kind = geom.get("type")
        name = _text(props, "name", f"feature {k}")
        what = f"feature {k}" + (f" ({name!r})" if name else "")
        raw_role = props.get("role")
        role = ROLES.get(raw_role) if isinstance(raw_role, str) else None
        if role is None:
            raise ValueError(
                f"{what}: properties.role must be one of fence, keep_out, home, rally; "
                f"got {raw_role!r}"
            )
        coords = geom.get("coordinates")
        if kind in ("Polygon", "MultiPolygon"):
            if role not in ("fence", "keep_out"):
                raise ValueError(f"{what}: a {kind} is a fence or keep_out, not {role}")
            polygons = [coords] if kind == "Polygon" else coords
            if not isinstance(polygons, list) or not polygons:
                raise ValueError(f"{what}: coordinates must be a list of rings")
            floor = _opt_number(props, "floor_m", what)
            ceiling = _opt_number(props, "ceiling_m", what)
            for j, rings in enumerate(polygons):
                if not isinstance(rings, list) or not rings:
                    raise ValueError(f"{what}: polygon {j} has no rings")
                if len(rings) > 1:
                    raise ValueError(f"{what}: polygons with holes are not supported")
                vertices = _ring(rings[0], to_ne, what)
                if role == "fence":
                    if fence is not None or len(polygons) > 1:
                        raise ValueError(
                            f"{what}: a second fence polygon (covey's fence is one polygon: "
                            "merge them, or make the rest keep-out zones)"
                        )
                    fence = Fence(vertices, floor, ceiling)
                else:
                    label = name if len(polygons) == 1 else f"{name} {j + 1}".strip()
                    zones.append(Zone(vertices, label, floor, ceiling))
        elif kind == "Point":
            if role not in ("home", "rally"):
                raise ValueError(f"{what}: a Point is home or rally, not {role}")
            if not isinstance(coords, list) or len(coords) < 2:
                raise ValueError(f"{what}: a Point needs [lon, lat]")
            n, e = to_ne(_number(coords[0], what), _number(coords[1], what))
            alt = _opt_number(props, "alt_m", what) or 0.0
            rally.append(RallyPoint(n, e, alt, "home" if role == "home" else name))
        else:
            raise ValueError(f"{what}: geometry type {kind!r} (Polygon, MultiPolygon, Point)")
    return PlanGeometry(fence, tuple(zones), tuple(rally))


def _lat(lat: float) -> float:
    if not -90.0 <= lat <= 90.0:
        raise ValueError(f"latitude {lat} is outside [-90, 90] (GeoJSON is [lon, lat])")
    return lat


def _lon(lon: float) -> float:
    if not -180.0 <= lon <= 180.0:
        raise ValueError(f"longitude {lon} is outside [-180, 180]")
    return lon


# -- QGroundControl ------------------------------------------------------------------------------
def _from_qgc(doc: dict, origin: GeoOrigin) -> PlanGeometry:
    def to_ne(lat: float, lon: float) -> tuple[float, float]:  # QGC is [lat, lon]
        n, e, _ = origin.to_local(_lat(lat), _lon(lon), origin.alt_m)
        return n, e

    notes = []
    geofence = doc.get("geoFence") or {}
    if not isinstance(geofence, dict):
        raise ValueError("its geoFence is not an object")
    fence, zones = None, []
    polygons = geofence.get("polygons") or []
    circles = geofence.get("circles") or []
    if not isinstance(polygons, list) or not isinstance(circles, list):
        raise ValueError("geoFence polygons and circles must be lists")
    shapes = []
    for k, item in enumerate(polygons):
        if not isinstance(item, dict):
            raise ValueError(f"geoFence polygon {k} is not an object")
        what = f"geoFence polygon {k}"
        shapes.append(
            (bool(item.get("inclusion", True)), _ring(item.get("polygon"), to_ne, what), what)
        )
    for k, item in enumerate(circles):
        if not isinstance(item, dict) or not isinstance(item.get("circle"), dict):
            raise ValueError(f"geoFence circle {k} has no circle object")
        what = f"geoFence circle {k}"
        circle = item["circle"]
        center = circle.get("center")
        if not isinstance(center, list) or len(center) < 2:
            raise ValueError(f"{what} needs a center [lat, lon]")
        radius_m = _number(circle.get("radius"), f"{what} radius")
        if not 0.5 <= radius_m <= 100_000.0:
            raise ValueError(f"{what} radius {radius_m:g} m is outside [0.5, 100000]")
        inclusion = bool(item.get("inclusion", True))
        c_n, c_e = to_ne(_number(center[0], what), _number(center[1], what))
        # Inscribed polygon (vertices on the circle) for inclusion; circumscribed (its edges
        # touch the circle: vertices at r / cos(pi/k)) for exclusion.
        r = radius_m if inclusion else radius_m / math.cos(math.pi / CIRCLE_VERTICES)
        ring = tuple(
            (c_n + r * math.cos(2 * math.pi * j / CIRCLE_VERTICES),
             c_e + r * math.sin(2 * math.pi * j / CIRCLE_VERTICES))
            for j in range(CIRCLE_VERTICES)
        )  # fmt: skip
        shapes.append((inclusion, ring, what))
        notes.append(f"{what} ({radius_m:g} m) flown as a {CIRCLE_VERTICES}-gon")
    for inclusion, ring, what in shapes:
        if inclusion:
            if fence is not None:
                raise ValueError(
                    f"{what}: a second inclusion fence (covey's fence is one polygon: merge them)"
                )
            fence = Fence(ring)
        else:
            zones.append(Zone(ring, what.replace("geoFence ", "")))
    rally = []
    mission = doc.get("mission") or {}
    home = mission.get("plannedHomePosition") if isinstance(mission, dict) else None
    if home is not None:
        if not isinstance(home, list) or len(home) < 2:
            raise ValueError("mission.plannedHomePosition must be [lat, lon, alt]")
        n, e = to_ne(_number(home[0], "home"), _number(home[1], "home"))
        rally.append(RallyPoint(n, e, 0.0, "home"))
    points = (doc.get("rallyPoints") or {}).get("points") or []
    if not isinstance(points, list):
        raise ValueError("rallyPoints.points must be a list")
    for k, p in enumerate(points):
        if not isinstance(p, list) or len(p) < 2:
            raise ValueError(f"rally point {k} must be [lat, lon, alt]")
        n, e = to_ne(_number(p[0], f"rally point {k}"), _number(p[1], f"rally point {k}"))
        alt = _number(p[2], f"rally point {k} alt") if len(p) > 2 else 0.0
        rally.append(RallyPoint(n, e, alt, f"rally {k + 1}"))
    return PlanGeometry(fence, tuple(zones), tuple(rally), tuple(notes))


# -- signed plan files -----------------------------------------------------------------------------
def read_signed_plan(path: str | Path) -> FleetPlan:
    """A `plan.bin` (PlanMessage wire bytes), decoded; BadPlanError otherwise. The signature is
    checked by whoever uses it (the members, `covey plan show` against the authority)."""
    try:
        raw = read_bounded(path, MAX_PLAN_BYTES, "signed plan")
        return PlanMessage.decode(raw).plan
    except BadFileError as exc:
        raise BadPlanError(str(exc)) from None
    except DecodeError as exc:
        raise BadPlanError(f"signed plan {Path(path).expanduser()}: {exc}") from None


def write_signed_plan(path: str | Path, plan: FleetPlan) -> Path:
    """Write `plan`'s wire bytes atomically."""
    p = Path(path).expanduser()
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_bytes(PlanMessage(plan).encode())
    tmp.replace(p)
    return p


def next_version(previous: FleetPlan | None, now_ns: int) -> int:
    """A new plan's version: the wall clock's seconds, and past the previous plan's in any
    case (two stations that load plans a second apart order them by time)."""
    return max(now_ns // 1_000_000_000, (previous.version + 1) if previous else 1)
