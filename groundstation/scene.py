"""The 3D scene: renders a FleetSnapshot into viser handles (one subtree per vehicle).

    /ground, /geofence, /origin                       static
    /vehicles/<id>                                    frame at the vehicle's position
    /vehicles/<id>/body | label | ring | velocity | stalk
    /goals/<id>, /trails/<id>                         in world coordinates

Handles are created once and changed by assigning properties, and only when the value changed,
so an update burst carries just what moved. The caller wraps `update` in `server.atomic()`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from groundstation.fleet import FleetSnapshot, VehicleView
from groundstation.frames import heading_to_wxyz, ned_to_scene
from groundstation.palette import (
    ALERT_RGB,
    GEOFENCE_RGB,
    GOAL_RGB,
    LOST_RGB,
    RING_OK_RGB,
    mode_rgb,
)

# Shadows need an extra render pass per light; without a GPU (software WebGL) that halves the frame
# rate, and an operator reads height from the stalks and labels anyway.
NO_SHADOW = {"cast_shadow": False, "receive_shadow": False}
HEADING_STEP_RAD = math.radians(2.0)


def circle_segments(radius_m: float, n: int = 48, z_m: float = 0.0) -> np.ndarray:
    """(n, 2, 3) line segments of a horizontal circle in the scene frame."""
    a = np.linspace(0.0, 2.0 * math.pi, n + 1)
    pts = np.stack([radius_m * np.cos(a), radius_m * np.sin(a), np.full_like(a, z_m)], axis=-1)
    return np.stack([pts[:-1], pts[1:]], axis=1).astype(np.float32)


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """(K, 3) points -> (K-1, 2, 3) segments (at least one, degenerate if K < 2)."""
    if len(points) < 2:
        p = points[0] if len(points) else np.zeros(3, np.float32)
        return np.stack([p, p])[None].astype(np.float32)
    return np.stack([points[:-1], points[1:]], axis=1).astype(np.float32)


def _rgb(rgb: tuple[int, int, int]) -> np.ndarray:
    """One colour for a whole line-segments node (viser accepts shape (3,))."""
    return np.array(rgb, np.uint8)


@dataclass
class _VehicleHandles:
    frame: Any
    body: Any
    label: Any
    ring: Any
    velocity: Any
    stalk: Any
    goal: Any
    trail: Any
    cache: dict[str, Any] = field(default_factory=dict)

    def set(
        self, key: str, handle: Any, prop: str, value: Any, make: Callable[[Any], Any] | None = None
    ) -> None:
        """Assign handle.prop = make(value) (or value) unless `value` is what was set last time."""
        marker = value.tobytes() if isinstance(value, np.ndarray) else value
        if self.cache.get(key) != marker:
            self.cache[key] = marker
            setattr(handle, prop, make(value) if make is not None else value)


@dataclass(frozen=True)
class SceneConfig:
    """How the scene looks."""

    geofence_radius_m: float = 50.0
    """Radius of the geofence circle around the origin, in metres (0 = none drawn)."""
    separation_m: float = 3.0
    """Separation distance; each vehicle's ring has half this radius, so rings touch at it."""
    trail_spread_updates: int = 10
    """Each vehicle's trail is re-sent every this many updates (1 s at 10 Hz), a slice of the
    fleet per update, so that no single update carries every trail (they are the heaviest part)."""
    trail_max_points: int = 120
    """Trails are thinned to at most this many points when sent (500 vehicles x 300 points is
    too much to re-send every second)."""
    velocity_scale_s: float = 1.0
    """Velocity arrows show where the vehicle will be in this many seconds."""


class FleetScene:
    """Owns every scene handle of the fleet. Call `update(snapshot)` from one thread."""

    def __init__(self, server: viser.ViserServer, cfg: SceneConfig,
                 on_vehicle_click: Callable[[int], None] | None = None) -> None:  # fmt: skip
        self.server = server
        self.cfg = cfg
        self._on_vehicle_click = on_vehicle_click
        self._vehicles: dict[int, _VehicleHandles] = {}
        self._trail_tick = 0
        scene = server.scene
        # No environment map and no shadow-casting lights: both cost seconds of CPU per frame set-up
        # without a GPU, and flat lighting reads fine for boxes and lines.
        scene.configure_environment_map(hdri=None)
        scene.configure_default_lights(enabled=True, cast_shadow=False)
        # The environment map also lit the shaded sides; a sky/ground light stands in for it.
        scene.add_light_hemisphere(
            "/light/sky", sky_color=(255, 255, 255), ground_color=(180, 180, 180), intensity=1.2
        )
        extent_m = max(20.0, 2.2 * cfg.geofence_radius_m)
        scene.add_grid("/ground", width=extent_m, height=extent_m, cell_size=1.0, section_size=10.0,
                       plane="xy", fade_distance=4 * extent_m, shadow_opacity=0.0, plane_color=(235, 240, 235),
                       plane_opacity=0.6)  # fmt: skip
        if cfg.geofence_radius_m > 0:
            ring = circle_segments(cfg.geofence_radius_m, 128, 0.02)
            scene.add_line_segments("/geofence", ring, _rgb(GEOFENCE_RGB), thickness=4.0,
                                    thickness_units="screen")  # fmt: skip
        scene.add_frame("/origin", axes_length=2.0, axes_radius=0.06)
        self.target_marker = scene.add_icosphere("/target", radius=0.4, color=GOAL_RGB, opacity=0.6, cast_shadow=False, receive_shadow=False,
                                                 visible=False)  # fmt: skip

    def _create(self, vid: int) -> _VehicleHandles:
        scene = self.server.scene
        root = f"/vehicles/{vid}"
        ring = circle_segments(self.cfg.separation_m / 2.0)
        h = _VehicleHandles(
            frame=scene.add_frame(root, show_axes=False),
            body=scene.add_box(f"{root}/body", color=mode_rgb(None), dimensions=(0.6, 0.9, 0.25), **NO_SHADOW),
            label=scene.add_label(f"{root}/label", f"{vid}", position=(0.0, 0.0, 0.7),
                                  anchor="bottom-center", font_screen_scale=0.9),
            ring=scene.add_line_segments(f"{root}/ring", ring, _rgb(RING_OK_RGB),
                                         thickness=2.0, thickness_units="screen"),
            velocity=scene.add_arrows(f"{root}/velocity", np.zeros((1, 2, 3), np.float32), (20, 20, 20),
                                      shaft_radius=0.05, head_radius=0.15, head_length=0.3),
            stalk=scene.add_line_segments(f"{root}/stalk", np.zeros((1, 2, 3), np.float32),
                                          (120, 120, 120), thickness=1.0, thickness_units="screen"),
            goal=scene.add_icosphere(f"/goals/{vid}", radius=0.35, color=GOAL_RGB, visible=False, subdivisions=2, **NO_SHADOW),
            trail=scene.add_line_segments(f"/trails/{vid}", np.zeros((1, 2, 3), np.float32),
                                          (120, 120, 120), thickness=2.0, thickness_units="screen"),
        )  # fmt: skip
        if self._on_vehicle_click is not None:
            cb = self._on_vehicle_click
            h.body.on_click(lambda _event, vid=vid: cb(vid))
        return h

    def trail_ids(self, ids: list[int]) -> set[int]:
        """The vehicles whose trails the next update should carry (round robin over `ids`)."""
        k = max(1, self.cfg.trail_spread_updates)
        tick, self._trail_tick = self._trail_tick, self._trail_tick + 1
        return {vid for i, vid in enumerate(sorted(ids)) if i % k == tick % k}

    def update(self, snap: FleetSnapshot, send_trails: bool = True) -> None:
        """Draw `snap`. Trails are drawn for the vehicles whose trail the snapshot carries."""
        for v in snap.vehicles:
            h = self._vehicles.get(v.vehicle_id)
            if h is None:
                h = self._vehicles[v.vehicle_id] = self._create(v.vehicle_id)
            self._update_vehicle(h, v, send_trails)
        gone = set(self._vehicles) - {v.vehicle_id for v in snap.vehicles}
        for vid in gone:
            h = self._vehicles.pop(vid)
            for handle in (h.frame, h.goal, h.trail):
                handle.remove()

    def _update_vehicle(self, h: _VehicleHandles, v: VehicleView, send_trails: bool) -> None:
        # Values are quantised (1 cm, 2 deg, 0.1 m/s) so that a hovering vehicle sends nothing and a
        # moving one sends only what an operator could see change.
        s = v.state
        if s is None:
            h.set("visible", h.frame, "visible", False)
            return
        h.set("visible", h.frame, "visible", True)
        x, y, z = (float(c) for c in ned_to_scene(s.pos_ned_m))
        h.set("pos", h.frame, "position", (round(x, 2), round(y, 2), round(z, 2)))
        h.set(
            "wxyz",
            h.body,
            "wxyz",
            heading_to_wxyz(round(s.heading_rad / HEADING_STEP_RAD) * HEADING_STEP_RAD),
        )
        lost = not v.alive
        colour = LOST_RGB if lost else mode_rgb(s.mode)
        h.set("color", h.body, "color", colour)
        status = "LOST" if lost else ("STALE" if v.stale else s.mode.name)
        h.set(
            "text", h.label, "text", f"{v.vehicle_id} {status} {v.alt_m:.1f}m {s.battery_pct:.0f}%"
        )
        h.set("ring", h.ring, "colors", ALERT_RGB if v.too_close else RING_OK_RGB, _rgb)
        vx, vy, vz = (
            round(float(c) * self.cfg.velocity_scale_s, 1) for c in ned_to_scene(s.vel_ned_m_s)
        )
        moving = abs(vx) + abs(vy) + abs(vz) > 0.0
        h.set("vel_vis", h.velocity, "visible", moving)
        if moving:
            h.set(
                "vel",
                h.velocity,
                "points",
                (vx, vy, vz),
                lambda p: np.array([[[0, 0, 0], p]], np.float32),
            )
        h.set(
            "stalk",
            h.stalk,
            "points",
            round(max(0.0, z), 1),
            lambda a: np.array([[[0, 0, 0], [0, 0, -a]]], np.float32),
        )
        h.set("goal_vis", h.goal, "visible", v.has_goal and not lost)
        if v.has_goal:
            h.set(
                "goal",
                h.goal,
                "position",
                tuple(round(float(c), 2) for c in ned_to_scene(s.goal_ned_m)),
            )
            h.set("goal_rgb", h.goal, "color", colour)
        if send_trails and len(v.trail_ned_m):
            trail = v.trail_ned_m
            if len(trail) > self.cfg.trail_max_points:
                keep = np.linspace(0, len(trail) - 1, self.cfg.trail_max_points).round().astype(int)
                trail = trail[keep]  # evenly thinned, first and latest points kept
            h.set("trail", h.trail, "points", polyline_segments(ned_to_scene(trail)))
            h.set("trail_rgb", h.trail, "colors", colour, _rgb)
