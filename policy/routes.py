"""Routes around keep-out zones: a visibility graph over inflated polygons turns a goto into
waypoints.

Each keep-out polygon is inflated by `RouteConfig.inflate_m` (the filter's zone radius plus a
route margin, shapely buffer with mitre joins, then simplified without coming any closer) and
the inflated polygons are merged, so a gap narrower than twice the inflation is closed. The fence
(an inclusion polygon) is deflated by the same amount. The graph's nodes are the corners of that
free space that a shortest path can bend around (its reflex corners); its edges, the straight
segments between them that stay in the free space. A goal is joined to the nodes it sees, and
Dijkstra from the goal gives every node's distance to it (cached per goal; the graph is cached
per plan: zones change rarely).

Segments from the vehicle's position are checked against the zones inflated by half the route
margin less (`RouteConfig.sight_m`): a vehicle that drifts a little inside the route's
inflation (traffic, lag) still sees its way on instead of being led back out every tick. So:
- `next_waypoint(pos, goal)` is stateless: the goal when it is in sight, else the node in sight
  with the least (distance to it + its distance to the goal); as the vehicle rounds a corner the
  next one comes into sight, so it advances without a radius to hit;
- a position nearer a zone than `sight_m` (or outside the fence deflated by it) is first led to
  the nearest point of the route's free space (projected out);
- a goal inside a keep-out zone or outside the fence is refused with the reason; a goal next to
  a zone (within the inflation, outside the zone) is approached through the nearest free point,
  and the separation filter stops the vehicle at its radius (policy.zone_lines, 1.8 m at 3 m,
  plus sigma_k x the position 1-sigma); `check_goal` moves a goal nearer than that to the
  nearest point outside it, where the vehicle can arrive (the flight core and `covey eval`
  fly there, or refuse the goto when that point lies beyond the arrival radius);
- no path (the goal walled off): `Route.reason` says so, and `next_waypoint` gives the goal
  itself (the filter still keeps the vehicle out of every zone);
- two-way ways first (`RouteConfig.two_way`): a gap that two vehicles cannot pass each other in
  (narrower than twice the zone clearance plus the pair's berth: 14 m on plain GNSS) jams when
  two streams meet in it, each waiting for the other. So the zones are also closed over such
  gaps (`Router.two_way`: grown and shrunk by half that width, which fills the narrow gaps and
  pockets and keeps every outline; the fence's outside is closed with them, so a gap between a
  zone and the fence counts as one between two zones), and a vehicle flies that router's route where it is at most
  `two_way_detour_max` (1.5) times the one-lane route from where it is; else, or where its
  position or goal lies in a filled gap, the one-lane route. Decided from the position each
  tick, without flip-flop: along the one-lane route its length falls as fast as the vehicle
  flies and the two-way route's at most as fast, so their ratio (>= 1) never falls there, and
  a vehicle once past the bound stays on the one-lane route.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import shapely
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from policy.zone_lines import ZONE_CLEARANCE_SHARE

BOUNDARY_TOL_M = 1e-6
"""Segments along the free space's boundary count as inside (numerical slack of the checks)."""
PROJECT_IN_M = 0.01
"""A point projected out of a zone's band is put this far inside the free space."""
PAD_STEP_M = 0.25
"""A widened router's padding is rounded up to this step (`Router.widened`): one router per
step of position uncertainty, not one per reported sigma."""
CORNER_PASSED_M = 0.3
"""A vehicle this near the corner it flies to has reached it: it flies on to the corner's
successor on the route. Without it, a vehicle that arrives a hair off the corner, on the side
from which the next leg clips the inflation, keeps choosing the corner, slows onto it (straight
flight stops on its waypoint) and never arrives (seed 59's zones-random-s2, ideal vehicles)."""
MAX_WIDENED = 8
"""Widened routers kept per plan (a fleet's sigmas fall in a few steps)."""
CLOSED_MIN_M2 = 0.5
"""A two-way router (`Router.two_way`) is built only where the closing filled at least this
much (a gap or pocket), not for the slivers of rounding around a lone convex zone."""
MAX_CACHED_GOALS = 2048
"""Goals whose Dijkstra distances are kept (each vehicle of a fleet-sim host has its own: a
thrashing cache re-runs Dijkstra every tick; 2048 x 434 corners is 14 MB at most)."""


@dataclass(frozen=True)
class RouteConfig:
    """How far routes keep from zones (world units)."""

    separation_m: float = 3.0
    """The fleet's separation (the filter's radius_m)."""
    margin: float = 0.2
    """The filter's relative padding (policy.safety.SafetyConfig.margin)."""
    route_margin_m: float = 0.5
    """Routes keep this much more than the filter's zone radius: the filter then rarely has to
    act on a vehicle flying its route (3 m separation: polygons inflated by 1.8 + 0.5 = 2.3 m,
    so gaps narrower than 4.6 m are closed)."""
    mitre_limit: float = 2.0
    """Sharp corners are bevelled beyond this many inflations from the vertex (shapely)."""
    simplify_m: float = 0.05
    """The inflated polygons are simplified to this tolerance (after inflating by as much more,
    so no simplified edge comes nearer than the inflation)."""
    pad_m: float = 0.0
    """Routes keep this much more again: the filter's padding for the position uncertainty,
    sigma_k x the 1-sigma (policy.safety), so a route on plain GNSS runs outside the padded
    radius the filter holds instead of along it (`Router.widened`)."""
    two_way: bool = True
    """Routes prefer ways wide enough for two vehicles to pass each other (`lane_m`): a gap
    between zones that only one vehicle fits through at a time jams when two streams meet in
    it (each waits for the other), so a route around it is taken where one exists within
    `two_way_detour_max` (`Router.next_waypoints`)."""
    two_way_detour_max: float = 1.5
    """A two-way route is flown when it is at most this many times the one-lane route's length
    (from where the vehicle is now); otherwise the one-lane route."""

    def __post_init__(self) -> None:
        for name in ("separation_m", "simplify_m", "mitre_limit"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        for name in ("margin", "route_margin_m", "pad_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.two_way_detour_max) and self.two_way_detour_max >= 1.0):
            raise ValueError(
                f"two_way_detour_max must be finite and >= 1, got {self.two_way_detour_max}"
            )

    @property
    def reach_m(self) -> float:
        """The separation filter's distance from a zone (policy.zone_lines)."""
        return ZONE_CLEARANCE_SHARE * self.separation_m * (1.0 + self.margin)

    @property
    def inflate_m(self) -> float:
        """How far route legs keep from a zone."""
        return self.reach_m + self.pad_m + self.route_margin_m

    @property
    def lane_m(self) -> float:
        """Half the berth two passing vehicles keep, (separation (1 + margin) + sqrt(2) pad_m)
        / 2 (policy.safety.pair_radius_m for two equal sigmas). Two passing vehicles each keep
        the zone clearance (reach_m + pad_m) from their side of a gap and the berth from each
        other, so a gap is two-way when at least 2 (reach_m + pad_m + lane_m) wide: 7.2 m at
        3 m separation and sigma 0, 14 m at sigma 0.5 and sigma_k 4 (`Router.two_way`)."""
        return 0.5 * (self.separation_m * (1.0 + self.margin) + math.sqrt(2.0) * self.pad_m)

    @property
    def sight_m(self) -> float:
        """How far the legs from the vehicle's own position keep (the hysteresis)."""
        return self.reach_m + self.pad_m + 0.5 * self.route_margin_m


@dataclass(frozen=True)
class GoalCheck:
    """A goal against the zone clearance the filter keeps (`Router.check_goal`)."""

    asked_m: np.ndarray
    """(2,) the goal asked for."""
    goal_m: np.ndarray
    """(2,) where to fly: the goal, or the nearest point at the clearance when it is nearer."""
    distance_m: float
    """From the goal to the nearest keep-out zone or the fence."""
    clearance_m: float
    """What the filter keeps from a zone: reach_m + sigma_k x the position 1-sigma."""
    zone: int
    """The nearest keep-out polygon (its index), -1 the fence."""

    @property
    def shift_m(self) -> float:
        """How far `goal_m` is from the goal asked for (0: unchanged)."""
        return float(np.hypot(*(self.goal_m - self.asked_m)))

    def problem(self, tol_m: float, what: str = "a keep-out zone") -> str:
        """Why the goal is refused ("" when not): the nearest point at the clearance lies
        farther than tol_m (the arrival radius) from it. `what` names the zone."""
        if self.shift_m <= tol_m:
            return ""
        return (
            f"the goal is {self.distance_m:.1f} m from {what}, nearer than the "
            f"{self.clearance_m:.1f} m the filter keeps from it; the nearest point outside that "
            f"is {self.shift_m:.1f} m away, beyond the {tol_m:g} m arrival radius"
        )


@dataclass(frozen=True)
class Route:
    """A planned route."""

    waypoints_m: np.ndarray
    """(M, 2) north/east waypoints after the start, the goal last; empty when refused."""
    length_m: float
    """Length from the start along the waypoints (inf when refused or walled off)."""
    reason: str = ""
    """Why there is no route ("" when there is)."""


def _polygons(geom) -> list:
    if geom.is_empty:
        return []
    return list(geom.geoms) if hasattr(geom, "geoms") else [geom]


def _inflate(polys, dist_m: float, cfg: RouteConfig):
    """Union of the polygons grown by at least dist_m (mitre joins), simplified."""
    grown = [
        shapely.Polygon(p).buffer(
            dist_m + cfg.simplify_m, join_style="mitre", mitre_limit=cfg.mitre_limit
        )
        for p in polys
    ]
    return shapely.union_all(grown).simplify(cfg.simplify_m, preserve_topology=True)


class Router:
    """Routes around one set of keep-out zones (and a fence), for any start and goal."""

    def __init__(self, keep_out_m, cfg: RouteConfig | None = None, fence_m=None) -> None:
        """keep_out_m: [(K, 2) polygon vertices, north/east metres]; fence_m: (K, 2) or None."""
        self.cfg = cfg or RouteConfig()
        polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in keep_out_m]
        for p in polys:
            if len(p) < 3 or not np.isfinite(p).all() or not shapely.Polygon(p).is_valid:
                raise ValueError("a keep-out zone must be a simple polygon of 3+ finite vertices")
        self.keep_out_m = polys
        self.fence_m = None if fence_m is None else np.asarray(fence_m, np.float64).reshape(-1, 2)
        zones = shapely.union_all([shapely.Polygon(p) for p in polys]) if polys else None
        self._zones = zones if zones is not None else shapely.Polygon()
        shapely.prepare(self._zones)
        fence = None if self.fence_m is None else shapely.Polygon(self.fence_m)
        if fence is not None and not fence.is_valid:
            raise ValueError("the fence must be a simple polygon")
        self._fence = fence
        if fence is not None:
            shapely.prepare(fence)
        c = self.cfg
        self.free_route = self._free(c.inflate_m)
        """The space route legs keep to: outside the inflated zones, inside the deflated fence."""
        self._route_ok = shapely.buffer(self.free_route, BOUNDARY_TOL_M)
        self._reach_ok = shapely.buffer(self._free(c.sight_m), BOUNDARY_TOL_M)
        shapely.prepare(self._route_ok)
        shapely.prepare(self._reach_ok)
        self.nodes_m, self._nb_a, self._nb_c = self._corners()
        self._graph = self._visibility(self.nodes_m)
        self._goals: OrderedDict = OrderedDict()
        self._inner = None  # the free space PROJECT_IN_M in (`_project`), made when first needed
        self._clear: dict = {}  # the free space at a goal clearance (`check_goal`), by clearance
        self._widened: OrderedDict = OrderedDict()  # routers padded more (`widened`), by pad
        self._fallback: Router | None = None
        """The unpadded router a widened one falls back to where its own routes are walled off
        (a gap the padding closed that the filter still lets through)."""
        self._lane: Router | None = None
        """The two-way router (`two_way`), built when first asked; None: none."""
        self._lane_asked = False
        self._one_lane: tuple = ()

    def two_way(self) -> Router | None:
        """The router whose zones are this one's closed over every gap narrower than two
        passing vehicles need (a morphological closing by `RouteConfig.lane_m`: grown by it,
        then shrunk by it, so the zones keep their outline and only the narrow gaps and
        pockets between or in them are filled), or None (`two_way` off, no zones, nothing
        closed). Its routes are preferred where at most `two_way_detour_max` times as long."""
        if not self._lane_asked:
            self._lane_asked = True
            if self.cfg.two_way and self.keep_out_m:
                c = self.cfg
                lane_m = c.reach_m + c.pad_m + c.lane_m  # half the two-way width
                joins = {"join_style": "mitre", "mitre_limit": c.mitre_limit}
                walls = self._zones
                if self._fence is not None:
                    # the fence's outside closes too: a gap between a zone and the fence is
                    # a lane like a gap between two zones
                    x0, y0, x1, y1 = self._fence.bounds
                    pad = 4.0 * lane_m + 1.0
                    box = shapely.box(x0 - pad, y0 - pad, x1 + pad, y1 + pad)
                    walls = shapely.union(walls, box.difference(self._fence))
                closed = walls.buffer(lane_m, **joins).buffer(-lane_m, **joins)
                if self._fence is not None:
                    closed = closed.intersection(self._fence)
                closed = closed.simplify(c.simplify_m, preserve_topology=True)
                polys = [
                    np.asarray(g.exterior.coords)[:-1]
                    for g in _polygons(closed)
                    if g.geom_type == "Polygon"
                    and len(g.exterior.coords) > 3
                    # a sliver the closing left along the fence's edge is no wall
                    and (g.area > CLOSED_MIN_M2 or g.intersects(self._zones))
                ]
                filled = closed.difference(self._zones)
                if polys and filled.area > CLOSED_MIN_M2:
                    cfg = RouteConfig(**{**c.__dict__, "two_way": False})
                    self._lane = Router(polys, cfg, self.fence_m)
                    gaps = [g for g in _polygons(filled) if g.area > CLOSED_MIN_M2]
                    for g in gaps:
                        shapely.prepare(g)
                    self._one_lane = tuple(gaps)
        return self._lane

    def one_lane_gaps(self) -> tuple:
        """The gaps and pockets (shapely polygons) two passing vehicles do not fit in, as
        `two_way` fills them: one vehicle at a time (policy.lanes decides who goes first)."""
        self.two_way()
        return self._one_lane

    def _clear_rows(self, pos: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """(R,) the position outside the sight band and the goal outside the route's inflation."""
        return shapely.covers(self._reach_ok, shapely.points(pos)) & shapely.covers(
            self._route_ok, shapely.points(goal)
        )

    def _ways(self, pos: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(waypoints (R, 2), route length (R,)) of rows clear here (`_clear_rows`): the goal
        when in sight, else the first corner of the shortest route; length inf (and the goal)
        where the goal is walled off here."""
        seen = self._visible(self._reach_ok, pos, goal)
        way = goal.copy()
        length = np.hypot(goal[:, 0] - pos[:, 0], goal[:, 1] - pos[:, 1])
        blocked = np.flatnonzero(~seen)
        if len(blocked):
            length[blocked] = np.inf
            if len(self.nodes_m):
                way[blocked], length[blocked] = self._corners_for(
                    pos[blocked], goal[blocked], fallback=False
                )
        return way, length

    def _prefer_two_way(self, pos: np.ndarray, goal: np.ndarray):
        """(rows, waypoints) decided by the two-way rule for finite rows clear of the two-way
        router: its waypoint where its route is at most two_way_detour_max times the one-lane
        route, else the one-lane waypoint; rows walled off in both are left out."""
        lane = self.two_way()
        rows = np.zeros(0, np.intp)
        if lane is None or not len(pos):
            return rows, np.zeros((0, 2))
        rows = np.flatnonzero(np.isfinite(pos).all(axis=1) & np.isfinite(goal).all(axis=1))
        if len(rows):
            rows = rows[lane._clear_rows(pos[rows], goal[rows])]
        if not len(rows):
            return rows, np.zeros((0, 2))
        lw, ll = lane._ways(pos[rows], goal[rows])
        nw, nl = self._ways(pos[rows], goal[rows])
        pick = np.isfinite(ll) & (ll <= self.cfg.two_way_detour_max * nl + 1e-9)
        keep = pick | np.isfinite(nl)
        return rows[keep], np.where(pick[:, None], lw, nw)[keep]

    def widened(self, pad_m) -> Router:
        """The router whose routes keep `pad_m` more from every zone (the filter's padding for
        the position uncertainty, sigma_k x the 1-sigma), rounded up to PAD_STEP_M: this one
        at 0, else one built and kept per step. Where its routes are walled off (the padding
        closed a gap), it routes as this one does."""
        pad = float(pad_m) if math.isfinite(pad_m) and pad_m > 0.0 else 0.0
        step = math.ceil(pad / PAD_STEP_M - 1e-9) * PAD_STEP_M
        if step <= 0.0:
            return self
        hit = self._widened.get(step)
        if hit is not None:
            self._widened.move_to_end(step)
            return hit
        cfg = RouteConfig(**{**self.cfg.__dict__, "pad_m": self.cfg.pad_m + step})
        hit = Router(self.keep_out_m, cfg, self.fence_m)
        hit._fallback = self
        self._widened[step] = hit
        if len(self._widened) > MAX_WIDENED:
            self._widened.popitem(last=False)
        return hit

    def _free(self, dist_m: float):
        keep = _inflate(self.keep_out_m, dist_m, self.cfg) if self.keep_out_m else None
        if self._fence is not None:
            inner = self._fence.buffer(
                -dist_m, join_style="mitre", mitre_limit=self.cfg.mitre_limit
            )
            return inner if keep is None else inner.difference(keep)
        if keep is None:
            return shapely.Polygon()
        # unbounded outside: a box well around the zones stands for the plane
        x0, y0, x1, y1 = keep.bounds
        pad = 1e4 + (x1 - x0) + (y1 - y0)
        return shapely.box(x0 - pad, y0 - pad, x1 + pad, y1 + pad).difference(keep)

    def _corners(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(V, 2) corners of the free space a shortest path can bend around: those where the
        free side's angle is above 180 degrees (the box around an unfenced plan excluded); and
        each one's neighbours along its ring (V, 2) twice, for the tangent test."""
        out, nb_a, nb_c = [], [], []
        for poly in _polygons(self.free_route):
            rings = list(poly.interiors)
            if self._fence is not None:
                rings.append(poly.exterior)
            for ring in rings:
                v = np.asarray(ring.coords)[:-1]
                if len(v) < 3:
                    continue
                a, c = np.roll(v, 1, axis=0), np.roll(v, -1, axis=0)
                ua = (a - v) / np.maximum(np.linalg.norm(a - v, axis=1), 1e-12)[:, None]
                uc = (c - v) / np.maximum(np.linalg.norm(c - v, axis=1), 1e-12)[:, None]
                bis = ua + uc
                n = np.linalg.norm(bis, axis=1)
                probe = v + 1e-3 * bis / np.maximum(n, 1e-12)[:, None]
                # inside the narrow angle a-v-c lies the obstacle at a corner worth keeping
                keep = ~shapely.contains_xy(poly, probe[:, 0], probe[:, 1]) & (n > 1e-9)
                out.append(v[keep])
                nb_a.append(a[keep])
                nb_c.append(c[keep])
        if not out:
            return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2))
        return np.concatenate(out), np.concatenate(nb_a), np.concatenate(nb_c)

    def _tangent(self, k: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(M,) the line through corner k[m] along d[m] touches the obstacle there without
        entering it (both ring neighbours on one side): only such legs can be on a shortest
        path (the reduced visibility graph), so the others need no geometry check."""
        u = self.nodes_m[k]
        a, c = self._nb_a[k] - u, self._nb_c[k] - u
        s1 = d[:, 0] * a[:, 1] - d[:, 1] * a[:, 0]
        s2 = d[:, 0] * c[:, 1] - d[:, 1] * c[:, 0]
        return s1 * s2 >= -1e-9 * (np.abs(s1) + np.abs(s2) + 1e-12)

    def _nearest_seen(self, here: np.ndarray, dist: np.ndarray) -> int:
        """The corner with the least |here - corner| + dist[corner] among those `here` sees
        (-1: none): candidates in that order, checked a few at a time, so the first visible
        one is the answer and most calls check a few."""
        nodes = self.nodes_m
        if not len(nodes):
            return -1
        d = nodes - here
        cost = np.hypot(d[:, 0], d[:, 1]) + dist
        # no tangent test here: a vehicle a little inside the route's inflation (it flies in
        # the sight region) sees legs along the boundary that are not quite tangent
        cand = np.flatnonzero(np.isfinite(cost))
        cand = cand[np.argsort(cost[cand], kind="stable")]
        for lo in range(0, len(cand), 8):
            chunk = cand[lo : lo + 8]
            seen = self._visible(
                self._reach_ok, np.broadcast_to(here, (len(chunk), 2)), nodes[chunk]
            )
            if seen.any():
                return int(chunk[np.argmax(seen)])
        return -1

    def _visible(self, region, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(M,) segment a[i] -> b[i] stays within `region`."""
        if len(a) == 0:
            return np.zeros(0, bool)
        segs = shapely.linestrings(np.stack([a, b], axis=1))
        ok = shapely.covers(region, segs)
        same = np.all(np.abs(a - b) < 1e-12, axis=1)  # a point: no line to check
        if same.any():
            ok[same] = shapely.covers(region, shapely.points(a[same]))
        return ok

    def _visibility(self, nodes: np.ndarray) -> np.ndarray:
        """(V, V) leg lengths between corners that see each other (inf: they do not)."""
        v = len(nodes)
        g = np.full((v, v), np.inf)
        if v < 2:
            return g
        i, j = np.triu_indices(v, 1)
        d_ij = nodes[j] - nodes[i]
        tan = self._tangent(i, d_ij) & self._tangent(j, d_ij)
        i, j = i[tan], j[tan]
        ok = self._visible(self._route_ok, nodes[i], nodes[j])
        d = np.hypot(*(nodes[i] - nodes[j]).T)
        g[i[ok], j[ok]] = d[ok]
        g[j[ok], i[ok]] = d[ok]
        return g

    def edge_distance_m(self, pts_m) -> np.ndarray:
        """(N,) each (N, 2) point's distance to the nearest keep-out zone or the fence's edge:
        0 inside a zone or outside the fence (the calm-tick rule, agent/calm.py)."""
        pts = shapely.points(np.asarray(pts_m, np.float64).reshape(-1, 2))
        out = np.full(len(pts), np.inf)
        if not self._zones.is_empty:
            out = np.minimum(out, shapely.distance(self._zones, pts))
        if self._fence is not None:
            inside = shapely.covers(self._fence, pts)
            out = np.minimum(
                out, np.where(inside, shapely.distance(self._fence.exterior, pts), 0.0)
            )
        return out

    def in_sight_space(self, pt) -> bool:
        """Whether a point lies where route legs may start: outside every zone's sight band
        (`RouteConfig.sight_m`) and inside the fence deflated by it."""
        return bool(self._reach_ok.covers(shapely.Point(np.asarray(pt, np.float64)[:2])))

    def inside_zone(self, pt) -> bool:
        """Whether a point is inside a keep-out zone or outside the fence."""
        p = shapely.Point(float(pt[0]), float(pt[1]))
        if self._zones.covers(p):
            return True
        return self._fence is not None and not self._fence.covers(p)

    def _project(self, pt: np.ndarray, region) -> np.ndarray:
        """`pt` when `region` covers it, else the nearest point of the route's free space,
        PROJECT_IN_M inside it."""
        p = shapely.Point(float(pt[0]), float(pt[1]))
        if region.covers(p) or self.free_route.is_empty:
            return pt
        if self._inner is None:
            inner = self.free_route.buffer(-PROJECT_IN_M)
            self._inner = self.free_route if inner.is_empty else inner
        q = shapely.shortest_line(self._inner, p).coords[0]
        return np.array([q[0], q[1]])

    def _to_goal(self, goal: np.ndarray):
        """(distance to the goal per node, next node per node (-1: the goal), entry point of
        the goal) for one goal, cached."""
        key = (round(float(goal[0]), 6), round(float(goal[1]), 6))
        hit = self._goals.get(key)
        if hit is not None:
            self._goals.move_to_end(key)
            return hit
        entry = self._project(goal, self._route_ok)
        nodes = self.nodes_m
        v = len(nodes)
        seen = self._visible(self._route_ok, nodes, np.broadcast_to(entry, nodes.shape))
        w = np.full((v + 1, v + 1), np.inf)
        w[:v, :v] = self._graph
        leg = np.hypot(*(nodes - entry).T)
        w[:v, v][seen] = leg[seen]
        w[v, :v][seen] = leg[seen]
        w[~np.isfinite(w)] = 0.0  # csgraph: 0 = no edge (no two corners coincide)
        dist, pred = dijkstra(csr_matrix(w), directed=False, indices=v, return_predecessors=True)
        hit = (dist[:v], np.where(pred[:v] == v, -1, pred[:v]), entry)
        self._goals[key] = hit
        if len(self._goals) > MAX_CACHED_GOALS:
            self._goals.popitem(last=False)
        return hit

    def refusal(self, goal) -> str:
        """Why a route to `goal` is refused ("" when it is not)."""
        g = np.asarray(goal, dtype=np.float64).reshape(2)
        if not np.isfinite(g).all():
            return "the goal is not a finite north/east position"
        p = shapely.Point(float(g[0]), float(g[1]))
        if self._zones.covers(p):
            return "the goal is inside a keep-out zone"
        if self._fence is not None and not self._fence.covers(p):
            return "the goal is outside the fence"
        return ""

    def check_goal(self, goal, pad_m: float = 0.0) -> GoalCheck:
        """`goal` against the clearance the filter keeps from every zone and the fence,
        reach_m + pad_m (pad_m: sigma_k x the position 1-sigma, as policy.safety pads zones):
        a goal nearer than that is moved to the nearest point outside it (PROJECT_IN_M in), so
        that the vehicle can arrive; the caller refuses it when that point lies beyond its
        arrival radius (`GoalCheck.problem`). A goal inside a zone or outside the fence is left
        as it is (`refusal`)."""
        g = np.asarray(goal, dtype=np.float64).reshape(2)
        pad = float(pad_m) if math.isfinite(pad_m) and pad_m > 0.0 else 0.0
        clearance = self.cfg.reach_m + pad
        p = shapely.Point(float(g[0]), float(g[1]))
        dists = [shapely.Polygon(z).distance(p) for z in self.keep_out_m]
        if self._fence is not None:
            dists.append(self._fence.exterior.distance(p))
        if not dists or self.refusal(g):
            return GoalCheck(g, g, math.inf if not dists else 0.0, clearance, -1)
        k = int(np.argmin(dists))
        d = float(dists[k])
        zone = k if k < len(self.keep_out_m) else -1
        if d >= clearance:
            return GoalCheck(g, g, d, clearance, zone)
        key = round(clearance, 3)
        free = self._clear.get(key)
        if free is None:
            free = self._free(clearance)
            inner = free.buffer(-PROJECT_IN_M)
            free = free if inner.is_empty else inner
            if len(self._clear) >= 8:  # a few sigmas at a time
                self._clear.clear()
            self._clear[key] = free
        if free.is_empty:
            return GoalCheck(g, g, d, clearance, zone)
        q = shapely.shortest_line(free, p).coords[0]
        return GoalCheck(g, np.array([q[0], q[1]]), d, clearance, zone)

    def next_waypoint(self, pos, goal, pad_m: float = 0.0) -> np.ndarray:
        """Where to fly now (2,): see the module docstring; pad_m: the routes keep that much
        more (`widened`). The goal itself when there is no route (refused or walled off)."""
        if pad_m:
            wide = self.widened(pad_m)
            if wide is not self:
                return wide.next_waypoint(pos, goal)
        pos = np.asarray(pos, dtype=np.float64).reshape(2)
        goal = np.asarray(goal, dtype=np.float64).reshape(2)
        if self.refusal(goal):
            return goal
        rows, ways = self._prefer_two_way(pos[None], goal[None])
        if len(rows):
            return ways[0]
        start = self._project(pos, self._reach_ok)
        if start is not pos:
            return start
        dist, _, entry = self._to_goal(goal)
        if self._visible(self._reach_ok, pos[None], entry[None])[0]:
            return goal if entry is goal else entry
        k = self._nearest_seen(pos, dist)
        if k >= 0:
            return self._past_corner(np.array([k]), pos[None], goal)[0]
        return goal if self._fallback is None else self._fallback.next_waypoint(pos, goal)

    def _past_corner(self, ks: np.ndarray, pos: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """The waypoints (R, 2) of R rows at `pos` (R, 2) that chose corners `ks` (R,) on the
        way to one `goal`: the corner, or its successor on the route (the goal's entry after
        the last) where the row is within CORNER_PASSED_M of it."""
        nodes = self.nodes_m
        out = nodes[ks].copy()
        near = np.hypot(*(out - pos).T) <= CORNER_PASSED_M
        if near.any():
            _, nxt, entry = self._to_goal(goal)
            after = nxt[ks[near]]
            out[near] = np.where((after >= 0)[:, None], nodes[np.maximum(after, 0)], entry)
        return out

    def next_waypoints(self, pos_m, goal_m, pad_m=None) -> np.ndarray:
        """`next_waypoint` of N rows (N, 2), the common case at once: a row whose position is
        clear, whose goal is clear of the route's inflation and in sight flies at its goal (one
        vectorised check for all of them); the others one by one. pad_m: None, one pad or (N,)
        pads (`widened`): rows are routed by the router of their pad's step."""
        pos = np.asarray(pos_m, dtype=np.float64).reshape(-1, 2)
        goal = np.asarray(goal_m, dtype=np.float64).reshape(-1, 2)
        if pad_m is not None:
            pads = np.broadcast_to(np.asarray(pad_m, dtype=np.float64), (len(pos),))
            bad = ~np.isfinite(pads) | (pads <= 0.0)
            steps = np.where(bad, 0.0, np.ceil(np.where(bad, 0.0, pads) / PAD_STEP_M - 1e-9))
            if steps.any():
                out = np.empty_like(goal)
                for step in np.unique(steps):
                    rows = steps == step
                    out[rows] = self.widened(step * PAD_STEP_M).next_waypoints(
                        pos[rows], goal[rows]
                    )
                return out
        out = goal.copy()
        if not len(pos):
            return out
        finite = np.array(np.isfinite(pos).all(axis=1) & np.isfinite(goal).all(axis=1))
        rows, ways = self._prefer_two_way(pos, goal)
        if len(rows):
            out[rows] = ways
            finite[rows] = False  # decided
        clear = np.array(finite)  # position clear, goal clear of the inflation (its own entry)
        if clear.any():
            f = np.flatnonzero(clear)
            clear[f] = shapely.covers(self._reach_ok, shapely.points(pos[f])) & shapely.covers(
                self._route_ok, shapely.points(goal[f])
            )
        seen = np.zeros(len(pos), bool)
        if clear.any():
            f = np.flatnonzero(clear)
            seen[f] = self._visible(self._reach_ok, pos[f], goal[f])
        blocked = np.flatnonzero(clear & ~seen)
        if len(blocked) and len(self.nodes_m):
            out[blocked] = self._corners_for(pos[blocked], goal[blocked])
        elif len(blocked) and self._fallback is not None:
            out[blocked] = self._fallback.next_waypoints(pos[blocked], goal[blocked])
        for i in np.flatnonzero(finite & ~clear):  # led out, refused, goal near a zone: rare
            out[i] = self.next_waypoint(pos[i], goal[i])
        return out

    def _corners_for(self, pos: np.ndarray, goal: np.ndarray, fallback: bool = True):
        """`_nearest_seen` of R rows whose goal is out of sight, at once: every row's corners in
        order of route length, the k-th candidates of the unresolved rows checked together,
        k = 0, 1, ... (most rows resolve at the first or second). Unresolved: the goal, or the
        fallback router's waypoint. `fallback` False: (waypoints, route lengths), inf for the
        unresolved."""
        nodes = self.nodes_m
        dist = np.stack([self._to_goal(g)[0] for g in goal])  # (R, V), cached per goal
        d = nodes[None] - pos[:, None]
        cost = np.hypot(d[..., 0], d[..., 1]) + dist
        order = np.argsort(cost, axis=1, kind="stable")
        out = goal.copy()
        length = np.full(len(pos), np.inf)
        chosen = np.full(len(pos), -1)
        todo = np.arange(len(pos))
        for rank in range(nodes.shape[0]):
            cand = order[todo, rank]
            live = np.isfinite(cost[todo, cand])
            todo, cand = todo[live], cand[live]
            if not len(todo):
                break
            ok = self._visible(self._reach_ok, pos[todo], nodes[cand])
            out[todo[ok]] = nodes[cand[ok]]
            chosen[todo[ok]] = cand[ok]
            length[todo[ok]] = cost[todo[ok], cand[ok]]
            todo = todo[~ok]
            if not len(todo):
                break
        if not fallback:
            return out, length
        near = np.flatnonzero((chosen >= 0) & (np.hypot(*(out - pos).T) <= CORNER_PASSED_M))
        for i in near:  # reached its corner: on to the next (`_past_corner`)
            out[i] = self._past_corner(chosen[i : i + 1], pos[i : i + 1], goal[i])[0]
        if len(todo) and self._fallback is not None:  # walled off here: route unpadded
            out[todo] = self._fallback.next_waypoints(pos[todo], goal[todo])
        return out

    def plan(self, start, goal, pad_m: float = 0.0) -> Route:
        """The whole route from `start` to `goal`: what `next_waypoint` leads through (with
        the same `pad_m`)."""
        if pad_m:
            wide = self.widened(pad_m)
            if wide is not self:
                return wide.plan(start, goal)
        start = np.asarray(start, dtype=np.float64).reshape(2)
        goal = np.asarray(goal, dtype=np.float64).reshape(2)
        why = self.refusal(goal)
        if why:
            return Route(np.zeros((0, 2)), math.inf, why)
        route = self._plan_one_lane(start, goal)
        lane = self.two_way()
        if lane is not None and lane._clear_rows(start[None], goal[None])[0]:
            two_way = lane.plan(start, goal)
            if two_way.length_m <= self.cfg.two_way_detour_max * route.length_m + 1e-9:
                return two_way
        return route

    def _plan_one_lane(self, start: np.ndarray, goal: np.ndarray) -> Route:
        """`plan` on this router's own routes (no two-way preference)."""
        pts = [start]
        first = self._project(start, self._reach_ok)
        if first is not start:
            pts.append(first)
        dist, nxt, entry = self._to_goal(goal)
        here = pts[-1]
        if self._visible(self._reach_ok, here[None], entry[None])[0]:
            tail = [entry]
        else:
            k = self._nearest_seen(here, dist)
            if k < 0 and self._fallback is not None:
                return self._fallback.plan(start, goal)
            if k < 0:
                return Route(np.zeros((0, 2)), math.inf, "no route: the goal is walled off")
            tail = []
            while k >= 0 and len(tail) <= len(self.nodes_m):
                tail.append(self.nodes_m[k])
                k = int(nxt[k])
            tail.append(entry)
        pts += tail
        if np.hypot(*(entry - goal)) > 0.0:
            pts.append(goal)
        way = np.array(pts)
        length = float(np.hypot(*np.diff(way, axis=0).T).sum())
        return Route(way[1:], length)


def zones_for(safety_cfg, keep_out_m, fence_m=None):
    """(ZoneSet, Router) for a filter config (policy.safety.SafetyConfig: radius_m, margin):
    the filter keeps ZONE_CLEARANCE_SHARE x radius_m (1 + margin) from every zone edge, routes
    that plus RouteConfig.route_margin_m; (None, None) without polygons or a fence. One rule for
    the runtime, the C wrapper, the agents' guidance and `covey eval`."""
    from policy.zone_lines import ZoneSet

    polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in keep_out_m or ()]
    if not polys and fence_m is None:
        return None, None
    route = RouteConfig(float(safety_cfg.radius_m), float(safety_cfg.margin))
    zones = ZoneSet.of(polys, route.reach_m, fence_m=fence_m)
    return zones, Router(polys, route, fence_m)
