"""ORCA's linear program: the velocity closest to a preferred one inside a set of half-planes
and a speed disc, with the fallback that minimises the worst violation when none meets them all
(van den Berg et al. 2011; RVO2's linearProgram1-3). Lines are [((px, py), (dx, dy))]; the
allowed side of each is det(d, p - v) <= 0. The first n_hard lines (keep-out zones, traffic
that does not cooperate) are never relaxed. policy.safety builds the lines; the C twin is
firmware/covey_safety.c covey_safety_solve.
"""

from __future__ import annotations

import numpy as np

EPS = 1e-9


def _det(ax, ay, bx, by):
    return ax * by - ay * bx


def _lp1(lines, n, radius, opt, direction_opt):
    # _det inlined and min / max as comparisons (the same values, NaN included): the hot path
    (px, py), (dx, dy) = lines[n]
    dot = px * dx + py * dy
    disc = dot * dot + radius * radius - (px * px + py * py)
    if disc < 0.0:
        return None
    sq = disc**0.5
    t_left, t_right = -dot - sq, -dot + sq
    for i in range(n):
        (qx, qy), (ex, ey) = lines[i]
        denom = dx * ey - dy * ex  # _det(dx, dy, ex, ey)
        numer = ex * (py - qy) - ey * (px - qx)  # _det(ex, ey, px - qx, py - qy)
        if abs(denom) <= EPS:
            if numer < 0.0:
                return None
            continue
        t = numer / denom
        if denom >= 0.0:
            if t < t_right:  # min(t_right, t)
                t_right = t
        elif t > t_left:  # max(t_left, t)
            t_left = t
        if t_left > t_right:
            return None
    if direction_opt:
        t = t_right if opt[0] * dx + opt[1] * dy > 0.0 else t_left
    else:
        t = dx * (opt[0] - px) + dy * (opt[1] - py)
        t = t_left if t_left > t else t  # max(t, t_left)
        t = t_right if t_right < t else t  # min(t, t_right)
    return (px + t * dx, py + t * dy)


def _lp2(lines, radius, opt, direction_opt):
    if direction_opt:
        result = (opt[0] * radius, opt[1] * radius)
    else:
        n = (opt[0] ** 2 + opt[1] ** 2) ** 0.5
        result = opt if n <= radius else (opt[0] / n * radius, opt[1] / n * radius)
    rx, ry = result
    for i, ((px, py), (dx, dy)) in enumerate(lines):
        if dx * (py - ry) - dy * (px - rx) > 0.0:  # _det(dx, dy, px - rx, py - ry)
            new = _lp1(lines, i, radius, opt, direction_opt)
            if new is None:
                return i, (rx, ry)
            rx, ry = new
    return len(lines), (rx, ry)


def _lp3(lines, begin, radius, result, n_hard=0):
    # lines[:n_hard] are hard (keep-out zones, policy.zone_lines): they stay as they are in
    # every projected program, so only the others are relaxed (RVO2's numObstLines)
    distance = 0.0
    for i in range(max(begin, n_hard), len(lines)):
        (px, py), (dx, dy) = lines[i]
        if _det(dx, dy, px - result[0], py - result[1]) > distance:
            proj = list(lines[:n_hard])
            for j in range(n_hard, i):
                (qx, qy), (ex, ey) = lines[j]
                determinant = _det(dx, dy, ex, ey)
                if abs(determinant) <= EPS:
                    if dx * ex + dy * ey > 0.0:
                        continue
                    point = (0.5 * (px + qx), 0.5 * (py + qy))
                else:
                    t = _det(ex, ey, px - qx, py - qy) / determinant
                    point = (px + t * dx, py + t * dy)
                nx, ny = ex - dx, ey - dy
                nn = max((nx * nx + ny * ny) ** 0.5, EPS)
                proj.append((point, (nx / nn, ny / nn)))
            fail, new = _lp2(proj, radius, (-dy, dx), True)
            if fail >= len(proj):
                result = new
            distance = _det(dx, dy, px - result[0], py - result[1])
    return result


def solve(point, direction, pref_vel, max_speed, hard=(), n_optional=0):
    """Velocity closest to pref_vel inside all half-planes and |v| <= max_speed.

    When infeasible, minimises the largest violation (ORCA's fallback). `hard` lines
    [((px, py), (dx, dy))] (keep-out zones) go first and are never relaxed (`solve_lines`;
    n_optional: its last lines that are dropped first).
    """
    lines = [
        ((float(p[0]), float(p[1])), (float(d[0]), float(d[1])))
        for p, d in zip(point, direction, strict=True)
    ]
    return solve_lines(
        list(hard) + lines,
        (float(pref_vel[0]), float(pref_vel[1])),
        max_speed,
        len(hard),
        n_optional,
    )


def solve_lines(lines, pref, max_speed, n_hard=0, n_optional=0):
    """`solve` on lines [((px, py), (dx, dy))], the first n_hard of them hard: when the rest
    cannot all be met, the worst violation of the rest is minimised inside the hard ones. Hard
    lines that cannot be met together (never for zone lines outside their radius: v = 0 meets
    them) are relaxed with the rest, after the last n_optional of them are dropped (the escape
    speed's track line, policy.traffic_rules.escape_lines). The C twin is covey_safety.c
    covey_safety_solve."""
    if not lines:
        return _clip_speed(np.array(pref, dtype=np.float64), max_speed)
    fail, result = _lp2(lines, max_speed, pref, False)
    if fail < n_hard and n_optional:
        lines = list(lines[: n_hard - n_optional]) + list(lines[n_hard:])
        n_hard -= n_optional
        fail, result = _lp2(lines, max_speed, pref, False)
    if fail < len(lines):
        result = _lp3(lines, fail, max_speed, result, n_hard if fail >= n_hard else 0)
    return np.array(result)


def _clip_speed(v, max_speed):
    n = np.hypot(v[..., 0], v[..., 1])
    return v * (max_speed / np.maximum(n, max_speed))[..., None]
