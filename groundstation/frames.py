"""The one conversion between covey's local NED frame and the viser scene frame.

viser's world is Z-up (its default), so the scene frame is ENU: x = east, y = north, z = up.
    scene = (e, n, -d)        ned = (y, x, -z)
"""

from __future__ import annotations

import math

import numpy as np


def ned_to_scene(ned_m: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """NED metres (..., 3) -> scene metres (..., 3): (n, e, d) -> (e, n, -d)."""
    if isinstance(ned_m, tuple):  # one position: the common case, 10x cheaper than np.stack
        n, e, d = ned_m
        return np.array((e, n, -d), dtype=np.float32)
    ned = np.asarray(ned_m, dtype=np.float32)
    return np.stack([ned[..., 1], ned[..., 0], -ned[..., 2]], axis=-1)


def scene_to_ned(scene_m: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """Scene metres (..., 3) -> NED metres (..., 3); the inverse of ned_to_scene."""
    xyz = np.asarray(scene_m, dtype=np.float64)
    return np.stack([xyz[..., 1], xyz[..., 0], -xyz[..., 2]], axis=-1)


def heading_to_wxyz(heading_rad: np.ndarray | float) -> np.ndarray:
    """Quaternions (..., 4) (w, x, y, z) of bodies with NED headings (...) (0 = north,
    clockwise) in the scene; float32.

    North is scene +y and clockwise-from-above is a negative rotation about +z, so a body whose
    nose points along its +y axis turns by yaw = -heading about z.
    """
    half = -0.5 * np.asarray(heading_rad, dtype=np.float64)
    wxyz = np.zeros((*half.shape, 4), np.float32)
    wxyz[..., 0] = np.cos(half)
    wxyz[..., 3] = np.sin(half)
    return wxyz


def ground_hit_ned(
    ray_origin: tuple[float, float, float], ray_direction: tuple[float, float, float]
) -> tuple[float, float] | None:
    """(north_m, east_m) where a scene-frame click ray meets the ground (z = 0), or None."""
    ox, oy, oz = ray_origin
    dx, dy, dz = ray_direction
    if not all(math.isfinite(v) for v in (ox, oy, oz, dx, dy, dz)) or dz >= -1e-9:
        return None  # looking up or along the ground: no hit in front of the camera
    t = -oz / dz
    if t < 0:
        return None
    return float(oy + t * dy), float(ox + t * dx)
