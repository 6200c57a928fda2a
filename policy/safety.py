"""Optional safety filter: ORCA half-planes and a small 2-D linear program.

Beyond the paper. Each vehicle alone, from its neighbours' positions and velocities,
changes the policy's velocity as little as possible (closest in the Euclidean sense)
so that it stays outside every neighbour's velocity obstacle for `time_horizon_s`,
taking half of the avoidance effort (reciprocity). The maths follows van den Berg et
al., "Reciprocal n-body collision avoidance" (2011); the LP is their incremental
2-D program with the fallback that minimises the worst violation when infeasible
(policy.orca_lp). Neighbours that do not cooperate follow policy.traffic_rules.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# the traffic rules (neighbours that do not cooperate) are policy.traffic_rules; the names
# callers know from here are re-exported
from policy.orca_lp import _clip_speed, _det, solve, solve_lines
from policy.traffic_rules import MANNED_SEPARATION_M as MANNED_SEPARATION_M
from policy.traffic_rules import NC_ESCAPE_SHARE as NC_ESCAPE_SHARE
from policy.traffic_rules import NC_MAX_HORIZON_FACTOR as NC_MAX_HORIZON_FACTOR
from policy.traffic_rules import NC_SIDE_BIAS as NC_SIDE_BIAS
from policy.traffic_rules import (
    ahead_one,
    ahead_track,
    effective_cooperative,
    escape,
    escape_lines,
    escape_one,
    pair_horizon_one_s,
    pair_horizon_s,
    pair_reach_m,
    planned_velocity,
    step_aside,
    step_aside_one,
)

EPS = 1e-9
COINCIDENT_M = 0.01
"""Neighbours nearer than this (horizontally) are coincident: their relative position gives no
direction to push apart (two vehicles that took off from one point and hover there give exactly
zero), so the ordered pair of vehicle ids gives one (`tie_direction`). The C twin is
COVEY_SAFETY_COINCIDENT_M."""


SIGMA_K = 4.0
"""Default `SafetyConfig.sigma_k`. The relative error of two independent estimates is a 2-D
Gaussian with per-axis sigma_rel = sqrt(sigma_i^2 + sigma_j^2); only its component along the
line between the vehicles eats into the separation, so a pair held at the inflated distance is
within radius_m (1 + margin) of each other in truth with probability Phi(-k) per look (3e-5
at k = 4), and within the bare radius_m only if the error also exceeds the margin. That is for
a pair that holds the inflated distance; dense crowds do not (the filter then minimises the
worst violation): in the centre of a circle swap on plain 0.5 m GNSS the estimates come 1-1.5 m
inside the berth, and what is left above 3 m between true positions is what k buys. Measured
with realistic vehicles on antipodal circles of 16, 32 and 50, 12 seeds, both links
(`python -m bench.crowd_sigma`, docs/sky.md "Dense crowds"): k = 3 left true-position
collisions in 6 of 72 cases (2.93 m), 3.5 in 1, 4 in none (closest 3.33 m) at about 13 %
more time in those circles, and a vehicle late in more two-way gaps; 5 jammed the circles. k = 1.5 and 2 were worse still (docs/policy.md,
"Real vehicles"). Zones are padded with the same k (sigma_k x the own 1-sigma)."""


RECOVER_SPEED_SHARE = 2.0
"""Default `SafetyConfig.recover_speed_share`. RVO2 asks a pair that already overlaps to part
within one control period: (r - d) / dt, 18 m/s for a pair 1.8 m inside its distance. No
vehicle can, so the program is infeasible and its fallback minimises the worst violation, which
that one pair then sets: every other neighbour, approaching or not, is ignored up to the same
violation. With uncertain positions this is common, not an emergency: a pair is "inside" as
soon as its estimates are within the sigma padding (`pair_pad_m`: 4.2 m of the 7.8 m at
0.75 m GNSS and k = 4), and a dense crowd has many such pairs. So a pair inside the padding
but not inside the separation itself (d >= r - pad) is asked to part at most at this share of
max_speed_m_s, relative: 2 lets each vehicle of a reciprocal pair part at its full speed, as
it did alone, and the demand stays feasible beside the others'. A pair inside the separation
itself is an emergency and keeps RVO2's demand; with exact positions (no padding) nothing
changes. Measured (docs/sky.md, "Parting pairs"; `python -m bench.gnss_beyond`): realistic
vehicles at 0.75 and 1 m GNSS, 0 collision cases where the old rule left 1 and 3 (of 96);
ideal vehicles the same flights. Capping inside the separation too, or capping at 1, left
collisions in dense or gusty circles.
The C twin is covey_safety_config_t.recover_speed_share (covey_safety_defaults)."""
MAX_RECOVER_SPEED_SHARE = 10.0
"""The largest `SafetyConfig.recover_speed_share` (COVEY_SAFETY_MAX_RECOVER_SHARE in C)."""


@dataclass(frozen=True)
class SafetyConfig:
    """ORCA parameters in world units (the runtime scales them)."""

    radius_m: float = 3.0
    """Combined radius kept between two vehicle centres (the separation)."""
    margin: float = 0.2
    """Relative padding on radius_m (3 m -> 3.6 m), to absorb discrete-time and link errors:
    neighbours dead-reckoned from 3 Hz states with losses are tenths of a metre off. With the
    weights fine-tuned with the filter in the loop, dense circles on such a link came to
    2.96-2.99 m at 0.1 and 3.004 m at 0.15; 3.24-3.34 m at 0.2 (docs/policy.md, issue 16)."""
    time_horizon_s: float = 4.0
    """How far ahead velocity obstacles look."""
    dt_s: float = 0.1
    """Control period; used only when two vehicles already overlap."""
    max_speed_m_s: float = 1.0
    """Speed limit of the filtered velocity."""
    responsibility: float = 0.5
    """Share of the avoidance each vehicle takes (0.5 = reciprocal)."""
    sigma_k: float = SIGMA_K
    """Confidence factor on position uncertainty: a pair whose estimates have 1-sigma errors
    sigma_i and sigma_j (per axis, metres) keeps radius_m (1 + margin) + sigma_k sqrt(sigma_i^2 +
    sigma_j^2) between estimated centres (`pair_radius_m`), so that the true centres keep
    radius_m with the confidence SIGMA_K states. 0: estimates are taken as the truth."""
    non_cooperative_radius_m: float | None = None
    """Separation kept from a non-cooperative neighbour (manned aircraft, another operator's
    drone; one that does not avoid), before margin and uncertainty; None = radius_m. Such a
    neighbour also gets full responsibility: this vehicle takes the whole correction."""
    manned_radius_m: float | None = MANNED_SEPARATION_M
    """Separation kept from a manned aircraft (a non-cooperative neighbour flagged manned:
    `nbr_manned`), before margin and uncertainty; None = as any non-cooperative neighbour."""
    recover_speed_share: float = RECOVER_SPEED_SHARE
    """A pair inside its uncertainty padding (not inside the separation itself) is asked to part
    at up to this share of max_speed_m_s (relative; each vehicle takes its share), not within
    one dt_s (`RECOVER_SPEED_SHARE`); 0: within one dt_s, as RVO2 does (before)."""

    def __post_init__(self) -> None:
        share = self.recover_speed_share
        if not (math.isfinite(share) and 0.0 <= share <= MAX_RECOVER_SPEED_SHARE):
            raise ValueError(
                f"recover_speed_share={share} must be within [0, {MAX_RECOVER_SPEED_SHARE:g}] "
                "(a share of max_speed_m_s; 0: part within one dt_s)"
            )


def tie_direction(own_id: int, nbr_id: int) -> tuple[float, float]:
    """Unit (north, east) vector at which a coincident neighbour is taken to be: one bearing per
    unordered pair of ids, seen from the lower id; the higher id sees the opposite, so the two
    are pushed apart along one line, each its own way. The bearing is hashed from both ids so
    that several vehicles at one point spread in different directions. Ids are 32-bit unsigned;
    the C twin (covey_safety.c tie_direction) computes the same integers."""
    lo, hi = min(own_id, nbr_id), max(own_id, nbr_id)
    h = ((lo * 0x9E3779B1) ^ (hi * 0x85EBCA77)) & 0xFFFFFFFF
    h ^= h >> 15
    bearing_rad = (h & 0xFFFF) * (2.0 * math.pi / 65536.0)
    sign = 1.0 if own_id == lo else -1.0
    return sign * math.cos(bearing_rad), sign * math.sin(bearing_rad)


def pair_radius_m(
    cfg: SafetyConfig,
    pos_sigma_m=None,
    nbr_pos_sigma_m=None,
    nbr_cooperative=None,
    nbr_manned=None,
):
    """The distance each pair keeps between estimated centres and this vehicle's share of the
    correction, from the position uncertainties (1-sigma, metres) and the cooperative flags.

        r_ij = base_j (1 + margin) + sigma_k sqrt(sigma_i^2 + sigma_j^2)
        base_j = radius_m (cooperative), non_cooperative_radius_m, or manned_radius_m for a
                 manned aircraft (nbr_manned; it is non-cooperative whatever nbr_cooperative says);
        share_j = responsibility (cooperative) or 1 (it will not avoid: all of it is ours).

    pos_sigma_m scalar or (...,); nbr_pos_sigma_m and nbr_cooperative (..., K) or None (0 and
    True). Returns (r, share): Python floats when nothing per-neighbour is given (today's
    values), else arrays broadcast to the neighbours' shape. The C twin is
    covey_safety.c pair_radius."""
    base = cfg.radius_m * (1.0 + cfg.margin)
    if (
        nbr_pos_sigma_m is None
        and nbr_cooperative is None
        and nbr_manned is None
        and (pos_sigma_m is None or not np.any(pos_sigma_m))
    ):
        return base, cfg.responsibility
    nbr_cooperative = effective_cooperative(nbr_cooperative, nbr_manned)
    own = np.asarray(0.0 if pos_sigma_m is None else pos_sigma_m, dtype=np.float64)
    nbr = np.asarray(0.0 if nbr_pos_sigma_m is None else nbr_pos_sigma_m, dtype=np.float64)
    coop = np.asarray(True if nbr_cooperative is None else nbr_cooperative, dtype=bool)
    shape = np.broadcast_shapes(own[..., None].shape, nbr.shape, coop.shape)
    nc = cfg.radius_m if cfg.non_cooperative_radius_m is None else cfg.non_cooperative_radius_m
    base_j = np.where(coop, cfg.radius_m, nc)
    if nbr_manned is not None and cfg.manned_radius_m is not None:
        manned = np.asarray(nbr_manned, dtype=bool)
        shape = np.broadcast_shapes(shape, manned.shape)
        base_j = np.where(manned, cfg.manned_radius_m, base_j)
    r = base_j * (1.0 + cfg.margin) + pair_pad_m(cfg, own, nbr)
    share = np.where(coop, cfg.responsibility, 1.0)
    return np.broadcast_to(r, shape), np.broadcast_to(share, shape)


def pair_radius_one_m(
    cfg: SafetyConfig,
    pos_sigma_m: float,
    nbr_pos_sigma_m: float,
    nbr_cooperative: bool,
    nbr_manned: bool,
) -> float:
    """`pair_radius_m`'s r of one pair in Python floats (agent/calm.py's one-vehicle path, a
    neighbour at a time), equal to it bit for bit: the same operations in the same order."""
    if nbr_manned and cfg.manned_radius_m is not None:
        base_j = cfg.manned_radius_m
    elif nbr_cooperative and not nbr_manned:
        base_j = cfg.radius_m
    elif cfg.non_cooperative_radius_m is not None:
        base_j = cfg.non_cooperative_radius_m
    else:
        base_j = cfg.radius_m
    pad = math.sqrt(pos_sigma_m * pos_sigma_m + nbr_pos_sigma_m * nbr_pos_sigma_m)
    return base_j * (1.0 + cfg.margin) + cfg.sigma_k * pad


def pair_pad_m(cfg: SafetyConfig, pos_sigma_m=None, nbr_pos_sigma_m=None):
    """The part of each pair's distance (`pair_radius_m`) that is there for the position
    uncertainty: sigma_k sqrt(sigma_i^2 + sigma_j^2); 0.0 when no sigma is given. pos_sigma_m
    scalar or (...,), nbr_pos_sigma_m (..., K): an array of the neighbours' shape."""
    if pos_sigma_m is None and nbr_pos_sigma_m is None:
        return 0.0
    own = np.asarray(0.0 if pos_sigma_m is None else pos_sigma_m, dtype=np.float64)
    nbr = np.asarray(0.0 if nbr_pos_sigma_m is None else nbr_pos_sigma_m, dtype=np.float64)
    return cfg.sigma_k * np.sqrt(own[..., None] ** 2 + nbr**2)


def untie(rel_pos, own_ids, nbr_ids):
    """rel_pos (..., K, 2) with coincident neighbours (nearer than COINCIDENT_M) moved to
    COINCIDENT_M along `tie_direction`; own_ids (...,) and nbr_ids (..., K) are vehicle ids, 0 or
    equal ids: unknown, left as they are. A copy only where something changes (it is rare)."""
    if own_ids is None or nbr_ids is None:
        return rel_pos
    near = (rel_pos**2).sum(-1) < COINCIDENT_M * COINCIDENT_M
    if not near.any():
        return rel_pos
    own = np.broadcast_to(np.asarray(own_ids, np.int64)[..., None], near.shape)
    nbr = np.asarray(nbr_ids, np.int64)
    fix = near & (own > 0) & (nbr > 0) & (own != nbr)
    if not fix.any():
        return rel_pos
    out = np.array(rel_pos, dtype=np.float64)
    for idx in zip(*np.nonzero(fix), strict=True):
        out[idx] = np.multiply(tie_direction(int(own[idx]), int(nbr[idx])), COINCIDENT_M)
    return out


def orca_lines(rel_pos, rel_vel, own_vel, cfg: SafetyConfig, r=None, share=None, nc=None, pad=None):
    """ORCA half-planes for one or many vehicles.

    rel_pos = p_j - p_i, rel_vel = v_i - v_j, shapes (..., K, 2); own_vel (..., 2).
    r and share (scalars or (..., K)): each pair's distance and this vehicle's share of the
    correction (`pair_radius_m`); None: radius_m (1 + margin) and responsibility.
    pad (..., K) or None: the part of r there for position uncertainty (`pair_pad_m`); a pair
    inside r but not inside r - pad parts at what vehicles can (`RECOVER_SPEED_SHARE`).
    nc (..., K) bool or None: non-cooperative neighbours, which get their own horizon
    (`pair_horizon_s`) and, on a collision course (v_rel inside the untruncated cone: v.p > 0
    and |det(p, v)| < r |v|), the projection onto a leg of the cone instead of the cut-off
    circle: the half-plane then has a lateral normal, so the vehicle steps aside rather than
    fleeing along the line of a faster intruder that would catch it. The leg: the one that
    keeps this vehicle on its side of the neighbour's track when the neighbour is at least as
    fast as max_speed_m_s (crossing ahead of a faster one lets it catch us from behind), else
    the side v_rel leans to; within NC_SIDE_BIAS r of the track (or of v_rel's axis), the
    right-hand leg (north/east frame; the rules of the air turn right for head-on).
    Cooperative pairs: unchanged.
    Returns (point, direction), each (..., K, 2): the allowed side is
    det(direction, point - v) <= 0, with det(a, b) = a_x b_y - a_y b_x.
    """
    if r is None:
        r = cfg.radius_m * (1.0 + cfg.margin)
    if share is None:
        share = cfg.responsibility
    px, py = rel_pos[..., 0], rel_pos[..., 1]
    vx, vy = rel_vel[..., 0], rel_vel[..., 1]
    tau = cfg.time_horizon_s if nc is None else pair_horizon_s(cfg, r, np.hypot(vx, vy), ~nc)
    dist_sq = px * px + py * py
    # not yet colliding: w = v_rel - p_rel / tau, relative to the cut-off circle centre
    wx, wy = vx - px / tau, vy - py / tau
    w_len_sq = wx * wx + wy * wy
    dot1 = wx * px + wy * py
    on_circle = (dot1 < 0) & (dot1 * dot1 > r * r * w_len_sq)
    w_len = np.sqrt(np.maximum(w_len_sq, EPS))
    ux_c, uy_c = wx / w_len, wy / w_len
    leg = np.sqrt(np.maximum(dist_sq - r * r, 0.0))
    left = (px * wy - py * wx) > 0
    if nc is not None:
        # det(p, w) = det(p, v): the side test is the same on v (policy.traffic_rules)
        steer, nc_left, side = step_aside(px, py, vx, vy, own_vel, r, cfg.max_speed_m_s)
        steer = nc & steer
        on_circle = on_circle & ~steer
        left = np.where(steer, nc_left, left)
    inv = 1.0 / np.maximum(dist_sq, EPS)
    lx = np.where(left, px * leg - py * r, -(px * leg + py * r)) * inv
    ly = np.where(left, px * r + py * leg, -(-px * r + py * leg)) * inv
    dot2 = vx * lx + vy * ly
    # direction and u (the smallest change of v_rel that leaves the obstacle)
    dir_x = np.where(on_circle, uy_c, lx)
    dir_y = np.where(on_circle, -ux_c, ly)
    u_x = np.where(on_circle, (r / tau - w_len) * ux_c, dot2 * lx - vx)
    u_y = np.where(on_circle, (r / tau - w_len) * uy_c, dot2 * ly - vy)
    # already colliding: resolve within one control period
    colliding = dist_sq <= r * r
    inv_dt: float | np.ndarray = 1.0 / cfg.dt_s
    if pad is not None and cfg.recover_speed_share > 0:
        # inside the padding only: part at what vehicles can (RECOVER_SPEED_SHARE)
        rec = cfg.recover_speed_share * cfg.max_speed_m_s
        d = np.sqrt(dist_sq)
        capped = np.minimum(inv_dt, rec / np.maximum(r - d, EPS))
        inv_dt = np.where(d >= r - pad, capped, inv_dt)
    cx, cy = vx - inv_dt * px, vy - inv_dt * py
    c_len = np.sqrt(np.maximum(cx * cx + cy * cy, EPS))
    ucx, ucy = cx / c_len, cy / c_len
    dir_x = np.where(colliding, ucy, dir_x)
    dir_y = np.where(colliding, -ucx, dir_y)
    u_x = np.where(colliding, (r * inv_dt - c_len) * ucx, u_x)
    u_y = np.where(colliding, (r * inv_dt - c_len) * ucy, u_y)
    k = share
    pt_x, pt_y = own_vel[..., None, 0] + k * u_x, own_vel[..., None, 1] + k * u_y
    if nc is not None:
        # within r of a faster one, closing: off its track at NC_ESCAPE_SHARE max speed or more
        active = nc & colliding & (px * vx + py * vy > 0)
        (pt_x, pt_y), (dir_x, dir_y) = escape(
            active, side, r, cfg.max_speed_m_s, (pt_x, pt_y), (dir_x, dir_y), px, py, own_vel
        )
    return np.stack([pt_x, pt_y], axis=-1), np.stack([dir_x, dir_y], axis=-1)


def filter_velocity(
    pos_m,
    vel_m_s,
    pref_vel_m_s,
    nbr_pos_m,
    nbr_vel_m_s,
    cfg: SafetyConfig,
    own_id: int | None = None,
    nbr_ids=None,
    pos_sigma_m: float = 0.0,
    nbr_pos_sigma_m=None,
    nbr_cooperative=None,
    zones=None,
    nbr_manned=None,
):
    """The filtered velocity of one vehicle (2,), world units. With ids (own_id, nbr_ids (K,)),
    coincident neighbours are pushed apart by id (`untie`); without, they are not. Position
    uncertainties (pos_sigma_m, nbr_pos_sigma_m (K,), 1-sigma metres) and cooperative flags
    (nbr_cooperative (K,) bool, default all True) and manned aircraft (nbr_manned (K,) bool,
    default none) set each pair's distance and share (`pair_radius_m`). `zones` (policy.zone_lines.ZoneSet): keep-out edges as hard lines,
    through `filter_one`."""
    if zones is not None:
        return filter_one(
            pos_m,
            vel_m_s,
            pref_vel_m_s,
            nbr_pos_m,
            nbr_vel_m_s,
            cfg,
            own_id,
            nbr_ids,
            pos_sigma_m,
            nbr_pos_sigma_m,
            nbr_cooperative,
            zones,
            nbr_manned,
        )
    nbr_cooperative = effective_cooperative(nbr_cooperative, nbr_manned)
    nbr_pos_m = np.asarray(nbr_pos_m, dtype=np.float64).reshape(-1, 2)
    if nbr_pos_m.shape[0] == 0:
        return _clip_speed(np.asarray(pref_vel_m_s, dtype=np.float64), cfg.max_speed_m_s)
    nbr_vel_m_s = planned_velocity(
        np.asarray(nbr_vel_m_s, dtype=np.float64).reshape(-1, 2), nbr_cooperative
    )
    rel_pos = untie(nbr_pos_m - pos_m, own_id, nbr_ids)
    rel_vel = np.asarray(vel_m_s) - nbr_vel_m_s
    r, share = pair_radius_m(cfg, pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned)
    # vehicles that cannot meet within the horizon add no constraint
    coop = None
    if nbr_cooperative is not None:
        coop = np.broadcast_to(np.asarray(nbr_cooperative, dtype=bool), rel_pos.shape[:-1])
    tau = pair_horizon_s(cfg, r, np.hypot(*rel_vel.T), coop)
    reach = pair_reach_m(cfg, r, np.hypot(*nbr_vel_m_s.T), coop, tau)
    near = (rel_pos**2).sum(-1) < reach * reach
    if not near.any():
        return _clip_speed(np.asarray(pref_vel_m_s, dtype=np.float64), cfg.max_speed_m_s)
    if np.ndim(r):
        r, share = r[near], share[near]
    pad = pair_pad_m(cfg, pos_sigma_m, nbr_pos_sigma_m)
    point, direction = orca_lines(
        rel_pos[near],
        rel_vel[near],
        np.asarray(vel_m_s, float),
        cfg,
        r,
        share,
        None if coop is None else ~coop[near],
        np.broadcast_to(pad, near.shape)[near],
    )
    if coop is None:
        return solve(point, direction, pref_vel_m_s, cfg.max_speed_m_s)
    nc_near = ~coop[near]
    nc_vel = nbr_vel_m_s[near][nc_near]
    ahead = (
        _ahead(rel_pos[near], rel_vel[near], vel_m_s, r, cfg, nc_near) if nc_near.any() else None
    )
    return _solve_nc_hard(
        point, direction, coop[near], pref_vel_m_s, cfg.max_speed_m_s, (), nc_vel, ahead
    )


def _ahead(rel_pos, rel_vel, own_vel, r, cfg: SafetyConfig, nc, valid=True):
    """`ahead_track` of the pairs (..., K) as `orca_lines` builds them: the escaping ones are
    non-cooperative (nc), valid, within r and closing."""
    px, py = rel_pos[..., 0], rel_pos[..., 1]
    vx, vy = rel_vel[..., 0], rel_vel[..., 1]
    active = nc & valid & (px * px + py * py <= r * r) & (px * vx + py * vy > 0)
    own = np.asarray(own_vel, np.float64)
    return ahead_track(px, py, vx, vy, own, cfg.max_speed_m_s, active)


def _solve_nc_hard(point, direction, coop, pref, max_speed, hard, nc_vel=(), ahead=None):
    """`solve` with the non-cooperative neighbours' lines hard after `hard` (the zones'): in a
    crowd that leaves no velocity meeting every line, the covey neighbours' lines are relaxed
    (each of them also avoids), never the line of traffic that will not. nc_vel (M, 2): the
    velocities of those neighbours, for the escape speed and its track line; ahead (2,): the
    ahead rule's track, NaN or None for none (`escape_lines`)."""
    nc = ~np.asarray(coop, bool)
    if not nc.any():
        return solve(point, direction, pref, max_speed, hard)
    extra = [
        ((float(p[0]), float(p[1])), (float(d[0]), float(d[1])))
        for p, d in zip(point[nc], direction[nc], strict=True)
    ]
    if ahead is not None and np.isnan(ahead).any():
        ahead = None
    vmax, opt = escape_lines(max_speed, np.asarray(nc_vel, np.float64).tolist(), ahead)
    return solve(point[~nc], direction[~nc], pref, vmax, list(hard) + extra + opt, len(opt))


def _orca_line(px, py, vx, vy, own_vx, own_vy, r, cfg: SafetyConfig):
    """`orca_lines` for one neighbour in Python floats (the branch it takes, not all three)."""
    return _orca_line_k(px, py, vx, vy, own_vx, own_vy, _line_constants(r, cfg))


def _line_constants(
    r: float,
    cfg: SafetyConfig,
    share: float | None = None,
    tau: float | None = None,
    pad: float = 0.0,
) -> tuple:
    """What `_orca_line_k` needs of the config, computed once per vehicle (per neighbour when
    the pairs differ: `pair_radius_m`; tau: a non-cooperative pair's `pair_horizon_s`, which
    also turns on its step-aside rule)."""
    nc = tau is not None
    tau = cfg.time_horizon_s if tau is None else tau
    inv_dt = 1.0 / cfg.dt_s
    k = cfg.responsibility if share is None else share
    rec = cfg.recover_speed_share * cfg.max_speed_m_s if pad > 0 else 0.0
    return r, r * r, tau, r / tau, inv_dt, r * inv_dt, k, nc, cfg.max_speed_m_s, rec, r - pad


def _orca_line_k(px, py, vx, vy, own_vx, own_vy, consts):
    """`_orca_line` with the config's constants precomputed (`_line_constants`); max(x, EPS)
    as a comparison (the same value, NaN included)."""
    r, r_sq, tau, r_tau, inv_dt, r_inv_dt, k, nc, vmax, rec, hard_r = consts
    dist_sq = px * px + py * py
    if nc and dist_sq <= r_sq and px * vx + py * vy > 0:  # the escape rule of `orca_lines`
        line = escape_one(px, py, vx, vy, own_vx, own_vy, r, vmax)
        if line is not None:
            return line
    if dist_sq <= r_sq:
        d = math.sqrt(dist_sq)
        if rec > 0 and d >= hard_r:  # inside the padding only: part at what vehicles can
            gap = r - d
            if gap * inv_dt > rec:
                inv_dt = rec / gap
                r_inv_dt = r * inv_dt
        cx, cy = vx - inv_dt * px, vy - inv_dt * py
        c_sq = cx * cx + cy * cy
        c_len = math.sqrt(EPS if c_sq < EPS else c_sq)
        ux, uy = cx / c_len, cy / c_len
        s = r_inv_dt - c_len
        return (own_vx + k * (s * ux), own_vy + k * (s * uy)), (uy, -ux)
    wx, wy = vx - px / tau, vy - py / tau
    w_len_sq = wx * wx + wy * wy
    dot1 = wx * px + wy * py
    left = px * wy - py * wx > 0
    steer = False
    if nc:  # the step-aside rule of `orca_lines`
        steer, nc_left = step_aside_one(px, py, vx, vy, own_vx, own_vy, r, vmax)
        if steer:
            left = nc_left
    if not steer and dot1 < 0 and dot1 * dot1 > r_sq * w_len_sq:
        w_len = math.sqrt(EPS if w_len_sq < EPS else w_len_sq)
        ux, uy = wx / w_len, wy / w_len
        s = r_tau - w_len
        return (own_vx + k * (s * ux), own_vy + k * (s * uy)), (uy, -ux)
    leg_sq = dist_sq - r_sq
    leg = math.sqrt(0.0 if leg_sq < 0.0 else leg_sq)
    inv = 1.0 / (EPS if dist_sq < EPS else dist_sq)
    if left:
        lx, ly = (px * leg - py * r) * inv, (px * r + py * leg) * inv
    else:
        lx, ly = -(px * leg + py * r) * inv, -(-px * r + py * leg) * inv
    dot2 = vx * lx + vy * ly
    return (own_vx + k * (dot2 * lx - vx), own_vy + k * (dot2 * ly - vy)), (lx, ly)


def filter_one(
    pos_m,
    vel_m_s,
    pref_vel_m_s,
    nbr_pos_m,
    nbr_vel_m_s,
    cfg: SafetyConfig,
    own_id: int | None = None,
    nbr_ids=None,
    pos_sigma_m: float = 0.0,
    nbr_pos_sigma_m=None,
    nbr_cooperative=None,
    zones=None,
    nbr_manned=None,
):
    """`filter_velocity` for one vehicle in Python floats: the runtime's hot path, faster for
    the few neighbours within reach (equal within 1e-12, tests/test_policy_speed.py). `zones`
    (policy.zone_lines.ZoneSet): its edges near the vehicle are hard lines (`solve_lines`)."""
    ids = None if own_id is None or nbr_ids is None else np.asarray(nbr_ids).tolist()
    base = cfg.radius_m * (1 + cfg.margin)
    nbr_cooperative = effective_cooperative(nbr_cooperative, nbr_manned)
    nbr_vel_m_s = planned_velocity(np.asarray(nbr_vel_m_s).reshape(-1, 2), nbr_cooperative)
    per_nbr = nbr_pos_sigma_m is not None or nbr_cooperative is not None or bool(pos_sigma_m)
    if per_nbr:
        radii, shares = pair_radius_m(
            cfg, pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned
        )
        k_n = np.asarray(nbr_pos_m).reshape(-1, 2).shape[0]
        pads = np.broadcast_to(pair_pad_m(cfg, pos_sigma_m, nbr_pos_sigma_m), (k_n,)).tolist()
        radii = np.broadcast_to(radii, (k_n,)).tolist()
        shares = np.broadcast_to(shares, (k_n,)).tolist()
        coops = (
            [True] * k_n
            if nbr_cooperative is None
            else np.broadcast_to(np.asarray(nbr_cooperative, bool), (k_n,)).tolist()
        )
    vmax_tau = cfg.max_speed_m_s * cfg.time_horizon_s
    reach = base + 2.0 * vmax_tau
    reach_sq = reach * reach
    x, y = float(pos_m[0]), float(pos_m[1])
    own_vx, own_vy = float(vel_m_s[0]), float(vel_m_s[1])
    lines: list = []
    nc_lines: list = []  # hard after the zones' (`_solve_nc_hard`)
    nc_vel: list = []  # their velocities (`escape_lines`)
    ahead = None  # (dist_sq, track) of the ahead rule (`ahead_one`)
    consts = None
    for k, ((nx, ny), (nvx, nvy)) in enumerate(
        zip(np.asarray(nbr_pos_m).tolist(), np.asarray(nbr_vel_m_s).tolist(), strict=True)
    ):
        px, py = nx - x, ny - y
        tau_nc = None
        if per_nbr:
            r = radii[k]
            if coops[k]:
                reach = r + 2.0 * vmax_tau
            else:
                vmax = cfg.max_speed_m_s
                tau_nc = pair_horizon_one_s(cfg, r, math.hypot(own_vx - nvx, own_vy - nvy))
                reach = r + (vmax + max(vmax, math.hypot(nvx, nvy))) * tau_nc
            reach_sq = reach * reach
        if px * px + py * py < reach_sq:
            if (
                ids is not None
                and own_id is not None
                and px * px + py * py < COINCIDENT_M * COINCIDENT_M
                and own_id > 0
                and ids[k] > 0
                and own_id != ids[k]
            ):
                tx, ty = tie_direction(own_id, ids[k])
                px, py = tx * COINCIDENT_M, ty * COINCIDENT_M
            if per_nbr:
                consts = _line_constants(radii[k], cfg, shares[k], tau_nc, pads[k])
            elif consts is None:
                consts = _line_constants(base, cfg)
            vx, vy = own_vx - nvx, own_vy - nvy
            line = _orca_line_k(px, py, vx, vy, own_vx, own_vy, consts)
            if tau_nc is None:
                lines.append(line)
            else:
                nc_lines.append(line)
                nc_vel.append((nvx, nvy))
                if px * px + py * py <= radii[k] * radii[k] and px * vx + py * vy > 0:
                    found = ahead_one(px, py, vx, vy, own_vx, own_vy, cfg.max_speed_m_s)
                    if found is not None and (ahead is None or found[0] < ahead[0]):
                        ahead = found
    pref = (float(pref_vel_m_s[0]), float(pref_vel_m_s[1]))
    hard = (
        []
        if zones is None
        else zones.lines(pos_m, vel_m_s, cfg.max_speed_m_s, cfg.sigma_k * float(pos_sigma_m or 0))
    )
    vmax, opt = escape_lines(cfg.max_speed_m_s, nc_vel, None if ahead is None else ahead[1])
    hard = hard + nc_lines + opt
    return solve_lines(hard + lines, pref, vmax, len(hard), len(opt))


def filter_batch(
    pos_m, vel_m_s, pref_vel_m_s, nbr, cfg: SafetyConfig, ids=None, pos_sigma_m=None, zones=None
):
    """Filtered velocities (N,2) for N vehicles; nbr (N,K) neighbour indices, -1 = none;
    ids (N,) vehicle ids for `untie` (None: coincident vehicles are not pushed apart);
    pos_sigma_m (N,) their position uncertainties (None: exact)."""
    pos_m = np.asarray(pos_m, dtype=np.float64)
    vel_m_s = np.asarray(vel_m_s, dtype=np.float64)
    j = np.maximum(nbr, 0)
    nbr_ids = None if ids is None else np.asarray(ids)[j]
    sig = None if pos_sigma_m is None else np.asarray(pos_sigma_m, dtype=np.float64)
    return filter_padded(
        pos_m,
        vel_m_s,
        pref_vel_m_s,
        pos_m[j],
        vel_m_s[j],
        nbr >= 0,
        cfg,
        ids,
        nbr_ids,
        sig,
        None if sig is None else sig[j],
        zones=zones,
    )


def filter_padded(
    pos_m,
    vel_m_s,
    pref_vel_m_s,
    nbr_pos_m,
    nbr_vel_m_s,
    nbr_valid,
    cfg: SafetyConfig,
    own_ids=None,
    nbr_ids=None,
    pos_sigma_m=None,
    nbr_pos_sigma_m=None,
    nbr_cooperative=None,
    zones=None,
    nbr_manned=None,
):
    """Filtered velocities (N,2); each vehicle has its own neighbour list (N,K,...), and with
    own_ids (N,) and nbr_ids (N,K) coincident neighbours are pushed apart by id (`untie`).
    pos_sigma_m (N,), nbr_pos_sigma_m (N,K), nbr_cooperative (N,K) and nbr_manned (N,K):
    `pair_radius_m`.
    `zones` (policy.zone_lines.ZoneSet): every vehicle's nearby zone edges are hard lines.

    Half-planes are built for all vehicles at once; the LP runs only for the
    vehicles whose preferred velocity breaks a constraint.
    """
    pos_m = np.asarray(pos_m, dtype=np.float64)
    vel_m_s = np.asarray(vel_m_s, dtype=np.float64)
    pref = _clip_speed(np.asarray(pref_vel_m_s, dtype=np.float64), cfg.max_speed_m_s)
    if nbr_valid.shape[1] == 0 and zones is None:
        return pref
    nbr_vel_m_s = np.asarray(nbr_vel_m_s, dtype=np.float64)
    rel_pos = untie(np.asarray(nbr_pos_m, dtype=np.float64) - pos_m[:, None], own_ids, nbr_ids)
    nbr_cooperative = effective_cooperative(nbr_cooperative, nbr_manned)
    nbr_vel_m_s = planned_velocity(nbr_vel_m_s, nbr_cooperative)
    rel_vel = vel_m_s[:, None] - nbr_vel_m_s
    r, share = pair_radius_m(cfg, pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned)
    coop = None
    if nbr_cooperative is not None:
        coop = np.broadcast_to(np.asarray(nbr_cooperative, dtype=bool), rel_pos.shape[:-1])
    tau = pair_horizon_s(cfg, r, np.hypot(rel_vel[..., 0], rel_vel[..., 1]), coop)
    reach = pair_reach_m(cfg, r, np.hypot(nbr_vel_m_s[..., 0], nbr_vel_m_s[..., 1]), coop, tau)
    ok = np.asarray(nbr_valid, dtype=bool) & ((rel_pos**2).sum(-1) < reach * reach)
    pad = np.broadcast_to(pair_pad_m(cfg, pos_sigma_m, nbr_pos_sigma_m), rel_pos.shape[:-1])
    point, direction = orca_lines(
        rel_pos, rel_vel, vel_m_s, cfg, r, share, None if coop is None else ~coop, pad
    )
    viol = _det(
        direction[..., 0],
        direction[..., 1],
        point[..., 0] - pref[:, None, 0],
        point[..., 1] - pref[:, None, 1],
    )
    out = pref.copy()
    need = ((viol > 0) & ok).any(axis=1)
    ahead = None
    if coop is not None and not coop.all():
        ahead = _ahead(rel_pos, rel_vel, vel_m_s, r, cfg, ~coop, ok)
        need |= (ahead * pref).sum(-1) < 0  # the ahead line (NaN: none, False)
    hard = (
        [()] * len(pref)
        if zones is None
        else zones.lines_rows(
            pos_m,
            vel_m_s,
            pref,
            need,
            cfg.max_speed_m_s,
            None if pos_sigma_m is None else cfg.sigma_k * np.asarray(pos_sigma_m, np.float64),
        )
    )
    for i in np.flatnonzero(need):
        m = ok[i]
        if coop is None:
            out[i] = solve(point[i, m], direction[i, m], pref[i], cfg.max_speed_m_s, hard[i])
        else:
            out[i] = _solve_nc_hard(
                point[i, m],
                direction[i, m],
                coop[i, m],
                pref[i],
                cfg.max_speed_m_s,
                hard[i],
                nbr_vel_m_s[i, m & ~coop[i]],
                None if ahead is None else ahead[i],
            )
    return out
