"""Demo scenarios: goals for every vehicle at once (pure; the caller sends them).

- swap: the vehicles take evenly spaced slots on a circle, in the order of their bearing from
  the circle's centre, and each flies to the slot opposite its own; every path crosses the middle,
  the classic test of collision avoidance.
- random goals: uniformly in a disc, at least `min_spacing_m` apart.
"""

from __future__ import annotations

import math

import numpy as np

DEFAULT_ALT_M = 5.0


def _alt_d_m(pos_ned_m: tuple[float, float, float], default_alt_m: float) -> float:
    """Keep an airborne vehicle's altitude; send a landed one to the default altitude."""
    return pos_ned_m[2] if -pos_ned_m[2] > 1.0 else -default_alt_m


def swap_goals(
    positions: dict[int, tuple[float, float, float]],
    radius_m: float,
    center_ne_m: tuple[float, float] = (0.0, 0.0),
    default_alt_m: float = DEFAULT_ALT_M,
) -> dict[int, tuple[float, float, float]]:
    """NED goal per vehicle: the antipode of its slot on a circle of `radius_m` around the centre."""
    if not positions:
        return {}
    cn, ce = center_ne_m
    # Bearing from the centre, clockwise from north: atan2(e, n).
    order = sorted(
        positions, key=lambda v: (math.atan2(positions[v][1] - ce, positions[v][0] - cn), v)
    )
    n = len(order)
    goals = {}
    for slot, vid in enumerate(order):
        # Slots follow the bearing order from -pi; the goal is the slot's antipode (+pi).
        angle = -math.pi + 2.0 * math.pi * (slot + 0.5) / n + math.pi
        goals[vid] = (
            cn + radius_m * math.cos(angle),
            ce + radius_m * math.sin(angle),
            _alt_d_m(positions[vid], default_alt_m),
        )
    return goals


def random_goals(
    positions: dict[int, tuple[float, float, float]],
    radius_m: float,
    rng: np.random.Generator,
    min_spacing_m: float = 4.0,
    default_alt_m: float = DEFAULT_ALT_M,
) -> dict[int, tuple[float, float, float]]:
    """NED goal per vehicle, uniform in a disc of `radius_m` around the origin, spaced apart."""
    chosen: list[tuple[float, float]] = []
    goals = {}
    for vid in sorted(positions):
        for _ in range(200):
            # Uniform in a disc: r = R sqrt(u).
            r = radius_m * math.sqrt(rng.random())
            a = 2.0 * math.pi * rng.random()
            cand = (r * math.cos(a), r * math.sin(a))
            if all(math.dist(cand, c) >= min_spacing_m for c in chosen):
                break
        chosen.append(cand)
        goals[vid] = (cand[0], cand[1], _alt_d_m(positions[vid], default_alt_m))
    return goals
