"""Evaluation scenarios in policy units (3 m separation, 1 m/s): starts and goals."""

from __future__ import annotations

import math

import numpy as np


def antipodal_circle(n: int, spacing_m: float = 6.0, min_radius_m: float = 20.0):
    """n vehicles evenly on a circle, each bound for the opposite point.

    The radius keeps neighbours spacing_m apart along the circle.
    """
    r = max(min_radius_m, spacing_m * n / (2 * math.pi))
    ang = 2 * math.pi * np.arange(n) / n
    starts = r * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    return starts, -starts


def _spread(rng, n, sample, min_gap_m, tries=2000):
    pts = []
    for _ in range(n):
        for _ in range(tries):
            p = sample()
            if all(math.dist(p, q) >= min_gap_m for q in pts):
                break
        pts.append(p)
    return np.array(pts).reshape(n, 2)


def random_conflict(
    rng: np.random.Generator, n: int, radius_m: float = 25.0, jitter_m: float = 6.0
):
    """Forced conflicts: starts on a circle at random angles, goals near the opposite
    side, so that all straight paths cross close to the centre."""

    def on_circle():
        a = rng.uniform(0, 2 * math.pi)
        return np.array([math.cos(a), math.sin(a)]) * radius_m

    starts = _spread(rng, n, on_circle, 6.0)
    goals = -starts + rng.uniform(-jitter_m, jitter_m, (n, 2))
    # goals apart too: nudge any pair closer than 6 m apart
    for i in range(n):
        for j in range(i):
            if math.dist(goals[i], goals[j]) < 6.0:
                goals[i] = -starts[i]
    return starts, goals


def random_large(rng: np.random.Generator, n: int, min_gap_m: float = 10.0):
    """n random starts and goals in a square that grows with n (side 20 sqrt(n), >= 60 m)."""
    side = max(60.0, 20.0 * math.sqrt(n))
    starts = _spread(rng, n, lambda: rng.uniform(0, side, 2), min_gap_m)
    goals = np.zeros_like(starts)
    for i in range(n):
        for _ in range(2000):
            g = rng.uniform(0, side, 2)
            if math.dist(g, starts[i]) >= min_gap_m and all(
                math.dist(g, goals[j]) >= min_gap_m for j in range(i)
            ):
                break
        goals[i] = g
    return starts, goals
