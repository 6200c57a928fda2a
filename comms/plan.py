"""The fleet plan: where a fleet may fly (an inclusion fence with floor and ceiling), where it may
never go (keep-out polygons) and where it may come down (home and rally points).

Plain geometry in local north/east metres relative to the fleet origin (comms/geo.py converts
WGS-84), altitudes in metres above the origin (up positive; NED down is ``-alt_m``). The agent's
flight core, the route planner, the separation filter and the station all read this one type;
the wire encoding and signature live in comms/schema.py and trust/auth.py, the file loaders in
comms/plan_io.py.

``plan_refusal`` is the one check "may a vehicle be sent here": the flight core refuses a goto or
take-off with its reason, missions and formations refuse their targets with it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

MAX_POLYGON_VERTICES = 256
"""Most vertices one polygon may have (bounds the wire message and every check's cost)."""
MAX_PLAN_VERTICES = 2048
"""Most vertices of all the plan's polygons together (bounds the wire message)."""
MAX_ZONES = 64
"""Most keep-out zones one plan may hold."""
MAX_RALLY_POINTS = 32
"""Most rally points one plan may hold."""
MAX_NAME_BYTES = 64
"""Longest zone or rally point name, in UTF-8 bytes."""
MAX_COORD_M = 1.0e6
"""No plan coordinate is further than this from the fleet origin (a swarm's plan spans km)."""
HOME = "home"
"""The name of the rally point that is the fleet's home (a plan holds at most one)."""
RALLY_PADS = 25
"""Landing pads around home or a rally point by default, a square grid (agent/returning.py
`ReturnConfig.rally_pads`): vehicle id v lands on pad (v - 1) mod pads + 1."""
RALLY_PAD_SPACING_M = 5.0
"""Distance between neighbouring landing pads by default (`ReturnConfig.rally_pad_spacing_m`)."""

PolygonNE = tuple[tuple[float, float], ...]
"""A polygon as (north_m, east_m) vertices, not closed (the last vertex is not the first)."""


def _polygon(vertices_ne_m: Iterable[tuple[float, float]], what: str) -> PolygonNE:
    """`vertices_ne_m` as a tuple of (float, float), checked: 3..MAX_POLYGON_VERTICES finite
    vertices within MAX_COORD_M of the origin."""
    try:
        out = tuple((float(n), float(e)) for n, e in vertices_ne_m)
    except (TypeError, ValueError):
        raise ValueError(f"{what} needs (north_m, east_m) vertex pairs") from None
    _check_polygon(out, what)
    return out


def _check_polygon(vertices_ne_m: PolygonNE, what: str) -> None:
    if not 3 <= len(vertices_ne_m) <= MAX_POLYGON_VERTICES:
        raise ValueError(
            f"{what} needs 3 to {MAX_POLYGON_VERTICES} vertices, got {len(vertices_ne_m)}"
        )
    for v in vertices_ne_m:
        if len(v) != 2 or not all(math.isfinite(c) and abs(c) <= MAX_COORD_M for c in v):
            raise ValueError(f"{what} has a bad vertex {v!r} (finite north/east metres expected)")


def _check_name(name: str, what: str) -> None:
    if not isinstance(name, str) or len(name.encode()) > MAX_NAME_BYTES or not name.isprintable():
        raise ValueError(f"{what} name must be printable text of at most {MAX_NAME_BYTES} bytes")


def _check_alt_band(floor_alt_m: float | None, ceiling_alt_m: float | None, what: str) -> None:
    for label, a in (("floor", floor_alt_m), ("ceiling", ceiling_alt_m)):
        if a is not None and not (math.isfinite(a) and abs(a) <= MAX_COORD_M):
            raise ValueError(f"{what} {label} must be finite metres, got {a}")
    if floor_alt_m is not None and ceiling_alt_m is not None and floor_alt_m >= ceiling_alt_m:
        raise ValueError(
            f"{what} floor {floor_alt_m:g} m must be below its ceiling {ceiling_alt_m:g} m"
        )


@dataclass(frozen=True)
class Fence:
    """The inclusion fence: vehicles stay inside the polygon and between floor and ceiling."""

    vertices_ne_m: PolygonNE
    """Polygon (north_m, east_m) vertices relative to the fleet origin, not closed."""
    floor_alt_m: float | None = None
    """Lowest altitude above the origin a target may have while airborne; None: no floor."""
    ceiling_alt_m: float | None = None
    """Highest altitude above the origin; None: no ceiling."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "vertices_ne_m", _polygon(self.vertices_ne_m, "the fence"))
        _check_alt_band(self.floor_alt_m, self.ceiling_alt_m, "the fence")


@dataclass(frozen=True)
class Zone:
    """A keep-out polygon: no target inside it, no route through it (between floor and ceiling
    when they are given; a zone without them is closed at every altitude)."""

    vertices_ne_m: PolygonNE
    """Polygon (north_m, east_m) vertices relative to the fleet origin, not closed."""
    name: str = ""
    """What the operator calls it ('school'); shown on the station and in refusals."""
    floor_alt_m: float | None = None
    """The zone starts at this altitude above the origin; None: from the ground."""
    ceiling_alt_m: float | None = None
    """The zone ends at this altitude above the origin; None: no top."""

    def __post_init__(self) -> None:
        what = f"keep-out zone {self.name!r}" if self.name else "a keep-out zone"
        _check_name(self.name, what)
        object.__setattr__(self, "vertices_ne_m", _polygon(self.vertices_ne_m, what))
        _check_alt_band(self.floor_alt_m, self.ceiling_alt_m, what)

    def covers_alt(self, alt_m: float) -> bool:
        """Whether the zone is closed at this altitude above the origin."""
        if self.floor_alt_m is not None and alt_m < self.floor_alt_m:
            return False
        return not (self.ceiling_alt_m is not None and alt_m > self.ceiling_alt_m)


@dataclass(frozen=True)
class RallyPoint:
    """A place to come down: home (name 'home') or a rally point."""

    n_m: float
    """North of the fleet origin, metres."""
    e_m: float
    """East of the fleet origin, metres."""
    alt_m: float = 0.0
    """Altitude above the origin, metres."""
    name: str = ""
    """'home' for the fleet's home, otherwise the operator's name for it."""

    def __post_init__(self) -> None:
        _check_name(self.name, "a rally point")
        for c in (self.n_m, self.e_m, self.alt_m):
            if not (math.isfinite(c) and abs(c) <= MAX_COORD_M):
                raise ValueError(f"rally point {self.name!r} needs finite metres, got {c}")


@dataclass(frozen=True)
class FleetPlan:
    """One version of a fleet's plan, as signed by the fleet authority or a roster station."""

    fleet: str
    """The fleet it is for (a plan for another fleet is refused)."""
    version: int
    """Strictly increasing: a member keeps the highest version it has verified."""
    stamp_ns: int
    """Wall-clock time the plan was signed, ns since the epoch."""
    fence: Fence | None = None
    """The inclusion fence; None: the agent's circular fence (agent/failsafe.py) stays in force."""
    keep_out: tuple[Zone, ...] = ()
    """Keep-out zones."""
    rally: tuple[RallyPoint, ...] = ()
    """Home and rally points."""
    signer_id: int = 0
    """Who signed it: 0 the fleet authority, N ground station N of the roster."""
    signature: bytes = field(default=b"", repr=False)
    """Ed25519 signature over the wire encoding (comms/schema.py PlanMessage, trust/auth.py);
    empty while unsigned."""

    def __post_init__(self) -> None:
        if not isinstance(self.version, int) or not 1 <= self.version < 2**32:
            raise ValueError(f"plan version must be an integer in 1..2^32-1, got {self.version!r}")
        if not isinstance(self.stamp_ns, int) or not 0 <= self.stamp_ns < 2**64:
            raise ValueError(f"plan stamp_ns must fit 64 bits, got {self.stamp_ns!r}")
        if not isinstance(self.signer_id, int) or not 0 <= self.signer_id < 2**16:
            raise ValueError("plan signer_id must be 0 (authority) or a station id")
        n_vertices = sum(len(p) for p in self.polygons_ne_m())
        if n_vertices > MAX_PLAN_VERTICES:
            raise ValueError(f"a plan holds at most {MAX_PLAN_VERTICES} vertices, got {n_vertices}")
        object.__setattr__(self, "keep_out", tuple(self.keep_out))
        object.__setattr__(self, "rally", tuple(self.rally))
        if len(self.keep_out) > MAX_ZONES:
            raise ValueError(f"a plan holds at most {MAX_ZONES} keep-out zones")
        if len(self.rally) > MAX_RALLY_POINTS:
            raise ValueError(f"a plan holds at most {MAX_RALLY_POINTS} rally points")

    @property
    def home(self) -> RallyPoint | None:
        """The rally point named 'home', if any."""
        return next((r for r in self.rally if r.name == HOME), None)

    def polygons_ne_m(self) -> list[PolygonNE]:
        """The fence's polygon (first, if any) and every keep-out polygon."""
        fence = [self.fence.vertices_ne_m] if self.fence is not None else []
        return fence + self.keep_out_polygons_ne_m()

    def keep_out_polygons_ne_m(self) -> list[PolygonNE]:
        """Every keep-out polygon's vertices (what the route planner and the filter inflate)."""
        return [z.vertices_ne_m for z in self.keep_out]


def rally_numbers(rally: tuple[RallyPoint, ...]) -> list[tuple[int, int]]:
    """(number, index into `rally`) of each rally point other than home, numbered from 1 in
    the plan's order: the numbers the station shows and edits them by."""
    return list(enumerate((i for i, r in enumerate(rally) if r.name != HOME), start=1))


@dataclass(frozen=True)
class PadLayout:
    """The landing pads a return lays around home or a rally point: a square grid centred on
    the point, ceil(sqrt(pads)) pads a side, `spacing_m` apart, numbered from the south-west
    corner eastwards, row by row northwards. The one layout: the returning vehicles land on it
    (agent/returning.py `ReturnConfig.pad_layout`) and the station checks every pad of it
    against the zones and the fence (groundstation/target_check.py `landing_problems`)."""

    pads: int = RALLY_PADS
    """Pads around a point; vehicle id v lands on pad (v - 1) mod pads + 1 (1 pad: the point)."""
    spacing_m: float = RALLY_PAD_SPACING_M
    """Distance between neighbouring pads, metres."""

    def __post_init__(self) -> None:
        if not 1 <= self.pads <= 10_000:
            raise ValueError(f"pads must be within 1..10000, got {self.pads}")
        if not (math.isfinite(self.spacing_m) and 0 < self.spacing_m <= MAX_COORD_M):
            raise ValueError(f"the pad spacing must be positive metres, got {self.spacing_m}")

    def offset_ne_m(self, pad_no: int) -> tuple[float, float]:
        """Offset (north_m, east_m) of pad `pad_no` (1..pads) from its point:

        side = ceil(sqrt(pads)), k = pad_no - 1
        offset = (k // side - (side - 1) / 2, k % side - (side - 1) / 2) x spacing_m
        """
        side = math.ceil(math.sqrt(self.pads))
        k = pad_no - 1
        half = (side - 1) / 2.0
        return (k // side - half) * self.spacing_m, (k % side - half) * self.spacing_m


def point_in_polygon(n_m: float, e_m: float, vertices_ne_m: PolygonNE) -> bool:
    """Even-odd ray cast; a point on an edge counts as inside (a target on a zone edge is in)."""
    inside = False
    k = len(vertices_ne_m)
    for a in range(k):
        n1, e1 = vertices_ne_m[a]
        n2, e2 = vertices_ne_m[(a + 1) % k]
        # On the edge: collinear and within the segment's box.
        cross = (n2 - n1) * (e_m - e1) - (e2 - e1) * (n_m - n1)
        if (
            abs(cross) <= 1e-9 * max(1.0, abs(n2 - n1) + abs(e2 - e1))
            and min(n1, n2) - 1e-9 <= n_m <= max(n1, n2) + 1e-9
            and min(e1, e2) - 1e-9 <= e_m <= max(e1, e2) + 1e-9
        ):
            return True
        if (e1 > e_m) != (e2 > e_m):
            n_cross = n1 + (e_m - e1) * (n2 - n1) / (e2 - e1)
            if n_m < n_cross:
                inside = not inside
    return inside


def plan_refusal(plan: FleetPlan | None, ne_m: tuple[float, float], alt_m: float) -> str | None:
    """Why a vehicle may not be sent to (north, east) at ``alt_m`` above the origin, or None.

    Reasons read as "inside keep-out zone 'school'", "outside the fence",
    "above the 120 m ceiling", "below the 5 m floor". No plan: None (the circular fence applies).
    """
    if plan is None:
        return None
    n_m, e_m = float(ne_m[0]), float(ne_m[1])
    for z in plan.keep_out:
        if z.covers_alt(alt_m) and point_in_polygon(n_m, e_m, z.vertices_ne_m):
            return f"inside keep-out zone {z.name!r}" if z.name else "inside a keep-out zone"
    f = plan.fence
    if f is None:
        return None
    if not point_in_polygon(n_m, e_m, f.vertices_ne_m):
        return "outside the fence"
    if f.ceiling_alt_m is not None and alt_m > f.ceiling_alt_m:
        return f"above the {f.ceiling_alt_m:g} m ceiling"
    if f.floor_alt_m is not None and alt_m < f.floor_alt_m:
        return f"below the {f.floor_alt_m:g} m floor"
    return None
