"""How the separation filter treats traffic that does not cooperate (issue 35): its berth, the
speed margin it is planned with, its horizon and reach, the step aside on a collision course,
the escape off a faster one's track and the ahead rule.

policy.safety builds the ORCA half-planes; for a non-cooperative neighbour (manned aircraft,
another operator's drone, an intruder: one that does not avoid) it asks this module which leg
of the cone to project on and whether the line becomes an escape. The C twin is in
firmware/covey_safety.c (orca_line, pair_radius); docs/sky.md, "How the filter treats traffic".
Conventions as policy.safety.orca_lines: p = p_j - p_i, v = v_i - v_j, r the pair's distance.
"""

from __future__ import annotations

import math

import numpy as np

EPS = 1e-9

NC_MAX_HORIZON_FACTOR = 3.0
"""A non-cooperative pair's time horizon is at most this many time_horizon_s (`pair_horizon_s`),
or the time to move its whole distance r sideways at the escape speed and then a horizon, if
that is longer (a manned aircraft's 36 m: 22 s). The C twin is
COVEY_SAFETY_NC_MAX_HORIZON_FACTOR."""
NC_SIDE_BIAS = 0.25
"""Step-aside tie-break (`step_aside`): against a non-cooperative neighbour on a collision course
this vehicle passes it on the right-hand leg of the cone (north/east frame: the rules of the air
turn right for head-on) unless it is already off the neighbour's track to the other side by more
than this share of the pair distance r (for a neighbour slower than us: unless v_rel leans that
way by more than this share of r |v|). A band, not a sign test, so that a dead-on encounter
seen through noisy states picks one side and keeps it. The C twin is
COVEY_SAFETY_NC_SIDE_BIAS."""

MANNED_SEPARATION_M = 30.0
"""Default `SafetyConfig.manned_radius_m`: the berth kept from a manned aircraft (ADS-B emitter
categories light to ultralight, comms/adsb.py MANNED_EMITTERS), whose pilot may not see a small
drone and whose wake and rotor downwash reach further than a multicopter's. The C twin is
COVEY_SAFETY_MANNED_SEPARATION_M."""

NC_ESCAPE_SPEED_FACTOR = 2.0
"""While non-cooperative neighbours add lines, the filter may fly as fast as the fastest of them,
up to this many max_speed_m_s (`escape_speed_m_s`): at the cruise speed alone a vehicle cannot
get out of the way of traffic up to twice as fast that crosses or overtakes it (docs/sky.md).
The C twin is COVEY_SAFETY_NC_ESCAPE_SPEED_FACTOR."""

NC_SPEED_MARGIN = 0.25
"""The filter plans against traffic that does not cooperate as if it flew this share faster
than it reports (`planned_velocity`): a reported velocity is a snapshot, and traffic that does
not coordinate speeds up with gusts, throttle or a new leg. A "1x" intruder in 0.2 m/s gusts
went from 0.4 to 1.3 m/s within 5 s on fresh seed 103 and caught a vehicle that flew on ahead
of it on its track (docs/sky.md, "Traffic's speed margin"). The C twin is
COVEY_SAFETY_NC_SPEED_MARGIN."""

NC_ESCAPE_SHARE = 0.8
"""Already within a non-cooperative neighbour's distance r, closing, and it at least as fast as
us: fleeing along the line cannot work, so the line becomes "move off its track at this share of
max_speed_m_s or more", v . n >= NC_ESCAPE_SHARE max_speed, n perpendicular to its velocity on
the step-aside side (`escape`); more where that would not clear the berth before it arrives
(`clear_speed`). The C twin is COVEY_SAFETY_NC_ESCAPE_SHARE."""


NC_KEEP_SIDE_SPEED_FACTOR = 1.5
"""A vehicle moving off a fast neighbour's track faster than this many max_speed_m_s is escaping
(guidance never flies faster than max_speed_m_s; gusts add a few tenths): within the side band,
it keeps the side it escapes to even where the track line swung across it (`kept_offset`). The
C twin is COVEY_SAFETY_NC_KEEP_SIDE_SPEED_FACTOR."""

NC_CLEAR_SHARE = 0.95
"""The escape line's lateral speed (`clear_speed`) is at most this share of the most that gains
room, so that the escape line, the track line and the speed limit can all be met with a margin
(at the full value they meet in one point, and float32 and float64 round it apart). The C twin is
COVEY_SAFETY_NC_CLEAR_SHARE."""


def effective_cooperative(nbr_cooperative=None, nbr_manned=None):
    """The cooperative flags with manned aircraft (nbr_manned True) made non-cooperative: a
    manned aircraft never avoids a covey vehicle. None when both are None."""
    if nbr_manned is None:
        return nbr_cooperative
    manned = np.asarray(nbr_manned, dtype=bool)
    coop = np.asarray(True if nbr_cooperative is None else nbr_cooperative, dtype=bool)
    return coop & ~manned


def planned_velocity(nbr_vel_m_s, nbr_cooperative=None):
    """Neighbours' velocities (..., K, 2) as the filter plans against them: traffic's
    (nbr_cooperative False, broadcast to (..., K)) times 1 + NC_SPEED_MARGIN, covey vehicles'
    as reported; all as reported when nbr_cooperative is None."""
    v = np.asarray(nbr_vel_m_s, dtype=np.float64)
    if nbr_cooperative is None:
        return v
    nc = ~np.broadcast_to(np.asarray(nbr_cooperative, bool), v.shape[:-1])
    if not nc.any():
        return v
    return np.where(nc[..., None], v * (1.0 + NC_SPEED_MARGIN), v)


def escape_speed_m_s(vmax: float, nc_speed_m_s: float = 0.0) -> float:
    """The filter's speed limit: vmax, or the speed of the fastest non-cooperative neighbour
    that adds a line (`nc_speed_m_s`, 0 for none) up to NC_ESCAPE_SPEED_FACTOR vmax."""
    return min(NC_ESCAPE_SPEED_FACTOR * vmax, max(vmax, nc_speed_m_s))


def escape_lines(vmax: float, nc_vel_m_s, ahead=None) -> tuple[float, list]:
    """The speed limit and the extra hard lines while non-cooperative neighbours add lines
    (nc_vel_m_s: their velocities, (M, 2), in the order their lines were added): the limit is
    `escape_speed_m_s` of the fastest; when that one is faster than vmax, the line "no faster
    than vmax along its track", v . t <= vmax (t its unit velocity), so that the escape speed
    takes the vehicle off its track and never races it along the track. `ahead` (a unit track
    (tx, ty) from `ahead_track`, or None) adds the ahead line, v . t >= 0. Returns (limit,
    [((px, py), (dx, dy))]), the lines as policy.orca_lp.solve_lines takes them, both
    optional (dropped first when the hard lines cannot all be met)."""
    best, fast = 0.0, None
    for vx, vy in nc_vel_m_s:
        speed = math.hypot(vx, vy)
        if speed > best:
            best, fast = speed, (vx, vy)
    lines = []
    limit = vmax
    if fast is not None and best > vmax:
        tx, ty = fast[0] / best, fast[1] / best
        limit = escape_speed_m_s(vmax, best)
        lines.append(((vmax * tx, vmax * ty), (-ty, tx)))
    if ahead is not None:
        lines.append(((0.0, 0.0), (float(ahead[1]), -float(ahead[0]))))
    return limit, lines


def ahead_track(px, py, vx, vy, own_vel, vmax: float, active):
    """The ahead rule, for arrays (..., K) of pairs (own_vel (..., 2)): among the pairs that
    escape (`active`: non-cooperative, within r, closing; `escape` then needs the neighbour at
    least as fast as vmax) and that this vehicle is ahead of (p . v_j < 0), the nearest one's
    unit velocity t, (..., 2), NaN where there is none. The escape line alone lets the vehicle
    come back along the track towards the neighbour it flees; the ahead line v . t >= 0
    (`escape_lines`) keeps the closing speed at the neighbour's own. The C twin is in
    firmware/covey_safety.c (the ahead line)."""
    jx = own_vel[..., None, 0] - vx
    jy = own_vel[..., None, 1] - vy
    j_len = np.sqrt(jx * jx + jy * jy)
    ok = active & (j_len >= vmax) & (px * jx + py * jy < 0)
    d = np.where(ok, px * px + py * py, np.inf)
    k = np.argmin(d, axis=-1)[..., None]
    jn = np.maximum(np.take_along_axis(j_len, k, -1), EPS)
    t = np.concatenate(
        [np.take_along_axis(jx, k, -1) / jn, np.take_along_axis(jy, k, -1) / jn], axis=-1
    )
    return np.where(np.take_along_axis(ok, k, -1), t, np.nan)


def ahead_one(px, py, vx, vy, own_vx, own_vy, vmax: float):
    """`ahead_track` for one escaping pair (within r and closing) in Python floats: (dist_sq,
    (tx, ty)) when the neighbour is at least as fast as vmax and this vehicle is ahead of it,
    else None."""
    jx, jy = own_vx - vx, own_vy - vy
    j_len = math.sqrt(jx * jx + jy * jy)
    if j_len < vmax or px * jx + py * jy >= 0:
        return None
    jn = EPS if j_len < EPS else j_len
    return px * px + py * py, (jx / jn, jy / jn)


def pair_horizon_s(cfg, r, rel_speed_m_s, nbr_cooperative=None):
    """Each pair's time horizon: time_horizon_s for a cooperative neighbour; for one that does
    not cooperate, long enough to step aside in time,

        tau_j = clip((r / v_max) (|v_i - v_j| / v_max), tau, cap),
        cap   = max(NC_MAX_HORIZON_FACTOR tau, r / (NC_ESCAPE_SPEED_FACTOR v_max) + tau),

    r / v_max being the time to move one pair distance sideways and |v_i - v_j| / v_max how
    many times faster the pair closes than this vehicle can move (a 2x intruder head-on: 10.8
    s at 3.6 m and 1 m/s). The cap is 3 tau unless the berth is wide: a manned aircraft's 36 m
    takes 18 s to leave at the escape speed, so it is seen 22 s ahead (at 60 m/s, 1.3 km);
    with 12 s a vehicle that had flown towards its track could not get out of the berth in
    time (docs/sky.md, "A manned aircraft's horizon"). Scalar tau when nbr_cooperative is
    None, else an array. cfg: policy.safety.SafetyConfig."""
    tau = cfg.time_horizon_s
    if nbr_cooperative is None:
        return tau
    vmax = cfg.max_speed_m_s
    r = np.asarray(r, np.float64)
    want = r / vmax * (np.asarray(rel_speed_m_s, np.float64) / vmax)
    cap = np.maximum(NC_MAX_HORIZON_FACTOR * tau, r / (NC_ESCAPE_SPEED_FACTOR * vmax) + tau)
    nc = np.minimum(np.maximum(want, tau), cap)
    return np.where(nbr_cooperative, tau, nc)


def pair_horizon_one_s(cfg, r: float, rel_speed_m_s: float) -> float:
    """`pair_horizon_s` of one non-cooperative pair, in Python floats."""
    vmax, tau = cfg.max_speed_m_s, cfg.time_horizon_s
    cap = max(NC_MAX_HORIZON_FACTOR * tau, r / (NC_ESCAPE_SPEED_FACTOR * vmax) + tau)
    return min(max(r / vmax * (rel_speed_m_s / vmax), tau), cap)


def pair_reach_m(cfg, r, nbr_speed_m_s=None, nbr_cooperative=None, tau=None):
    """Beyond this distance a neighbour cannot come within r in the horizon: r + 2 max_speed
    tau for a cooperative one (it flies at most our speed), r + (max_speed + max(max_speed,
    |v_j|)) tau_j for a non-cooperative one (it may be faster; tau_j: `pair_horizon_s`, default
    time_horizon_s)."""
    vmax = cfg.max_speed_m_s
    if tau is None:
        tau = cfg.time_horizon_s
    if nbr_cooperative is None:
        return r + 2.0 * vmax * tau
    fast = np.maximum(vmax, np.asarray(nbr_speed_m_s, dtype=np.float64))
    return r + (vmax + np.where(nbr_cooperative, vmax, fast)) * tau


def kept_offset(px, py, jx, jy, j_len, own_x, own_y, r, vmax: float):
    """This vehicle's offset from a neighbour's track times its speed, m = det(p, v_j) (arrays
    or floats; p = p_j - p_i, v_j = (jx, jy), |v_j| = j_len, own velocity (own_x, own_y)), or,
    on the side m > 0 that the band would make it leave (`step_aside`), where it will be when
    the neighbour arrives alongside if that is further off: m - T det(v_own, v_j), T = along /
    closing (0 when it is behind us or not gaining). A vehicle already leaving the track on
    that side keeps it instead of turning back across the track: the offset measured at long
    range swings with the neighbour's heading (0.2 m/s of gust on a 60 m/s aircraft 1.3 km out
    moves its track line by 4 m), and a vehicle 8-14 m off a manned aircraft's track that crossed
    it got to only 27-29 m of the 30 m berth (docs/sky.md, "Keeping a side"). Moving towards
    the track, m is kept as it is, with one exception: a vehicle on the other side but within
    the band (m > -NC_SIDE_BIAS r |v_j|, r the pair distance) that is escaping towards the side
    m > 0 faster than any guidance flies (its speed off the track above
    NC_KEEP_SIDE_SPEED_FACTOR vmax: only the escape speed does that) has had the track line
    swing across it, not crossed it, and keeps that side too (docs/sky.md, "A track line that
    swings across an escaping vehicle": a 20 m/s aircraft's line swung 9 m at 440 m and turned
    a vehicle back across it)."""
    jn = np.maximum(j_len, EPS)
    tx, ty = jx / jn, jy / jn
    along = -(px * tx + py * ty)
    closing = j_len - (own_x * tx + own_y * ty)
    t = np.where((along > 0) & (closing > EPS), along / np.maximum(closing, EPS), 0.0)
    m = px * jy - py * jx
    off_track = own_y * jx - own_x * jy  # own speed towards m > 0, times |v_j|
    keep = (m > 0) | _swung(m, off_track, j_len, r, vmax)
    return np.where(keep, np.maximum(m, m + t * off_track), m)


def _swung(m, off_track, j_len, r, vmax: float):
    """`kept_offset`'s exception (arrays or floats): within the band on the other side, and
    escaping towards m > 0 faster than guidance flies."""
    return (m > -NC_SIDE_BIAS * r * j_len) & (off_track > NC_KEEP_SIDE_SPEED_FACTOR * vmax * j_len)


def kept_offset_one(px, py, jx, jy, j_len, own_x, own_y, r: float, vmax: float) -> float:
    """`kept_offset` in Python floats."""
    m = px * jy - py * jx
    off_track = own_y * jx - own_x * jy
    if m <= 0 and not _swung(m, off_track, j_len, r, vmax):
        return m
    jn = EPS if j_len < EPS else j_len
    tx, ty = jx / jn, jy / jn
    along = -(px * tx + py * ty)
    closing = j_len - (own_x * tx + own_y * ty)
    if along <= 0 or closing <= EPS:
        return m
    return max(m, m + along / closing * off_track)


def step_aside(px, py, vx, vy, own_vel, r, vmax: float):
    """The step-aside rule for arrays (..., K) of pairs (own_vel (..., 2)):

    - steer: on a collision course (v inside the untruncated cone: v.p > 0 and |det(p, v)| <
      r |v|), where the velocity goes onto a leg of the cone, never the cut-off circle;
    - left: which leg. Off the neighbour's own track (p x v_j: this vehicle's offset from it,
      times |v_j|, or where it will be if it is leaving the track: `kept_offset`) when it is at
      least as fast as vmax (crossing ahead of it would let it catch us), else the side v leans
      to; within NC_SIDE_BIAS r of either, the right-hand leg;
    - side: what `escape` needs of the same geometry (fast, m, |v_j|, v_j).
    """
    det_pv = px * vy - py * vx
    v_len = np.sqrt(vx * vx + vy * vy)
    steer = (px * vx + py * vy > 0) & (np.abs(det_pv) < r * v_len)
    jx = own_vel[..., None, 0] - vx
    jy = own_vel[..., None, 1] - vy
    j_len = np.sqrt(jx * jx + jy * jy)
    fast = j_len >= vmax
    kept = kept_offset(px, py, jx, jy, j_len, own_vel[..., None, 0], own_vel[..., None, 1], r, vmax)
    m = np.where(fast, kept, -det_pv)
    left = m < NC_SIDE_BIAS * r * np.where(fast, j_len, v_len)
    return steer, left, (fast, m, j_len, jx, jy)


def clear_speed(off, along, closing, r, vmax: float, j_len):
    """The escape line's lateral speed (arrays or floats): NC_ESCAPE_SHARE vmax, or what clears
    the berth before the neighbour arrives when that is more, (r - off) / (along / closing), up
    to NC_CLEAR_SHARE of sqrt(V^2 - b^2). V is the escape speed (`escape_speed_m_s` of the
    neighbour, speed |v_j|); b is the speed the vehicle keeps along the neighbour's track, its
    own now (|v_j| - closing), at least 0 (the ahead line) and at most min(vmax, V^2 / |v_j|):
    with b(a) = min(b, sqrt(V^2 - a^2)) left along the track at lateral speed a, the room gained
    per metre the neighbour closes, a / (|v_j| - b(a)), peaks at a = sqrt(V^2 - b^2). A vehicle
    overtaken on its own track (b near vmax) thus keeps its speed along the track instead of
    spending it all sideways, and the intruder arrives later; one met head-on (b 0: it does not
    fly towards the intruder) steps aside at up to NC_CLEAR_SHARE V. The share keeps the escape
    line, the track line and the speed limit from meeting in one point. off: this vehicle's
    distance off the neighbour's track on the escape side; along: how far ahead of the neighbour
    along its track (> 0: it comes up behind); closing: how fast it gains."""
    base = NC_ESCAPE_SHARE * vmax
    speed = np.minimum(NC_ESCAPE_SPEED_FACTOR * vmax, np.maximum(vmax, j_len))
    best = np.minimum(vmax, speed * speed / np.maximum(j_len, EPS))
    ahead = np.minimum(np.maximum(j_len - closing, 0.0), best)
    cap = NC_CLEAR_SHARE * np.sqrt(np.maximum(speed * speed - ahead * ahead, 0.0))
    t = np.where((along > 0) & (closing > EPS), along / np.maximum(closing, EPS), np.inf)
    need = (r - off) / np.maximum(t, EPS)
    return np.maximum(base, np.minimum(need, cap))


def escape(active, side, r, vmax: float, point, direction, px=None, py=None, own_vel=None):
    """The escape rule for arrays: where `active` (non-cooperative, already within r, closing)
    and the neighbour is fast (`step_aside`'s side), the line "v . n >= s", n perpendicular to
    its velocity on the step-aside side and s `clear_speed` (with the pair's p = (px, py) and
    own_vel; without them NC_ESCAPE_SHARE vmax), replaces (point, direction), each a pair of
    (..., K) arrays. Returns the pair of pairs."""
    fast, m, j_len, jx, jy = side
    esc = active & fast
    if not esc.any():
        return point, direction
    jn = np.maximum(j_len, EPS)
    tx, ty = jx / jn, jy / jn
    sgn = np.where(m < NC_SIDE_BIAS * r * j_len, 1.0, -1.0)
    nx, ny = sgn * ty, -sgn * tx
    spd = NC_ESCAPE_SHARE * vmax
    if px is not None and own_vel is not None:
        off = -(px * nx + py * ny)
        along = -(px * tx + py * ty)
        closing = j_len - (own_vel[..., None, 0] * tx + own_vel[..., None, 1] * ty)
        spd = clear_speed(off, along, closing, r, vmax, j_len)
    (pt_x, pt_y), (dir_x, dir_y) = point, direction
    return (
        (np.where(esc, spd * nx, pt_x), np.where(esc, spd * ny, pt_y)),
        (np.where(esc, ny, dir_x), np.where(esc, -nx, dir_y)),
    )


def escape_one(px, py, vx, vy, own_vx, own_vy, r: float, vmax: float):
    """`escape` for one pair within r and closing, in Python floats: the line ((point),
    (direction)) when the neighbour is at least as fast as vmax, else None."""
    jx, jy = own_vx - vx, own_vy - vy
    j_len = math.sqrt(jx * jx + jy * jy)
    if j_len < vmax:
        return None
    jn = EPS if j_len < EPS else j_len
    m = kept_offset_one(px, py, jx, jy, j_len, own_vx, own_vy, r, vmax)
    sgn = 1.0 if m < NC_SIDE_BIAS * r * j_len else -1.0
    nx, ny = sgn * jy / jn, -sgn * jx / jn
    tx, ty = jx / jn, jy / jn
    spd = float(
        clear_speed(
            -(px * nx + py * ny),
            -(px * tx + py * ty),
            j_len - (own_vx * tx + own_vy * ty),
            r,
            vmax,
            j_len,
        )
    )
    return (spd * nx, spd * ny), (ny, -nx)


def step_aside_one(px, py, vx, vy, own_vx, own_vy, r: float, vmax: float):
    """`step_aside` for one pair in Python floats: (steer, left); left is None when not
    steering (the cone's own side test then holds)."""
    det_pv = px * vy - py * vx
    v_len = math.sqrt(vx * vx + vy * vy)
    if not (px * vx + py * vy > 0 and abs(det_pv) < r * v_len):
        return False, None
    jx, jy = own_vx - vx, own_vy - vy
    j_len = math.sqrt(jx * jx + jy * jy)
    if j_len >= vmax:
        return True, kept_offset_one(px, py, jx, jy, j_len, own_vx, own_vy, r, vmax) < (
            NC_SIDE_BIAS * r * j_len
        )
    return True, -det_pv < NC_SIDE_BIAS * r * v_len
