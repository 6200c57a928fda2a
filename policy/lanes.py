"""One-lane gaps: who goes first.

A gap between zones (or between a zone and the fence) narrower than two passing vehicles need
(policy.routes `Router.one_lane_gaps`: 14 m at 3 m separation on plain GNSS) fits one vehicle
at a time. Routes fly round such a gap where a short way round exists (two-way ways first);
where none does (a gate in a long wall), two vehicles that meet in it push each other back and
forth (the separation filter is reciprocal, and neither can step aside), and streams from both
sides mill at its mouths. So a vehicle whose route enters such a gap within `gate_m` looks at
its cooperative neighbours first:

- one inside the gap flying against it (its velocity against the vehicle's way through by more
  than `oncoming_m_s`): the vehicle holds short, its waypoint a point `hold_m` before the gap
  and pulled over to the right of its way in (`pull_over_share`; the two-way width: room for
  the other to come out and pass it);
- one with a lower vehicle id in the gap or at its mouths (`mouth_share` of hold_m) that is
  not going the vehicle's way (stopped, or just come out and held up there): it holds short;
- one outside the gap on its far side, within `gate_m` of it, closing on it and flying against
  the vehicle, with a lower id, while the vehicle itself is within `gate_m`: it holds short
  too (the lower id goes first; both sides apply the same rule);
- inside the gap, a vehicle with one in it that is not going its way and has a lower id backs
  out (its waypoint `hold_m` back along its way); the lower id goes on.

Vehicles at their hold points are further out than the mouths and are not waited for, nor is
one going the vehicle's way (a queue through the gap), so two that wait for each other both
set off, and the lower id goes first. A vehicle stopped in a gap for good (its goal there)
keeps higher ids out of it until it moves: the operator sees them hold. Traffic that does
not cooperate is not waited for (the filter keeps clear of it). Decided from the positions each
tick (stateless), the same in the agents' guidance (agent/guidance.py) and `covey eval`
(policy/zone_eval.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

IN_GAP_TOL_M = 0.5
"""A neighbour this near a gap counts as in it (position estimates wander)."""


@dataclass(frozen=True)
class LaneConfig:
    """Who waits at a one-lane gap (module docstring)."""

    enabled: bool = True
    """Off: vehicles enter one-lane gaps as they come (the filter sorts out who passes)."""
    oncoming_m_s: float = 0.2
    """A neighbour flies against a vehicle when its velocity along the vehicle's way through
    the gap is below minus this, and closes on the gap when it nears it this fast."""
    look_m: float = 5.0
    """A vehicle starts to look this far beyond its hold point: gate_m = hold_m + look_m."""
    mouth_share: float = 0.5
    """A neighbour within this share of hold_m of the gap is at its mouth: one there that is
    not going the vehicle's way (stopped, or come out and held up) and has a lower id is waited
    for, so that nobody enters while the last one out still blocks the way."""
    pull_over_share: float = 0.5
    """A waiting vehicle holds this share of hold_m to the right of its way in (north-east
    frame: right of a way heading north is east), out of the way of those coming out."""

    def __post_init__(self) -> None:
        for name in ("oncoming_m_s", "look_m", "mouth_share", "pull_over_share"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")


def hold_m(route_cfg) -> float:
    """How far before a one-lane gap a vehicle waits: the two-way width (policy.routes
    RouteConfig: 2 (reach_m + pad_m + lane_m), 7.2 m at sigma 0 and 14 m at sigma 0.5)."""
    return 2.0 * (route_cfg.reach_m + route_cfg.pad_m + route_cfg.lane_m)


def _entry(pts: np.ndarray, gaps, max_s: float):
    """(gap, distance along the polyline to where it first enters one of `gaps`, that point,
    the unit direction of the leg that enters) within max_s, or None; distance 0: the
    polyline starts inside."""
    s_acc = 0.0
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        leg_m = float(math.hypot(*(b - a)))
        if leg_m < 1e-9:
            continue
        leg = shapely.LineString([a, b])
        best = None
        for g in gaps:
            hit = g.intersection(leg)
            if hit.is_empty:
                continue
            t = min(leg.project(shapely.Point(c)) for c in shapely.get_coordinates(hit))
            if best is None or t < best[1]:
                best = (g, t)
        if best is not None:
            g, t = best
            u = (b - a) / leg_m
            return g, s_acc + t, a + u * t, u
        s_acc += leg_m
        if s_acc > max_s:
            return None
    return None


def _along(pts: np.ndarray, s_m: float) -> np.ndarray:
    """The point `s_m` along the polyline (its end beyond it)."""
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        leg_m = float(math.hypot(*(b - a)))
        if s_m <= leg_m and leg_m > 0:
            return a + (b - a) * (s_m / leg_m)
        s_m -= leg_m
    return pts[-1].copy()


def _back_from(router, here: np.ndarray, u: np.ndarray, back_m: float, fallback: np.ndarray):
    """`here - u back_m` where the router's route legs may start, else `fallback`."""
    pt = here - u * back_m
    return pt if router.in_sight_space(pt) else fallback


def hold_short(
    router,
    pos_m,
    goal_m,
    way_m,
    pad_m,
    nbr_pos_m,
    nbr_vel_m_s,
    valid,
    own_ids=None,
    nbr_ids=None,
    cfg: LaneConfig | None = None,
) -> np.ndarray:
    """`way_m` (R, 2), the waypoints `router.next_waypoints(pos_m, goal_m, pad_m)` gave, with
    the rows that must wait for a one-lane gap (module docstring) given their hold point.
    pos_m, goal_m (R, 2); pad_m None, one pad or (R,); nbr_pos_m, nbr_vel_m_s (R, K, 2+) what
    each row knows of its cooperative neighbours, valid (R, K); own_ids (R,), nbr_ids (R, K)
    vehicle ids for the tie-break (None: only vehicles in a gap are waited for)."""
    cfg = cfg or LaneConfig()
    out = np.array(way_m, dtype=np.float64, copy=True).reshape(-1, 2)
    if router is None or not cfg.enabled or not len(out):
        return out
    pos = np.asarray(pos_m, dtype=np.float64).reshape(-1, 2)
    goal = np.asarray(goal_m, dtype=np.float64).reshape(-1, 2)
    pads = (
        np.zeros(len(pos))
        if pad_m is None
        else np.broadcast_to(np.asarray(pad_m, float), (len(pos),))
    )
    nbr_pos = np.asarray(nbr_pos_m, dtype=np.float64)
    nbr_vel = np.asarray(nbr_vel_m_s, dtype=np.float64)
    valid = np.asarray(valid, bool)
    for i in range(len(pos)):
        if not valid[i].any() or not (np.isfinite(pos[i]).all() and np.isfinite(goal[i]).all()):
            continue
        pad = float(pads[i]) if math.isfinite(pads[i]) and pads[i] > 0 else 0.0
        r = router.widened(pad) if pad > 0 else router
        gaps = r.one_lane_gaps()
        if not gaps:
            continue
        wait_m = hold_m(r.cfg)
        gate_m = wait_m + cfg.look_m
        here = shapely.Point(pos[i])
        near = [g for g in gaps if g.distance(here) <= gate_m]
        if not near:
            continue
        route = r.plan(pos[i], goal[i])
        if not len(route.waypoints_m):
            continue
        pts = np.vstack([pos[i], route.waypoints_m])
        hit = _entry(pts, near, gate_m)
        if hit is None:
            continue
        gap, s_in, entry, u = hit
        m = valid[i]
        q, w = nbr_pos[i, m, :2], nbr_vel[i, m, :2]
        along = w @ u
        against = along < -cfg.oncoming_m_s
        with_it = along > cfg.oncoming_m_s
        if with_it.all():
            continue
        ids = None if own_ids is None or nbr_ids is None else np.asarray(nbr_ids)[i, m]
        lower = np.zeros(len(q), bool) if ids is None else ids < int(np.asarray(own_ids)[i])
        d_now = shapely.distance(gap, shapely.points(q))
        in_gap = d_now <= IN_GAP_TOL_M
        if s_in <= 0.0:  # inside: back out for a lower id in it not going its way
            if (in_gap & ~with_it & lower).any():
                out[i] = _back_from(r, pos[i], u, wait_m, pos[i])
            continue
        # one in the gap coming the other way, or stopped in it or at its mouths with a lower id
        at_mouth = d_now <= cfg.mouth_share * wait_m
        wait = bool((in_gap & against).any() or (at_mouth & ~with_it & lower).any())
        if not wait and ids is not None:
            d_soon = shapely.distance(gap, shapely.points(q + w))  # a second on
            closing = (d_now - d_soon) > cfg.oncoming_m_s
            far = ((q - entry) @ u) > 0.0
            wait = bool((far & closing & against & lower & (d_now <= gate_m)).any())
        if wait:
            # pulled over to the right of the way in: the ones coming out pass on its left
            side = np.array([-u[1], u[0]]) * (cfg.pull_over_share * wait_m)
            spot = _back_from(r, entry + side, u, wait_m, np.full(2, np.nan))
            if np.isnan(spot).any():
                spot = _along(pts, s_in - wait_m) if s_in > wait_m else pos[i]
            out[i] = spot
    return out
