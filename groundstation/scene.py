"""The 3D scene: renders a FleetSnapshot into a constant number of viser nodes.

    /ground, /geofence, /origin, /target                static
    /fleet/bodies, /fleet/rings, /fleet/goals           batched meshes, one instance per vehicle
    /fleet/velocity, /fleet/stalks                      line segments, every vehicle in one node
    /fleet/trails                                       point cloud, every vehicle's trail
    /labels/<id>                                        only a few (see SceneConfig.labels_*)
    /traffic/<track>/body, ring, label                  traffic that does not cooperate (few)
    /plan/fence, /plan/zones/<k>/{fill,edge,label},      the fleet plan (comms/plan.py) on the
    /plan/rally/<k>                                     ground: fence, keep-out zones, rally points

A browser pays per scene node (a draw call, a React component, an update message), so the fleet
is drawn in batches: the node count does not grow with the fleet. Trails are dots: as one line node
(a quad instance per segment) they cut software WebGL's frame rate by 3x at 100 vehicles. Nodes are
rebuilt only when the set of drawn vehicles changes; otherwise their arrays are re-assigned, and
only when the quantised value changed, so an update burst carries just what moved. The caller wraps
`update` in `server.atomic()`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, TypedDict

import numpy as np
import viser

from comms.plan import FleetPlan, RallyPoint, rally_numbers
from comms.schema import Mode, VehicleState
from groundstation import scene_geometry as geo
from groundstation.fleet import FleetSnapshot, VehicleView
from groundstation.frames import heading_to_wxyz, ned_to_scene
from groundstation.palette import (
    ALERT_RGB,
    GEOFENCE_RGB,
    GOAL_RGB,
    KEEP_OUT_RGB,
    LOST_RGB,
    RING_OK_RGB,
    TRAFFIC_RGB,
    mode_rgb,
)


# Shadows need an extra render pass per light; without a GPU (software WebGL) that halves the frame
# rate, and an operator reads height from the stalks and labels anyway.
class _Shadows(TypedDict):
    cast_shadow: bool
    receive_shadow: bool


NO_SHADOW: _Shadows = {"cast_shadow": False, "receive_shadow": False}
HEADING_STEP_RAD = math.radians(2.0)
BODY_SIZE_M = (0.6, 0.9, 0.25)
LABEL_HEIGHT_M = 0.7
VELOCITY_RGB = (20, 20, 20)
STALK_RGB = (120, 120, 120)


@dataclass(frozen=True)
class SceneConfig:
    """How the scene looks."""

    geofence_radius_m: float = 50.0
    """Radius of the geofence circle around the origin, in metres (0 = none drawn)."""
    separation_m: float = 3.0
    """Separation distance; each vehicle's ring has half this radius, so rings touch at it."""
    trail_spread_updates: int = 10
    """Each vehicle's trail is read from the model every this many updates (1 s at 10 Hz), a
    slice of the fleet per update (`trail_ids`), so that no update copies every trail; the one
    trail node is re-sent once every vehicle's trail has been read again."""
    trail_max_points: int = 60
    """Trails are thinned to this many dots when sent (every vehicle's trail takes this many,
    padded, so the trail node keeps its shape)."""
    trail_dot_m: float = 0.12
    """Diameter of a trail dot, in metres."""
    velocity_scale_s: float = 1.0
    """Velocity lines show where the vehicle will be in this many seconds."""
    labels_all_max_vehicles: int = 20
    """Every vehicle is labelled up to this fleet size. Above it, only vehicles that need the
    operator (lost, stale, too close) are, at most `labels_max` of them: 100 labels halved the
    frame rate in Chromium without a GPU (bench/gcs_browser: 6.8 -> 3.0 frames/s)."""
    labels_max: int = 20
    """At most this many labels above `labels_all_max_vehicles` vehicles."""
    traffic_separation_m: float | None = None
    """The berth kept from traffic that does not cooperate (its ring's radius less half the
    separation); None: the separation."""


@dataclass(frozen=True)
class _Fleet:
    """The drawn vehicles' quantised values, as arrays in `ids` order."""

    ids: tuple[int, ...]
    pos_m: np.ndarray  # (N, 3) scene frame, 1 cm
    wxyz: np.ndarray  # (N, 4) heading in 2-degree steps
    rgb: np.ndarray  # (N, 3) uint8, by mode; lost = grey
    vel_m: np.ndarray  # (N, 3) where it will be in velocity_scale_s, 0.1 m
    ring_rgb: np.ndarray  # (N, 3) uint8
    goal_m: np.ndarray  # (N, 3)
    goal_scale: np.ndarray  # (N,) 1 with a goal, 0 (hidden) without


def _xyz(rows: list) -> np.ndarray:
    """NED rows -> (N, 3) scene-frame float32, also for N = 0."""
    return ned_to_scene(np.array(rows, np.float32).reshape(-1, 3))


def _state_of(view: VehicleView) -> VehicleState:
    if view.state is None:
        raise ValueError(f"vehicle {view.vehicle_id} has no state to draw")
    return view.state


def _fleet(vehicles: list[VehicleView], velocity_scale_s: float) -> _Fleet:
    states = [_state_of(v) for v in vehicles]
    heading = np.fromiter((s.heading_rad for s in states), np.float64, count=len(states))
    with_goal = [v.has_goal and v.alive for v in vehicles]
    return _Fleet(
        ids=tuple(v.vehicle_id for v in vehicles),
        pos_m=_xyz([s.pos_ned_m for s in states]).round(2),
        wxyz=heading_to_wxyz(np.round(heading / HEADING_STEP_RAD) * HEADING_STEP_RAD),
        rgb=np.array(
            [
                mode_rgb(s.mode) if v.alive else LOST_RGB
                for v, s in zip(vehicles, states, strict=True)
            ],
            np.uint8,
        ),
        vel_m=(_xyz([s.vel_ned_m_s for s in states]) * velocity_scale_s).round(1),
        ring_rgb=np.array([ALERT_RGB if v.too_close else RING_OK_RGB for v in vehicles], np.uint8),
        goal_m=_xyz(
            [s.goal_ned_m if g else (0.0, 0.0, 0.0) for s, g in zip(states, with_goal, strict=True)]
        ).round(2),
        goal_scale=np.array(with_goal, np.float32),
    )


def traffic_label(track: Any, now_s: float) -> str:
    """What a traffic marker says: TRF, its track id, what it is, its speed and age."""
    speed_m_s = math.hypot(*track.vel_ned_m_s[:2])
    kind = "manned" if track.manned else "unmanned"
    age_s = max(0.0, now_s - track.stamp_s)
    return (
        f"TRF {track.track_id:X} {track.source.name} {kind} {speed_m_s:.1f}m/s "
        f"{-track.pos_ned_m[2]:.0f}m {age_s:.1f}s"
    )


def label_text(v: VehicleView) -> str:
    s = v.state
    assert s is not None
    status = "LOST" if not v.alive else ("STALE" if v.stale else s.mode.name)
    return f"{v.vehicle_id} {status} {v.alt_m:.1f}m {s.battery_pct:.0f}%"


class FleetScene:
    """Owns every scene handle of the fleet. Call `update(snapshot)` from one thread."""

    def __init__(
        self,
        server: viser.ViserServer,
        cfg: SceneConfig,
        on_vehicle_click: Callable[[int, int | None, bool], None] | None = None,
    ) -> None:
        """`on_vehicle_click(vehicle id, client id, add)`: a vehicle was clicked in a tab (its
        body or its separation ring); `add` when shift was held (add it to the selection)."""
        self.server = server
        self.cfg = cfg
        self._on_vehicle_click = on_vehicle_click
        self.ids: tuple[int, ...] = ()
        """The drawn vehicles (those with a state), in batch-instance order."""
        self.nodes: dict[str, Any] = {}
        """The fleet's batched nodes by layer: bodies, rings, goals, velocity, stalks, trails."""
        self.labels: dict[int, Any] = {}
        self._label_sent: dict[int, tuple] = {}
        self.sent: dict[str, Any] = {}
        """What was last assigned to each node property (quantised), to send only changes."""
        self._trails: dict[int, np.ndarray] = {}
        self.traffic: dict[int, dict[str, Any]] = {}
        self.plan_nodes: list[Any] = []
        self.route_nodes: dict[int, Any] = {}
        """Each vehicle's mission route (`update_routes`)."""
        """The drawn fleet plan's nodes (`update_plan`)."""
        """Drawn traffic by track id: its body (a magenta diamond), its ring and its label."""
        self._fresh: set[int] = set()
        self._trail_tick = 0
        self._meshes = {
            "bodies": geo.box_mesh(BODY_SIZE_M),
            "rings": geo.band_mesh(cfg.separation_m / 2.0, 0.15),
            "goals": geo.icosahedron_mesh(0.35),
        }
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
        scene.add_grid(
            "/ground",
            width=extent_m,
            height=extent_m,
            cell_size=1.0,
            section_size=10.0,
            plane="xy",
            fade_distance=4 * extent_m,
            shadow_opacity=0.0,
            plane_color=(235, 240, 235),
            plane_opacity=0.6,
        )
        if cfg.geofence_radius_m > 0:
            ring = geo.circle_segments(cfg.geofence_radius_m, 128, 0.02)
            scene.add_line_segments(
                "/geofence",
                ring,
                np.array(GEOFENCE_RGB, np.uint8),
                thickness=4.0,
                thickness_units="screen",
            )
            # Said where it is drawn: an unlabelled orange arc reads as anything.
            at_m = geo.fence_label_position(cfg.geofence_radius_m)
            self.fence_label = scene.add_label(
                "/geofence/label",
                f"geofence {cfg.geofence_radius_m:g} m",
                position=at_m,
                anchor="bottom-center",
                font_screen_scale=0.9,
            )
        scene.add_frame("/origin", axes_length=2.0, axes_radius=0.06)
        self.target_marker = scene.add_icosphere(
            "/target",
            radius=0.4,
            color=GOAL_RGB,
            opacity=0.6,
            cast_shadow=False,
            receive_shadow=False,
            visible=False,
        )

    def trail_ids(self, ids: list[int]) -> set[int]:
        """The vehicles whose trails the next update should carry (round robin over `ids`)."""
        k = max(1, self.cfg.trail_spread_updates)
        tick, self._trail_tick = self._trail_tick, self._trail_tick + 1
        return {vid for i, vid in enumerate(sorted(ids)) if i % k == tick % k}

    def update(self, snap: FleetSnapshot, send_trails: bool = True) -> None:
        """Draw `snap`. Trails are redrawn once the snapshots since the last time carried every
        drawn vehicle's trail (see `trail_ids`)."""
        drawn = [v for v in snap.vehicles if v.state is not None]
        fleet = _fleet(drawn, self.cfg.velocity_scale_s)
        if fleet.ids != self.ids:
            self._rebuild(fleet)
        if fleet.ids:
            self._update_layers(fleet)
            self._update_trails(fleet, drawn if send_trails else [])
        self._update_labels(fleet, drawn, len(snap.vehicles))

    def update_traffic(self, tracks: list, now_s: float) -> None:
        """Draw traffic that does not cooperate (agent.traffic tracks, dead-reckoned to `now_s`):
        a magenta diamond, a ring at the berth kept from it, a label; gone tracks are removed.
        Few nodes each (the table is bounded), so one node set per track."""
        scene = self.server.scene
        keep = set()
        for t in tracks:
            keep.add(t.track_id)
            x, y, z = (float(v) for v in ned_to_scene(np.array([t.at(now_s)], np.float32))[0])
            pos = (x, y, z)
            nodes = self.traffic.get(t.track_id)
            if nodes is None:
                path = f"/traffic/{t.track_id}"
                berth_m = self.cfg.traffic_separation_m or self.cfg.separation_m
                # vehicles' rings are half the separation: the two rings touch at the berth
                vertices, faces = geo.band_mesh(berth_m - self.cfg.separation_m / 2.0, 0.2)
                nodes = self.traffic[t.track_id] = {
                    "body": scene.add_icosphere(
                        f"{path}/body",
                        radius=0.6,
                        subdivisions=0,
                        color=TRAFFIC_RGB,
                        position=pos,
                        **NO_SHADOW,
                    ),
                    "ring": scene.add_mesh_simple(
                        f"{path}/ring",
                        vertices,
                        faces,
                        color=TRAFFIC_RGB,
                        position=pos,
                        side="double",
                        **NO_SHADOW,
                    ),
                    "label": scene.add_label(
                        f"{path}/label",
                        traffic_label(t, now_s),
                        position=(pos[0], pos[1], pos[2] + LABEL_HEIGHT_M + 0.3),
                        anchor="bottom-center",
                        font_screen_scale=0.9,
                    ),
                }
                continue
            nodes["body"].position = pos
            nodes["ring"].position = pos
            nodes["label"].position = (pos[0], pos[1], pos[2] + LABEL_HEIGHT_M + 0.3)
            nodes["label"].text = traffic_label(t, now_s)
        for track_id in set(self.traffic) - keep:
            for node in self.traffic.pop(track_id).values():
                node.remove()

    def _put(
        self, layer: str, prop: str, value: Any, make: Callable[[Any], Any] | None = None
    ) -> None:
        """nodes[layer].prop = make(value) (or value), unless `value` is what was put last time."""
        marker = value.tobytes() if isinstance(value, np.ndarray) else value
        if self.sent.get(f"{layer}.{prop}") != marker:
            self.sent[f"{layer}.{prop}"] = marker
            setattr(self.nodes[layer], prop, make(value) if make is not None else value)

    def _rebuild(self, fleet: _Fleet) -> None:
        """New nodes sized for `fleet` (its vehicles changed); none for an empty fleet."""
        for node in self.nodes.values():
            node.remove()
        self.nodes.clear()
        self.sent.clear()
        self.ids = fleet.ids
        self._trails = {vid: t for vid, t in self._trails.items() if vid in fleet.ids}
        n = len(fleet.ids)
        if n == 0:
            return
        scene = self.server.scene
        sides: tuple[tuple[str, Literal["front", "double"]], ...] = (
            ("bodies", "front"),
            ("rings", "double"),
            ("goals", "front"),
        )
        for layer, side in sides:
            vertices, faces = self._meshes[layer]
            self.nodes[layer] = scene.add_batched_meshes_simple(
                f"/fleet/{layer}",
                vertices,
                faces,
                batched_wxyzs=fleet.wxyz,
                batched_positions=fleet.pos_m,
                batched_colors=fleet.rgb,
                lod="off",
                side=side,
                flat_shading=True,
                **NO_SHADOW,
            )
        for layer in ("velocity", "stalks"):
            self.nodes[layer] = scene.add_line_segments(
                f"/fleet/{layer}",
                np.zeros((n, 2, 3), np.float32),
                np.zeros((n, 2, 3), np.uint8),
                thickness=2.0 if layer == "velocity" else 1.0,
                thickness_units="screen",
            )
        dots = n * self.cfg.trail_max_points
        self.nodes["trails"] = scene.add_point_cloud(
            "/fleet/trails",
            np.zeros((dots, 3), np.float32),
            np.zeros((dots, 3), np.uint8),
            point_size=self.cfg.trail_dot_m,
            point_shape="circle",
            precision="float32",
        )
        if self._on_vehicle_click is not None:
            cb, ids = self._on_vehicle_click, fleet.ids

            def clicked(event: Any) -> None:
                if event.instance_index is not None and 0 <= event.instance_index < len(ids):
                    cb(ids[event.instance_index], event.client_id, event.modifier == "shift")

            # The ring (the separation radius) is a far larger target than the body: both
            # select, so any vehicle can be hit at any zoom.
            for layer in ("bodies", "rings"):
                self.nodes[layer].on_click(clicked)
                self.nodes[layer].on_click(modifier="shift")(clicked)

    def _update_layers(self, fleet: _Fleet) -> None:
        n, pos = len(fleet.ids), fleet.pos_m
        self._put("bodies", "batched_positions", pos)
        self._put("bodies", "batched_wxyzs", fleet.wxyz)
        self._put("bodies", "batched_colors", fleet.rgb)
        self._put("rings", "batched_positions", pos)
        self._put("rings", "batched_colors", fleet.ring_rgb)
        self._put("goals", "batched_positions", fleet.goal_m)
        self._put("goals", "batched_scales", fleet.goal_scale)
        self._put("goals", "batched_colors", fleet.rgb)
        self._put("velocity", "points", np.stack([pos, pos + fleet.vel_m], axis=1))
        self._put("velocity", "colors", n, lambda k: np.full((k, 2, 3), VELOCITY_RGB, np.uint8))
        ground = pos * np.array([1.0, 1.0, 0.0], np.float32)
        self._put("stalks", "points", np.stack([pos, ground], axis=1))
        self._put("stalks", "colors", n, lambda k: np.full((k, 2, 3), STALK_RGB, np.uint8))
        dots = self.cfg.trail_max_points
        self._put("trails", "colors", fleet.rgb, lambda rgb: np.repeat(rgb, dots, axis=0))

    def _update_trails(self, fleet: _Fleet, vehicles: list[VehicleView]) -> None:
        """Keep the trails the snapshot carries; re-send the trail node once all are fresh."""
        for v in vehicles:
            if len(v.trail_ned_m):
                trail = geo.thin(v.trail_ned_m, self.cfg.trail_max_points)
                self._trails[v.vehicle_id] = ned_to_scene(trail)
                self._fresh.add(v.vehicle_id)
        complete = self._fresh.issuperset(fleet.ids)
        if complete or "trails.points" not in self.sent:  # a new node shows what there is
            if complete:
                self._fresh.clear()
            lines = [
                self._trails.get(vid, pos[None])
                for vid, pos in zip(fleet.ids, fleet.pos_m, strict=True)
            ]
            self._put("trails", "points", geo.padded_points(lines, self.cfg.trail_max_points))

    def _update_labels(self, fleet: _Fleet, drawn: list[VehicleView], fleet_size: int) -> None:
        cfg = self.cfg
        if fleet_size <= cfg.labels_all_max_vehicles:
            wanted = drawn
        else:
            wanted = [v for v in drawn if not v.alive or v.stale or v.too_close][: cfg.labels_max]
        index = {vid: i for i, vid in enumerate(fleet.ids)}
        for vid in set(self.labels) - {v.vehicle_id for v in wanted}:
            self.labels.pop(vid).remove()
            del self._label_sent[vid]
        for v in wanted:
            x, y, z = (float(c) for c in fleet.pos_m[index[v.vehicle_id]])
            key = (label_text(v), (x, y, round(z + LABEL_HEIGHT_M, 2)))
            if self._label_sent.get(v.vehicle_id) == key:
                continue
            self._label_sent[v.vehicle_id] = key
            label = self.labels.get(v.vehicle_id)
            if label is None:
                self.labels[v.vehicle_id] = self.server.scene.add_label(
                    f"/labels/{v.vehicle_id}",
                    key[0],
                    position=key[1],
                    anchor="bottom-center",
                    font_screen_scale=0.9,
                )
            else:
                label.text, label.position = key

    # -- the fleet plan ------------------------------------------------------------------------
    def update_plan(self, plan: FleetPlan | None) -> None:
        """Draw the fleet plan on the ground, replacing the previous one: the fence as a closed
        orange line (the circular geofence hidden while the plan has a fence: the vehicles then
        check the polygon), each keep-out zone filled translucent red with its edge and its
        name, each rally point a small marker with its name. A few nodes per zone; a plan holds
        at most 64 zones."""
        scene = self.server.scene
        for handle in reversed(self.plan_nodes):  # children (labels) before their parents
            handle.remove()
        self.plan_nodes = []
        root = scene.get_handle_by_name("/plan")  # the frames viser made for the paths
        if root is not None:
            root.remove()
        for name in ("/geofence", "/geofence/label"):
            circle = scene.get_handle_by_name(name)
            if circle is not None:
                circle.visible = plan is None or plan.fence is None
        if plan is None:
            return
        add = self.plan_nodes.append
        if plan.fence is not None:
            f = plan.fence
            add(
                scene.add_line_segments(
                    "/plan/fence",
                    polygon_segments(f.vertices_ne_m, 0.04),
                    np.array(GEOFENCE_RGB, np.uint8),
                    thickness=4.0,
                    thickness_units="screen",
                )
            )
            band = [
                f"{a} {v:g} m"
                for a, v in (("floor", f.floor_alt_m), ("ceiling", f.ceiling_alt_m))
                if v is not None
            ]
            n, e = f.vertices_ne_m[0]
            add(
                scene.add_label(
                    "/plan/fence/label",
                    "fence" + (f" ({', '.join(band)})" if band else ""),
                    position=(e, n, 0.3),
                    anchor="bottom-center",
                    font_screen_scale=0.9,
                )
            )
        for k, z in enumerate(plan.keep_out):
            path = f"/plan/zones/{k}"
            vertices, faces = polygon_mesh(z.vertices_ne_m, 0.02)
            add(
                scene.add_mesh_simple(
                    f"{path}/fill",
                    vertices,
                    faces,
                    color=KEEP_OUT_RGB,
                    opacity=0.35,
                    side="double",
                    **NO_SHADOW,
                )
            )
            add(
                scene.add_line_segments(
                    f"{path}/edge",
                    polygon_segments(z.vertices_ne_m, 0.05),
                    np.array(KEEP_OUT_RGB, np.uint8),
                    thickness=3.0,
                    thickness_units="screen",
                )
            )
            n, e = zone_label_position(z.vertices_ne_m)
            top = "" if z.ceiling_alt_m is None else f" (to {z.ceiling_alt_m:g} m)"
            add(
                scene.add_label(
                    f"{path}/label",
                    f"keep out: {z.name or k + 1}{top}",
                    position=(e, n, 0.5),
                    anchor="bottom-center",
                    font_screen_scale=0.9,
                )
            )
        numbers = {i: no for no, i in rally_numbers(plan.rally)}  # as the plan editor's
        for k, r in enumerate(plan.rally):
            label = r.name or f"rally {numbers[k]}"
            add_rally_point(scene, f"/plan/rally/{k}", r, label, GEOFENCE_RGB, add, 0.9)

    # -- missions ------------------------------------------------------------------------------
    def update_routes(self, routes: dict[int, list[tuple[float, float, float]]]) -> None:
        """Draw each vehicle's mission route (its waypoints in order, NED) as a line in the
        MISSION colour, replacing what was drawn; vehicles left out lose theirs."""
        scene = self.server.scene
        for vid in [v for v in self.route_nodes if v not in routes]:
            self.route_nodes.pop(vid).remove()
        for vid, points in routes.items():
            self.route_nodes[vid] = scene.add_line_segments(
                f"/missions/{vid}",
                route_segments(points),
                np.array(mode_rgb(Mode.MISSION), np.uint8),
                thickness=2.0,
                thickness_units="screen",
            )


def route_segments(points_ned_m) -> np.ndarray:
    """(k-1, 2, 3) scene-frame segments joining a route's NED points in order."""
    p = ned_to_scene(np.asarray(points_ned_m, np.float32).reshape(-1, 3))
    if len(p) < 2:
        return np.zeros((0, 2, 3), np.float32)
    return np.stack([p[:-1], p[1:]], axis=1).astype(np.float32)


def add_rally_point(
    scene: viser.SceneApi,
    path: str,
    point: RallyPoint,
    label: str,
    rgb: tuple[int, int, int],
    add: Callable[[Any], None],
    font_scale: float,
) -> None:
    """A home or rally point: a sphere at its altitude, `label` above it; each handle to `add`."""
    add(
        scene.add_icosphere(
            path,
            radius=0.5,
            color=rgb,
            position=(point.e_m, point.n_m, point.alt_m + 0.5),
            **NO_SHADOW,
        )
    )
    add(
        scene.add_label(
            f"{path}/label",
            label,
            position=(0.0, 0.0, 0.8),
            anchor="bottom-center",
            font_screen_scale=font_scale,
        )
    )


def polygon_segments(vertices_ne_m, z_m: float) -> np.ndarray:
    """(k, 2, 3) scene-frame segments of a closed polygon given as (north, east) vertices."""
    ne = np.asarray(vertices_ne_m, np.float32)
    pts = np.stack([ne[:, 1], ne[:, 0], np.full(len(ne), z_m, np.float32)], axis=-1)
    return np.stack([pts, np.roll(pts, -1, axis=0)], axis=1)


def polygon_mesh(vertices_ne_m, z_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat (vertices, faces) mesh of a simple polygon, concave ones included (shapely's
    constrained Delaunay triangulation keeps every triangle inside the polygon)."""
    import shapely

    triangles = shapely.constrained_delaunay_triangles(shapely.Polygon(vertices_ne_m))
    tris = np.array(
        [np.asarray(t.exterior.coords)[:3] for t in shapely.get_parts(triangles)], np.float32
    ).reshape(-1, 3, 2)
    verts = np.stack(
        [tris[..., 1], tris[..., 0], np.full(tris.shape[:2], z_m, np.float32)], axis=-1
    ).reshape(-1, 3)
    return verts, np.arange(len(verts), dtype=np.uint32).reshape(-1, 3)


def zone_label_position(vertices_ne_m) -> tuple[float, float]:
    """A point inside the polygon (north, east) for its name: shapely's representative point
    (the centroid of a U-shaped zone lies outside it)."""
    import shapely

    p = shapely.Polygon(vertices_ne_m).representative_point()
    return float(p.x), float(p.y)
