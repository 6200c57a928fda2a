"""Keep-out zones as static constraints of the separation filter: ORCA's obstacle half-planes.

For each zone edge near the vehicle, the velocities that would bring it within `radius_m` of the
edge within `time_horizon_s` form a truncated cone (the edge's velocity obstacle, van den Berg et
al. 2011, section 5.3; the construction is RVO2's `Agent::computeNewVelocity`, obstacle part).
Its half-plane goes into policy.safety's LP *before* the neighbours' and is hard: when the
neighbours' lines cannot all be met, only theirs are relaxed (`orca_lp._lp3` with `n_hard`), so
a crowd can never push a vehicle into a zone. A static edge takes the whole correction (it does
not move), and v = 0 always meets every edge line of a vehicle outside the radius, so the hard
lines alone are always feasible.

Polygons are (north, east) metres; each keep-out polygon is stored counter-clockwise in (n, e)
(its inside to the left of every edge), the fence clockwise (its outside to the left), so one
rule serves both: an edge constrains a vehicle on its right, the side it faces. Concave zones
work: an edge whose end vertex is reflex leaves that side to its neighbour edge (RVO2's
convexity rules). The C twin is firmware/covey_zones.c (parity tested, tests/test_zones_filter.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EPS = 1e-9
ZONE_CLEARANCE_SHARE = 0.5
"""A vehicle keeps this share of the padded separation, radius_m (1 + margin), from a zone edge
(3 m -> 1.8 m): a zone is held off like the midpoint to a neighbour. `covey eval` counts an entry
when a true position comes within ZONE_ENTRY_SHARE x radius_m (1.5 m) of a zone, so the margin
absorbs lag and discrete time as it does between vehicles."""
ZONE_ENTRY_SHARE = 0.5
"""A true position within this share of the separation (1.5 m at 3 m) of a zone is an entry."""
MAX_ZONE_EDGES = 32
"""Nearest facing edges that get a line per call (COVEY_MAX_ZONE_EDGES in C): bounds the LP."""
ZONE_RECOVER_S = 0.5
"""A vehicle found within the radius of an edge (gusts, lag, a jump of its estimate) must move
away from it at (radius - distance) / ZONE_RECOVER_S, at most ZONE_MAX_PUSH_SHARE of its speed
limit (RVO2 only forbids moving closer: a gust the loop does not reject would carry it in). A
steady gust g towards the zone holds the vehicle g x ZONE_RECOVER_S inside the radius while g is
below the cap: with 1 s and half the speed (the first values) a 2-sigma gust of realistic
vehicles (0.4-0.6 m/s) beat the cap and carried a vehicle 1.4 m into its 3.3 m padded radius
(seed 11, docs/sky.md); 0.5 s and the whole speed hold it 0.2-0.3 m in."""
ZONE_MAX_PUSH_SHARE = 1.0
ZONE_TIME_HORIZON_S = 2.0
"""How far ahead zone edges are looked at (RVO2's timeHorizonObst): shorter than the neighbours'
4 s, as an edge does not come towards the vehicle; a vehicle flying along an edge is not slowed,
one flying at it starts to turn 2 s x speed + radius out (3.8 m at 1 m/s)."""


def _orient(vertices, ccw: bool) -> np.ndarray:
    """(K, 2) float64 vertices without a closing repeat or repeated neighbours, turned so that
    the signed area in (n, e) is positive (ccw) or negative; ValueError for a bad polygon."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 2:
        raise ValueError(f"a zone polygon must be (K, 2) north/east vertices, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("a zone polygon has a non-finite vertex")
    keep = np.ones(len(v), bool)
    keep[1:] = np.any(v[1:] != v[:-1], axis=1)
    v = v[keep]
    if len(v) > 1 and np.all(v[0] == v[-1]):
        v = v[:-1]
    if len(v) < 3:
        raise ValueError(f"a zone polygon needs 3 distinct vertices, got {len(v)}")
    area2 = float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
    if area2 == 0.0:
        raise ValueError("a zone polygon has no area")
    import shapely  # the runtime's geometry library (policy.routes); only here, at setup

    if not shapely.LinearRing(v).is_simple:
        raise ValueError("a zone polygon crosses itself (its edges must not intersect)")
    return v if (area2 > 0) == ccw else v[::-1].copy()


@dataclass(frozen=True)
class ZoneSet:
    """Zone edges prepared for the filter (`ZoneSet.of`): every polygon's vertices in one array,
    with each vertex's next / previous vertex, the unit direction of its outgoing edge and
    whether it is convex (RVO2's Obstacle)."""

    points: np.ndarray
    """(V, 2) vertices, north/east metres."""
    next_idx: np.ndarray
    """(V,) the vertex after each, along its polygon."""
    prev_idx: np.ndarray
    """(V,) the vertex before each."""
    unit_dir: np.ndarray
    """(V, 2) unit vector from each vertex to the next."""
    convex: np.ndarray
    """(V,) the vertex is convex (on the side the edges face)."""
    radius_m: float
    """Distance kept from every edge."""
    time_horizon_s: float
    """How far ahead edges are looked at (tau_obst)."""
    polygons: tuple
    """The polygons as given, oriented: keep-out ones (K, 2) counter-clockwise, then the fence
    (if any) clockwise."""
    n_keep_out: int
    """How many of `polygons` are keep-out zones (the fence, if any, follows)."""

    @classmethod
    def of(
        cls,
        keep_out_m,
        radius_m: float,
        time_horizon_s: float = ZONE_TIME_HORIZON_S,
        fence_m=None,
    ) -> ZoneSet:
        """Keep-out polygons [(K, 2) arrays, north/east metres] and an optional inclusion fence
        (K, 2), kept radius_m away from."""
        if not (math.isfinite(radius_m) and radius_m > 0):
            raise ValueError(f"radius_m must be finite and > 0, got {radius_m}")
        if not (math.isfinite(time_horizon_s) and time_horizon_s > 0):
            raise ValueError(f"time_horizon_s must be finite and > 0, got {time_horizon_s}")
        polys = [_orient(p, ccw=True) for p in keep_out_m]
        n_keep = len(polys)
        if fence_m is not None:
            polys.append(_orient(fence_m, ccw=False))
        pts, nxt, prv = [], [], []
        base = 0
        for p in polys:
            k = len(p)
            idx = np.arange(k)
            pts.append(p)
            nxt.append(base + (idx + 1) % k)
            prv.append(base + (idx - 1) % k)
            base += k
        points = np.concatenate(pts) if pts else np.zeros((0, 2))
        next_idx = np.concatenate(nxt) if nxt else np.zeros(0, np.int64)
        prev_idx = np.concatenate(prv) if prv else np.zeros(0, np.int64)
        d = points[next_idx] - points
        unit = d / np.maximum(np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]), EPS)[:, None]
        # convex: the next vertex is not to the right of prev -> this (RVO2's leftOf >= 0)
        a, b, c = points[prev_idx], points, points[next_idx]
        left_of = (a[:, 0] - c[:, 0]) * (b[:, 1] - a[:, 1]) - (a[:, 1] - c[:, 1]) * (
            b[:, 0] - a[:, 0]
        )
        return cls(
            points,
            next_idx,
            prev_idx,
            unit,
            left_of >= 0.0,
            float(radius_m),
            float(time_horizon_s),
            tuple(polys),
            n_keep,
        )

    def __len__(self) -> int:
        return len(self.points)

    def nearby_edges(self, pos_m, max_speed_m_s: float, pad_m: float = 0.0) -> list[int]:
        """Edges (by start vertex) that face the vehicle and lie within tau vmax + radius +
        pad_m, nearest first (ties by index: the order the C twin sorts in)."""
        if not len(self.points):
            return []
        px, py = float(pos_m[0]), float(pos_m[1])
        a = self.points
        b = a[self.next_idx]
        # the vehicle is right of the edge a -> b: det(a - p, b - a) < 0 (RVO2's leftOf)
        ax, ay = a[:, 0] - px, a[:, 1] - py
        ex, ey = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        left_of = ax * ey - ay * ex
        # squared distance from p to the segment: s = clamp((p - a).e / |e|^2)
        ee = ex * ex + ey * ey
        s = np.clip((-ax * ex - ay * ey) / ee, 0.0, 1.0)
        dx, dy = ax + s * ex, ay + s * ey
        dist_sq = dx * dx + dy * dy
        reach = self.time_horizon_s * max_speed_m_s + self.radius_m + pad_m
        ok = np.flatnonzero((left_of < 0.0) & (dist_sq < reach * reach))
        return ok[np.argsort(dist_sq[ok], kind="stable")][:MAX_ZONE_EDGES].tolist()

    def lines(self, pos_m, vel_m_s, max_speed_m_s: float, pad_m: float = 0.0) -> list:
        """The vehicle's obstacle half-planes [((point_n, point_e), (dir_n, dir_e))] in absolute
        velocity space: velocities v with det(dir, point - v) <= 0 keep it radius_m + pad_m off
        every edge for time_horizon_s. `vel_m_s` (the current velocity) picks the side of each
        cone. pad_m: the position estimate's uncertainty times sigma_k (policy.safety: the
        filter pads zones as it pads pairs, sigma_k x the own 1-sigma)."""
        if not (pad_m >= 0.0):
            pad_m = 0.0
        edges = self.nearby_edges(pos_m, max_speed_m_s, pad_m)
        if not edges:
            return []
        r = self.radius_m + pad_m
        push = ZONE_MAX_PUSH_SHARE * max_speed_m_s
        return obstacle_lines(self, float(pos_m[0]), float(pos_m[1]), vel_m_s, edges, r, push)

    def _near_rows(self, pos_m: np.ndarray, max_speed_m_s: float, pads: np.ndarray) -> np.ndarray:
        """(N,) some edge lies within tau vmax + radius + pad of the row (all rows at once)."""
        if not len(self.points) or not len(pos_m):
            return np.zeros(len(pos_m), bool)
        a = self.points
        e = a[self.next_idx] - a
        ee = (e * e).sum(axis=1)
        rel = pos_m[:, None, :] - a[None]
        t = np.clip((rel * e[None]).sum(axis=2) / ee[None], 0.0, 1.0)
        d = rel - t[..., None] * e[None]
        dist_sq = (d * d).sum(axis=2).min(axis=1)
        reach = self.time_horizon_s * max_speed_m_s + self.radius_m + pads
        return dist_sq < reach * reach

    def lines_rows(
        self, pos_m, vel_m_s, pref_m_s, need: np.ndarray, max_speed_m_s: float, pad_m=None
    ):
        """`lines` of N vehicles (rows of (N, 2) arrays), pad_m (N,) or None; marks in `need`
        (N,) bool the rows whose preferred velocity breaks one of them (their LP must run)."""
        n = len(pos_m)
        pads = np.zeros(n) if pad_m is None else np.broadcast_to(np.asarray(pad_m, float), (n,))
        near = self._near_rows(np.asarray(pos_m, float).reshape(-1, 2), max_speed_m_s, pads)
        out: list = []
        for i in range(n):
            if not near[i]:  # no edge within reach: no line (most rows, most ticks)
                out.append([])
                continue
            ls = self.lines(pos_m[i], vel_m_s[i], max_speed_m_s, float(pads[i]))
            out.append(ls)
            if not need[i]:
                vx, vy = float(pref_m_s[i][0]), float(pref_m_s[i][1])
                need[i] = any(dx * (py - vy) - dy * (px - vx) > 0.0 for (px, py), (dx, dy) in ls)
        return out


def _push(r: float, d: float, cap: float) -> float:
    """The speed away from an edge found at d < r: (r - d) / ZONE_RECOVER_S, at most cap."""
    k = (r - d) / ZONE_RECOVER_S
    return cap if k > cap else k


def _normalize(x: float, y: float) -> tuple[float, float]:
    n = math.sqrt(x * x + y * y)
    n = EPS if n < EPS else n
    return x / n, y / n


def obstacle_lines(
    zones: ZoneSet, px: float, py: float, vel_m_s, edges: list[int], r: float, push_cap: float
) -> list:
    """RVO2's obstacle lines for `edges` (nearest first), in Python floats; see ZoneSet.lines.

    With p1, p2 the edge's ends relative to the vehicle, r the radius and 1/tau:
      already covered by an earlier line (both cut-off points beyond it by r / tau): nothing;
      within r of the edge (or an end) at distance d: v must move away from it at
      s = min((r - d) / ZONE_RECOVER_S, push_cap), a line through s times the unit normal
      (RVO2's, through 0, only forbids approaching);
      else the truncated cone between the legs (tangents to the discs at the ends, or the
      neighbour edge where the leg would point into the polygon) and the cut-off segment
      p1 / tau -> p2 / tau: the line nearest to v among its left cut-off disc, right disc,
      the cut-off line and the two legs, pushed r / tau outwards.
    """
    pts, nxt, prv = zones.points.tolist(), zones.next_idx.tolist(), zones.prev_idx.tolist()
    udir, convex = zones.unit_dir.tolist(), zones.convex.tolist()
    r_sq = r * r
    inv_tau = 1.0 / zones.time_horizon_s
    vx, vy = float(vel_m_s[0]), float(vel_m_s[1])
    lines: list = []
    for e in edges:
        o1, o2 = e, nxt[e]
        r1x, r1y = pts[o1][0] - px, pts[o1][1] - py
        r2x, r2y = pts[o2][0] - px, pts[o2][1] - py
        covered = False
        for (qx, qy), (dx, dy) in lines:
            # det(a, b) = a_x b_y - a_y b_x; the cut-off point a = p / tau beyond the line by r / tau
            c1 = (inv_tau * r1x - qx) * dy - (inv_tau * r1y - qy) * dx - inv_tau * r
            c2 = (inv_tau * r2x - qx) * dy - (inv_tau * r2y - qy) * dx - inv_tau * r
            if c1 >= -EPS and c2 >= -EPS:
                covered = True
                break
        if covered:
            continue
        dist_sq1 = r1x * r1x + r1y * r1y
        dist_sq2 = r2x * r2x + r2y * r2y
        ovx, ovy = pts[o2][0] - pts[o1][0], pts[o2][1] - pts[o1][1]
        s = (-r1x * ovx - r1y * ovy) / (ovx * ovx + ovy * ovy)
        lx_, ly_ = -r1x - s * ovx, -r1y - s * ovy
        dist_sq_line = lx_ * lx_ + ly_ * ly_
        if s < 0.0 and dist_sq1 <= r_sq:
            # within r of the left vertex: away from it (a reflex one: its edges do it)
            if convex[o1] and dist_sq1 > 0.0:
                dx, dy = _normalize(-r1y, r1x)
                k = _push(r, math.sqrt(dist_sq1), push_cap)
                lines.append(((-k * dy, k * dx), (dx, dy)))  # point -k r1 / |r1|
            continue
        if s > 1.0 and dist_sq2 <= r_sq:
            # the right vertex; the next edge covers it unless the vehicle is beside this one
            if convex[o2] and r2x * udir[o2][1] - r2y * udir[o2][0] >= 0.0 and dist_sq2 > 0.0:
                dx, dy = _normalize(-r2y, r2x)
                k = _push(r, math.sqrt(dist_sq2), push_cap)
                lines.append(((-k * dy, k * dx), (dx, dy)))
            continue
        if 0.0 <= s <= 1.0 and dist_sq_line <= r_sq:
            # within r of the edge itself: away from it, along the outward normal (e_y, -e_x)
            ex, ey = udir[o1]
            k = _push(r, math.sqrt(dist_sq_line), push_cap)
            lines.append(((k * ey, -k * ex), (-ex, -ey)))
            continue
        # no collision: the legs; seen obliquely, both come from one vertex
        if s < 0.0 and dist_sq_line <= r_sq:
            if not convex[o1]:
                continue
            o2 = o1
            leg1 = math.sqrt(dist_sq1 - r_sq)
            left = (
                (r1x * leg1 - r1y * r) / dist_sq1,
                (r1x * r + r1y * leg1) / dist_sq1,
            )
            right = (
                (r1x * leg1 + r1y * r) / dist_sq1,
                (-r1x * r + r1y * leg1) / dist_sq1,
            )
        elif s > 1.0 and dist_sq_line <= r_sq:
            if not convex[o2]:
                continue
            o1 = o2
            leg2 = math.sqrt(dist_sq2 - r_sq)
            left = (
                (r2x * leg2 - r2y * r) / dist_sq2,
                (r2x * r + r2y * leg2) / dist_sq2,
            )
            right = (
                (r2x * leg2 + r2y * r) / dist_sq2,
                (-r2x * r + r2y * leg2) / dist_sq2,
            )
        else:
            if convex[o1]:
                leg1 = math.sqrt(dist_sq1 - r_sq)
                left = (
                    (r1x * leg1 - r1y * r) / dist_sq1,
                    (r1x * r + r1y * leg1) / dist_sq1,
                )
            else:  # a reflex left vertex: the left leg extends the cut-off line
                left = (-udir[o1][0], -udir[o1][1])
            if convex[o2]:
                leg2 = math.sqrt(dist_sq2 - r_sq)
                right = (
                    (r2x * leg2 + r2y * r) / dist_sq2,
                    (-r2x * r + r2y * leg2) / dist_sq2,
                )
            else:
                right = (udir[o1][0], udir[o1][1])
        # a leg never points into the neighbouring edge at a convex vertex: take that edge's
        # cut-off line instead, and add no line if v projects onto such a foreign leg
        lnb = prv[o1]
        left_foreign = right_foreign = False
        if convex[o1] and left[0] * -udir[lnb][1] - left[1] * -udir[lnb][0] >= 0.0:
            left = (-udir[lnb][0], -udir[lnb][1])
            left_foreign = True
        if convex[o2] and right[0] * udir[o2][1] - right[1] * udir[o2][0] <= 0.0:
            right = (udir[o2][0], udir[o2][1])
            right_foreign = True
        lcx, lcy = inv_tau * (pts[o1][0] - px), inv_tau * (pts[o1][1] - py)
        rcx, rcy = inv_tau * (pts[o2][0] - px), inv_tau * (pts[o2][1] - py)
        cvx, cvy = rcx - lcx, rcy - lcy
        same = o1 == o2
        t = 0.5 if same else ((vx - lcx) * cvx + (vy - lcy) * cvy) / (cvx * cvx + cvy * cvy)
        t_left = (vx - lcx) * left[0] + (vy - lcy) * left[1]
        t_right = (vx - rcx) * right[0] + (vy - rcy) * right[1]
        if (t < 0.0 and t_left < 0.0) or (same and t_left < 0.0 and t_right < 0.0):
            ux, uy = _normalize(vx - lcx, vy - lcy)  # the left cut-off disc
            lines.append(((lcx + r * inv_tau * ux, lcy + r * inv_tau * uy), (uy, -ux)))
            continue
        if t > 1.0 and t_right < 0.0:
            ux, uy = _normalize(vx - rcx, vy - rcy)  # the right cut-off disc
            lines.append(((rcx + r * inv_tau * ux, rcy + r * inv_tau * uy), (uy, -ux)))
            continue
        inf = math.inf
        if t < 0.0 or t > 1.0 or same:
            d_cut = inf
        else:
            wx, wy = vx - (lcx + t * cvx), vy - (lcy + t * cvy)
            d_cut = wx * wx + wy * wy
        if t_left < 0.0:
            d_left = inf
        else:
            wx, wy = vx - (lcx + t_left * left[0]), vy - (lcy + t_left * left[1])
            d_left = wx * wx + wy * wy
        if t_right < 0.0:
            d_right = inf
        else:
            wx, wy = vx - (rcx + t_right * right[0]), vy - (rcy + t_right * right[1])
            d_right = wx * wx + wy * wy
        if d_cut <= d_left and d_cut <= d_right:
            dx, dy = -udir[o1][0], -udir[o1][1]  # the cut-off line
            lines.append(((lcx + r * inv_tau * -dy, lcy + r * inv_tau * dx), (dx, dy)))
            continue
        if d_left <= d_right:
            if left_foreign:
                continue
            dx, dy = left
            lines.append(((lcx + r * inv_tau * -dy, lcy + r * inv_tau * dx), (dx, dy)))
            continue
        if right_foreign:
            continue
        dx, dy = -right[0], -right[1]
        lines.append(((rcx + r * inv_tau * -dy, rcy + r * inv_tau * dx), (dx, dy)))
    return lines


def distance_to_zones_m(pos_m, polygons) -> np.ndarray:
    """(N,) distance from each position (N, 2) to the nearest zone polygon, 0 inside one (what
    `covey eval` counts entries with)."""
    import shapely

    pts = shapely.points(np.asarray(pos_m, dtype=np.float64).reshape(-1, 2))
    zones = shapely.union_all([shapely.Polygon(p) for p in polygons])
    return shapely.distance(pts, zones)
