"""Geometry the scene draws, as plain numpy arrays in the scene frame (metres, z up).

Meshes are (vertices (V, 3) float32, faces (F, 3) uint32), drawn once per vehicle by a batched
mesh node; line layers are (S, 2, 3) float32 segments and trails (P, 3) dots, one node each for
the whole fleet.
"""

from __future__ import annotations

import math

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def box_mesh(size_m: tuple[float, float, float]) -> Mesh:
    """A box centred on the origin, `size_m` = (x, y, z) edge lengths, outward-facing triangles."""
    hx, hy, hz = (s / 2.0 for s in size_m)
    v = np.array([[x, y, z] for z in (-hz, hz) for y in (-hy, hy) for x in (-hx, hx)], np.float32)
    # Corner k has x = bit 0, y = bit 1, z = bit 2; two counter-clockwise triangles per side.
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = [(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads]
    return v, np.array(faces, np.uint32)


def band_mesh(radius_m: float, height_m: float, n: int = 48) -> Mesh:
    """A short open cylinder wall around the z axis, centred on z = 0 (draw with side="double").
    Its sides face sideways, so the lights do not wash out its colour as they would a flat ring."""
    a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    ring = np.stack([radius_m * np.cos(a), radius_m * np.sin(a), np.zeros_like(a)], axis=-1)
    up = np.array([0.0, 0.0, height_m / 2.0])
    v = np.concatenate([ring - up, ring + up])
    i = np.arange(n)
    j = (i + 1) % n
    faces = np.concatenate([np.stack([i, j, n + j], -1), np.stack([i, n + j, n + i], -1)])
    return v.astype(np.float32), faces.astype(np.uint32)


def icosahedron_mesh(radius_m: float) -> Mesh:
    """A 20-sided ball: the goal marker."""
    p = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [
            (-1, p, 0),
            (1, p, 0),
            (-1, -p, 0),
            (1, -p, 0),
            (0, -1, p),
            (0, 1, p),
            (0, -1, -p),
            (0, 1, -p),
            (p, 0, -1),
            (p, 0, 1),
            (-p, 0, -1),
            (-p, 0, 1),
        ],
        np.float32,
    )
    faces = [
        (0, 11, 5),
        (0, 5, 1),
        (0, 1, 7),
        (0, 7, 10),
        (0, 10, 11),
        (1, 5, 9),
        (5, 11, 4),
        (11, 10, 2),
        (10, 7, 6),
        (7, 1, 8),
        (3, 9, 4),
        (3, 4, 2),
        (3, 2, 6),
        (3, 6, 8),
        (3, 8, 9),
        (4, 9, 5),
        (2, 4, 11),
        (6, 2, 10),
        (8, 6, 7),
        (9, 8, 1),
    ]
    return v * (radius_m / np.linalg.norm(v[0])), np.array(faces, np.uint32)


def circle_segments(radius_m: float, n: int = 48, z_m: float = 0.0) -> np.ndarray:
    """(n, 2, 3) line segments of a horizontal circle in the scene frame."""
    a = np.linspace(0.0, 2.0 * math.pi, n + 1)
    pts = np.stack([radius_m * np.cos(a), radius_m * np.sin(a), np.full_like(a, z_m)], axis=-1)
    return np.stack([pts[:-1], pts[1:]], axis=1).astype(np.float32)


def fence_label_position(radius_m: float) -> tuple[float, float, float]:
    """Where the geofence's label sits in the scene frame (x east, y north, z up): on the
    circle due north of the origin, straight ahead of the station's initial camera (which
    looks north from the south, so the southern arc is behind it)."""
    return (0.0, radius_m, 0.3)


def thin(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most `max_points` of (K, 3) points, evenly spread, first and latest kept."""
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).round().astype(int)]


def padded_points(polylines: list[np.ndarray], points_each: int) -> np.ndarray:
    """Each (K, 3) polyline (1 <= K <= points_each) padded to points_each points by repeating its
    latest, all stacked (N * points_each, 3): the shape depends only on how many there are."""
    pts = np.zeros((len(polylines), points_each, 3), np.float32)
    for i, line in enumerate(polylines):
        pts[i, : len(line)] = line
        pts[i, len(line) :] = line[-1]
    return pts.reshape(-1, 3)
