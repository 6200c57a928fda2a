"""covey messages -> Foxglove's well-known messages: the one conversion that recordings and the
live bridge (`covey foxglove`) share.

Standard channels (schemas and encoders from foxglove-sdk; protobuf unless marked JSON):

    /tf                       FrameTransform  world (ENU, z up) -> ned, and ned -> vehicle/<id>
    /vehicles/<id>/pose       PoseInFrame     frame "ned": position = pos_ned_m, yaw = heading
    /vehicles/<id>/fix        LocationFix     WGS-84 from the fleet origin (comms.geo)
    /vehicles/<id>/link       JSON            rate_hz, age_s, loss_share of its state stream
    /scene                    SceneUpdate     per vehicle: body, velocity arrow, separation ring,
                                              goal, coloured by mode; deleted when it leaves;
                                              per TrafficReport an entity "traffic/<reporter>/
                                              <track>": magenta sphere, ring, arrow, "TRF" label;
                                              the fleet plan as one entity "plan": the fence
                                              (orange loop), keep-out zones (red loops, named);
                                              per vehicle that accepted a mission upload an
                                              entity "route/<id>": its waypoints as a line in
                                              the MISSION colour, labelled "mission N";
                                              per vehicle flying a goto, a return or a mission
                                              item while the plan has zones or a fence, an
                                              entity "plan_route/<id>": its planned route
                                              around the zones (groundstation/state_routes.py,
                                              the station's), recomputed every
                                              route_interval_s, deleted when it stops
    /events                   Log             every Event and ActionOutcome, level from its
                                              severity
    /commands                 JSON            who sent which command (or mission) to whom
    /acks                     JSON            each vehicle's answer to a command

Poses stay in NED (frame "ned", metres, exactly the wire values); the static world -> ned
transform turns them upright for Foxglove's z-up 3D panel. A Converter is not thread-safe:
callers feed it from one thread (the recorder's writer thread) or under a lock (the bridge).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

from foxglove import messages as fm

from comms import keys, schema
from comms.geo import GeoOrigin, mission_route_ned_m
from comms.plan import Fence, FleetPlan, Zone
from groundstation.palette import (
    GEOFENCE_RGB,
    GOAL_RGB,
    KEEP_OUT_RGB,
    RING_OK_RGB,
    TRAFFIC_RGB,
    mode_rgb,
)
from groundstation.state_routes import ReportedState, is_routed, planned_routes
from groundstation.target_check import bands_for, router_for
from recording.state_batch import StateRow, decode_states

_STATE_TYPE = bytes([schema.MsgType.VEHICLE_STATE])
WORLD_FRAME = "world"
NED_FRAME = "ned"
TF_TOPIC = "/tf"
SCENE_TOPIC = "/scene"
EVENTS_TOPIC = "/events"
COMMANDS_TOPIC = "/commands"
ACKS_TOPIC = "/acks"
# world (ENU) -> ned is a half turn about (1, 1, 0)/sqrt(2): R = 2nn^T - I swaps x, y and flips z.
_ENU_TO_NED_Q = (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)
_LOG_LEVEL = {
    schema.Severity.DEBUG: fm.LogLevel.Debug,
    schema.Severity.INFO: fm.LogLevel.Info,
    schema.Severity.WARNING: fm.LogLevel.Warning,
    schema.Severity.ERROR: fm.LogLevel.Error,
    schema.Severity.CRITICAL: fm.LogLevel.Fatal,
}


def vehicle_frame(vehicle_id: int) -> str:
    return f"vehicle/{vehicle_id}"


def route_entity_id(vehicle_id: int) -> str:
    return f"route/{vehicle_id}"


def plan_route_entity_id(vehicle_id: int) -> str:
    """The entity of a vehicle's planned route around the zones ("route/<id>" is its mission)."""
    return f"plan_route/{vehicle_id}"


def pose_topic(vehicle_id: int) -> str:
    return f"/vehicles/{vehicle_id}/pose"


def fix_topic(vehicle_id: int) -> str:
    return f"/vehicles/{vehicle_id}/fix"


def link_topic(vehicle_id: int) -> str:
    return f"/vehicles/{vehicle_id}/link"


def _object(props: dict, title: str) -> dict:
    return {"title": title, "type": "object", "properties": props, "required": sorted(props)}


_INT, _NUM, _STR = {"type": "integer"}, {"type": "number"}, {"type": "string"}
COMMAND_JSON_SCHEMA = _object(
    {
        "nonce": _INT,
        "stamp_ns": _INT,
        "source_id": _INT,
        "kind": _STR,
        "params": {"type": "array", "items": _NUM},
        "targets": {"type": "array", "items": _INT, "description": "empty = the whole fleet"},
        "seq": _INT,
        "signed": {"type": "boolean"},
    },
    "covey.CommandJson",
)
ACK_JSON_SCHEMA = _object(
    {
        "vehicle_id": _INT,
        "nonce": _INT,
        "stamp_ns": _INT,
        "result": _STR,
        "accepted": {"type": "boolean"},
        "mode": _STR,
        "reason": _STR,
        "command_kind": _STR,
        "source_id": _INT,
    },
    "covey.CommandAckJson",
)
LINK_JSON_SCHEMA = _object(
    {"vehicle_id": _INT, "rate_hz": _NUM, "age_s": _NUM, "loss_share": _NUM, "states": _INT},
    "covey.LinkHealthJson",
)


@dataclass(frozen=True)
class SchemaSpec:
    """A channel's schema and message encoding, as MCAP and the WebSocket protocol name them."""

    name: str
    """Schema name, e.g. foxglove.SceneUpdate."""
    encoding: str
    """Schema encoding: protobuf (a FileDescriptorSet) or jsonschema."""
    data: bytes = field(repr=False)
    """The schema itself."""
    message_encoding: str
    """protobuf or json."""


class _HasSchema(Protocol):
    """A foxglove-sdk message class (its `get_schema()`: name, encoding, data)."""

    def get_schema(self) -> Any: ...


def _proto(cls: _HasSchema) -> SchemaSpec:
    s = cls.get_schema()
    return SchemaSpec(s.name, s.encoding, bytes(s.data), "protobuf")


def _json(js: dict) -> SchemaSpec:
    return SchemaSpec(js["title"], "jsonschema", json.dumps(js).encode(), "json")


FRAME_TRANSFORM = _proto(fm.FrameTransform)
POSE_IN_FRAME = _proto(fm.PoseInFrame)
LOCATION_FIX = _proto(fm.LocationFix)
SCENE_UPDATE = _proto(fm.SceneUpdate)
LOG = _proto(fm.Log)
COMMAND_JSON = _json(COMMAND_JSON_SCHEMA)
ACK_JSON = _json(ACK_JSON_SCHEMA)
LINK_JSON = _json(LINK_JSON_SCHEMA)


FLEET_CHANNELS: tuple[tuple[str, SchemaSpec], ...] = (
    (TF_TOPIC, FRAME_TRANSFORM),
    (SCENE_TOPIC, SCENE_UPDATE),
    (EVENTS_TOPIC, LOG),
    (COMMANDS_TOPIC, COMMAND_JSON),
    (ACKS_TOPIC, ACK_JSON),
)
"""The channels of the fleet as a whole (not of one vehicle): the live bridge advertises them
when it starts, so a client can subscribe before the first command, ack or event."""


class Out(NamedTuple):
    """One standard message to write or send (a tuple: a frozen dataclass took ~1 us to make,
    and a state makes four or five)."""

    topic: str
    schema: SchemaSpec
    data: bytes
    log_time_ns: int


@dataclass(frozen=True)
class FoxgloveConfig:
    """How covey traffic is drawn in Foxglove."""

    origin: GeoOrigin = field(default_factory=GeoOrigin)
    """Fleet origin: local NED (0, 0, 0) on WGS-84, for the LocationFix channels."""
    separation_m: float = 3.0
    """The fleet's separation: radius of the ring drawn around each vehicle, and what the
    planned routes around the plan's zones are computed for (the agents' --separation-m)."""
    link_interval_s: float = 1.0
    """Publish each vehicle's link health this often (by receive time)."""
    scene_interval_s: float = 0.2
    """Redraw a vehicle's 3D entity at most this often (by receive time); poses and /tf keep
    every state. The SceneUpdate is most of the conversion's cost (bench/foxglove.py)."""
    body_size_m: float = 0.6
    """Edge of the cube drawn for a vehicle's body."""
    entity_lifetime_s: float = 5.0
    """A vehicle's 3D entity fades after this long without a state (0 = forever); so does its
    planned route."""
    route_interval_s: float = 1.0
    """Recompute the vehicles' planned routes around the plan's zones at most this often (by
    receive time): each costs a planner query (at most MAX_ROUTES vehicles, the lowest ids).
    The planner is built for the fleet's `separation_m`, as the station builds it."""

    def __post_init__(self) -> None:
        for name in (
            "separation_m",
            "link_interval_s",
            "scene_interval_s",
            "body_size_m",
            "route_interval_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}={v} must be a finite number > 0")
        if not (math.isfinite(self.entity_lifetime_s) and self.entity_lifetime_s >= 0):
            raise ValueError(f"entity_lifetime_s={self.entity_lifetime_s} must be >= 0")


def _ts(stamp_ns: int) -> fm.Timestamp:
    return fm.Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)


def _v3(x: float, y: float, z: float) -> fm.Vector3:
    return fm.Vector3(x=float(x), y=float(y), z=float(z))


def _q(x: float, y: float, z: float, w: float) -> fm.Quaternion:
    return fm.Quaternion(x=x, y=y, z=z, w=w)


def _colour(rgb: tuple[int, int, int], a: float = 1.0) -> fm.Color:
    return fm.Color(r=rgb[0] / 255, g=rgb[1] / 255, b=rgb[2] / 255, a=a)


def yaw_quaternion(heading_rad: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a turn by heading_rad about the NED z axis (down): q = (0, 0, sin h/2, cos h/2)."""
    return 0.0, 0.0, math.sin(heading_rad / 2), math.cos(heading_rad / 2)


def x_to(v: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """(x, y, z, w) turning +x onto v: q ~ (x cross v_hat, 1 + x . v_hat), normalised."""
    n = math.sqrt(sum(c * c for c in v))
    if n < 1e-9:
        return 0.0, 0.0, 0.0, 1.0
    a, b, c = (comp / n for comp in v)
    if a < -1 + 1e-9:  # opposite: any half turn about an axis normal to x
        return 0.0, 0.0, 1.0, 0.0
    x, y, z, w = 0.0, -c, b, 1.0 + a
    k = math.sqrt(y * y + z * z + w * w)
    return x, y / k, z / k, w / k


def _kind_name(c: schema.Command | schema.Mission) -> str:
    return c.kind if isinstance(c, schema.Mission) else c.kind.name


def _velocity_arrows(
    position: fm.Vector3, vel_ned_m_s, colour: fm.Color, sizes_m: tuple[float, float, float]
) -> list[fm.ArrowPrimitive]:
    """The velocity as one arrow its length in m/s long (none below 0.05 m/s); `sizes_m`:
    shaft diameter, head length and head diameter."""
    speed = math.sqrt(sum(v * v for v in vel_ned_m_s))
    if speed <= 0.05:
        return []
    shaft_d, head_l, head_d = sizes_m
    return [
        fm.ArrowPrimitive(
            pose=fm.Pose(position=position, orientation=_q(*x_to(vel_ned_m_s))),
            shaft_length=speed,
            shaft_diameter=shaft_d,
            head_length=head_l,
            head_diameter=head_d,
            color=colour,
        )
    ]


@dataclass
class _Link:
    first_seq: int
    last_seq: int
    window_start_ns: int
    states: int = 0
    window_states: int = 0
    window_first_seq: int = 0


class Converter:
    """Turns covey wire messages (by Zenoh key) into standard Foxglove messages.

    Keeps a little state per vehicle (link statistics, for the command <-> ack join the last
    commands by nonce); both tables are bounded by the vehicles and commands seen.
    """

    MAX_COMMANDS = 1024
    MAX_TOPICS = 100_000
    MAX_EARLY_ACCEPTS = 4096
    """Accepted acks kept per nonce until their mission arrives (an ack can overtake it)."""
    MAX_ROUTED = 4096
    """Vehicles flying a routed goal whose latest state is kept for the routes (ids come from
    the network; a vehicle silent past entity_lifetime_s is forgotten)."""

    def __init__(self, cfg: FoxgloveConfig = FoxgloveConfig()) -> None:
        self.cfg = cfg
        self._links: dict[int, _Link] = {}
        self._commands: dict[int, schema.Command | schema.Mission] = {}
        self._early_accepts: dict[int, list[int]] = {}  # nonce -> vehicles, command not seen
        self._tf_due_ns = 0
        self._scene_due_ns: dict[int, int] = {}  # vehicle -> next receive time to redraw it
        self._scene_mode: dict[int, schema.Mode] = {}  # a mode change is drawn at once
        self._names: dict[int, tuple[str, str, str, str]] = {}  # vehicle -> frame and topics
        self._kinds: dict[str, tuple[str, int]] = {}  # Zenoh key -> (leaf, vehicle id)
        # Parts that never change, built once: each foxglove object costs ~0.5 us to make, and
        # a conversion makes dozens per state (bench/foxglove.py).
        size, ring_d = cfg.body_size_m, 2 * cfg.separation_m
        self._identity = _q(0, 0, 0, 1)
        self._body_size = _v3(size, size, size * 0.3)
        self._ring_size = _v3(ring_d, ring_d, 0.02)
        self._ring_colour = _colour(RING_OK_RGB, 0.25)
        self._goal_size = _v3(0.4, 0.4, 0.4)
        self._goal_colour = _colour(GOAL_RGB)
        self._white = _colour((255, 255, 255))
        self._mode_colours: dict[schema.Mode, fm.Color] = {
            m: _colour(mode_rgb(m)) for m in schema.Mode
        }
        lifetime = cfg.entity_lifetime_s
        self._lifetime = fm.Duration.from_secs(lifetime) if lifetime > 0 else None
        self._world_tf_rotation = _q(*_ENU_TO_NED_Q)
        self._zero = _v3(0, 0, 0)
        # The planned routes: the latest plan's zones, the router built for them (only when
        # they change, at a route tick: a flood of plans builds at most one per interval), the
        # routed vehicles' latest states, and which routes are drawn (to delete them).
        self._plan_zones: tuple[Fence | None, tuple[Zone, ...]] | None = None
        self._router_zones: tuple[Fence | None, tuple[Zone, ...]] | None = None
        self._router: Any = None
        self._bands: Any = None
        self._routed: dict[int, tuple[ReportedState, int]] = {}  # vehicle -> (state, recv_ns)
        self._routes_due_ns = 0
        self._routes_drawn: set[int] = set()
        self._route_colour = _colour(mode_rgb(schema.Mode.GOTO))

    def _vehicle_names(self, vid: int) -> tuple[str, str, str, str]:
        """(frame, pose topic, fix topic, link topic) of a vehicle."""
        names = self._names.get(vid)
        if names is None:
            names = (vehicle_frame(vid), pose_topic(vid), fix_topic(vid), link_topic(vid))
            self._names[vid] = names
        return names

    def _kind(self, topic: str) -> tuple[str, int]:
        """(leaf, vehicle id or 0) of a Zenoh key: state, event, alive, ack, cmd or other."""
        kind = self._kinds.get(topic)
        if kind is None:
            parsed = keys.parse_vehicle_key(topic)
            if parsed is not None:
                kind = parsed[2], parsed[1]
            else:
                kind = ("cmd" if topic.endswith("/cmd") else "other"), 0
            if len(self._kinds) >= self.MAX_TOPICS:  # keys come from the network: bounded
                self._kinds.pop(next(iter(self._kinds)))
            self._kinds[topic] = kind
        return kind

    def convert(self, topic: str, data: bytes, recv_ns: int) -> list[Out]:
        """Standard messages for one recorded/received message; [] for anything undecodable."""
        leaf, vid = self._kind(topic)
        if leaf == "alive":
            return self._alive(vid, data, recv_ns)
        try:
            msg = schema.decode(data)
        except schema.DecodeError:
            return []
        if isinstance(msg, schema.VehicleState):
            return self.state(msg, recv_ns)
        if isinstance(msg, schema.Event | schema.ActionOutcome):
            return [self.event(msg, recv_ns)]
        if isinstance(msg, schema.Command):
            return [self.command(msg, recv_ns)]
        if isinstance(msg, schema.Mission):
            return [self.command(msg, recv_ns), *self._early_routes(msg, recv_ns)]
        if isinstance(msg, schema.CommandAck):
            return [self.ack(msg, recv_ns), *self._accepted_route(msg, recv_ns)]
        if isinstance(msg, schema.TrafficReport):
            return [self.traffic(msg, recv_ns)]
        if isinstance(msg, schema.PlanMessage):
            self._plan_zones = (msg.plan.fence, msg.plan.keep_out)
            return [self.plan(msg.plan, recv_ns)]
        return []

    def convert_all(self, items: Sequence[tuple[str, bytes, int]]) -> Iterator[list[Out]]:
        """convert() of each (topic, data, recv_ns), in order, with the states among them
        decoded together (recording/state_batch.py, a fraction of the cost): the same outputs."""
        states = [
            i
            for i, (topic, data, _) in enumerate(items)
            if data[:1] == _STATE_TYPE and self._kind(topic)[0] != "alive"
        ]
        rows = dict(zip(states, decode_states([items[i][1] for i in states]), strict=True))
        for i, (topic, data, recv_ns) in enumerate(items):
            if i not in rows:
                yield self.convert(topic, data, recv_ns)
            elif (row := rows[i]) is not None:
                yield self.state(row, recv_ns)
            else:
                yield []

    # -- per message kind ------------------------------------------------------------------
    def state(self, s: schema.VehicleState | StateRow, recv_ns: int) -> list[Out]:
        vid, stamp = s.vehicle_id, _ts(s.stamp_ns)
        frame, pose_t, fix_t, link_t = self._vehicle_names(vid)
        n, e, d = s.pos_ned_m
        position = fm.Vector3(x=n, y=e, z=d)
        q = _q(*yaw_quaternion(s.heading_rad))
        out: list[Out] = []
        if recv_ns >= self._tf_due_ns:
            self._tf_due_ns = recv_ns + int(self.cfg.link_interval_s * 1e9)
            world = fm.FrameTransform(
                timestamp=_ts(recv_ns),
                parent_frame_id=WORLD_FRAME,
                child_frame_id=NED_FRAME,
                translation=self._zero,
                rotation=self._world_tf_rotation,
            )
            out.append(Out(TF_TOPIC, FRAME_TRANSFORM, world.encode(), recv_ns))
        tf = fm.FrameTransform(
            timestamp=stamp,
            parent_frame_id=NED_FRAME,
            child_frame_id=frame,
            translation=position,
            rotation=q,
        )
        out.append(Out(TF_TOPIC, FRAME_TRANSFORM, tf.encode(), recv_ns))
        pose = fm.PoseInFrame(
            timestamp=stamp, frame_id=NED_FRAME, pose=fm.Pose(position=position, orientation=q)
        )
        out.append(Out(pose_t, POSE_IN_FRAME, pose.encode(), recv_ns))
        lat, lon, alt = self.cfg.origin.to_global(n, e, d)
        # LocationFix.heading: degrees clockwise from north, as NED's heading is.
        fix = fm.LocationFix(
            timestamp=stamp,
            frame_id=frame,
            latitude=lat,
            longitude=lon,
            altitude=alt,
            heading=math.degrees(s.heading_rad) % 360.0,
            color=self._mode_colour(s.mode),
        )
        out.append(Out(fix_t, LOCATION_FIX, fix.encode(), recv_ns))
        if recv_ns >= self._scene_due_ns.get(vid, 0) or s.mode != self._scene_mode.get(vid):
            self._scene_due_ns[vid] = recv_ns + int(self.cfg.scene_interval_s * 1e9)
            self._scene_mode[vid] = s.mode
            entity = self._entity(s, stamp, frame, position, q)
            out.append(
                Out(SCENE_TOPIC, SCENE_UPDATE, fm.SceneUpdate(entities=[entity]).encode(), recv_ns)
            )
        link = self._link(s, recv_ns)
        if link is not None:
            out.append(Out(link_t, LINK_JSON, json.dumps(link).encode(), recv_ns))
        if is_routed(s):
            if vid in self._routed or len(self._routed) < self.MAX_ROUTED:
                self._routed[vid] = (s, recv_ns)
        else:
            self._routed.pop(vid, None)
        if recv_ns >= self._routes_due_ns and (self._plan_zones or self._routes_drawn):
            out += self.routes(recv_ns)
        return out

    def routes(self, recv_ns: int) -> list[Out]:
        """The routed vehicles' planned routes around the latest plan's zones (the station's
        computation, groundstation/state_routes.py `planned_routes`), one entity each, and a
        deletion for each drawn route whose vehicle no longer flies one (it holds, lands, left
        or went silent); at most every route_interval_s."""
        self._routes_due_ns = recv_ns + int(self.cfg.route_interval_s * 1e9)
        if self._plan_zones != self._router_zones:
            self._router_zones = self._plan_zones
            fence, zones = self._plan_zones or (None, ())
            plan = FleetPlan("routes", 1, 0, fence, zones)
            self._router = router_for(plan, self.cfg.separation_m)
            self._bands = bands_for(plan, self.cfg.separation_m, self._router)
        if self._lifetime is not None:
            old_ns = recv_ns - int(self.cfg.entity_lifetime_s * 1e9)
            for vid in [v for v, (_, t) in self._routed.items() if t < old_ns]:
                del self._routed[vid]
        routes = planned_routes(self._router, [s for s, _ in self._routed.values()], self._bands)
        gone = sorted(self._routes_drawn - routes.keys())
        self._routes_drawn = set(routes)
        if not routes and not gone:
            return []
        stamp = _ts(recv_ns)
        update = fm.SceneUpdate(
            deletions=[
                fm.SceneEntityDeletion(
                    timestamp=stamp,
                    type=fm.SceneEntityDeletionType.MatchingId,
                    id=plan_route_entity_id(vid),
                )
                for vid in gone
            ],
            entities=[self._route_entity(vid, pts, stamp) for vid, pts in routes.items()],
        )
        return [Out(SCENE_TOPIC, SCENE_UPDATE, update.encode(), recv_ns)]

    def _route_entity(self, vid: int, points_ned_m, stamp: fm.Timestamp) -> fm.SceneEntity:
        """A planned route (frame ned): a line from the vehicle through its waypoints to its
        goal, in the goto colour, as the station draws it."""
        line = fm.LinePrimitive(
            type=fm.LinePrimitiveLineType.LineStrip,
            pose=fm.Pose(position=self._zero, orientation=self._identity),
            thickness=2.5,
            scale_invariant=True,
            points=[fm.Point3(x=float(n), y=float(e), z=float(d)) for n, e, d in points_ned_m],
            color=self._route_colour,
        )
        return fm.SceneEntity(
            timestamp=stamp,
            frame_id=NED_FRAME,
            id=plan_route_entity_id(vid),
            lifetime=self._lifetime,
            metadata=[fm.KeyValuePair(key="waypoints", value=str(len(points_ned_m) - 2))],
            lines=[line],
        )

    def _mode_colour(self, mode: schema.Mode) -> fm.Color:
        colour = self._mode_colours.get(mode)
        return colour if colour is not None else _colour(mode_rgb(mode))

    def scene_entity(self, s: schema.VehicleState) -> fm.SceneEntity:
        """A vehicle drawn in the ned frame: body, velocity arrow, separation ring and goal."""
        n, e, d = s.pos_ned_m
        return self._entity(
            s,
            _ts(s.stamp_ns),
            vehicle_frame(s.vehicle_id),
            fm.Vector3(x=n, y=e, z=d),
            _q(*yaw_quaternion(s.heading_rad)),
        )

    def _entity(
        self,
        s: schema.VehicleState | StateRow,
        stamp: fm.Timestamp,
        frame: str,
        position: fm.Vector3,
        yaw: fm.Quaternion,
    ) -> fm.SceneEntity:
        colour = self._mode_colour(s.mode)
        body = fm.CubePrimitive(
            pose=fm.Pose(position=position, orientation=yaw),
            size=self._body_size,
            color=colour,
        )
        ring = fm.CylinderPrimitive(
            pose=fm.Pose(position=position, orientation=self._identity),
            size=self._ring_size,
            bottom_scale=1.0,
            top_scale=1.0,
            color=self._ring_colour,
        )
        arrows = _velocity_arrows(position, s.vel_ned_m_s, colour, (0.08, 0.3, 0.2))
        spheres, lines = [], []
        if s.flags & schema.StateFlag.HAS_GOAL:
            goal = _v3(*s.goal_ned_m)
            n, e, d = s.pos_ned_m
            gn, ge, gd = s.goal_ned_m
            spheres.append(
                fm.SpherePrimitive(
                    pose=fm.Pose(position=goal, orientation=self._identity),
                    size=self._goal_size,
                    color=self._goal_colour,
                )
            )
            # the leg to it: a formation's slot assignment, a mission's next item
            lines.append(
                fm.LinePrimitive(
                    type=fm.LinePrimitiveLineType.LineList,
                    pose=fm.Pose(position=_v3(0.0, 0.0, 0.0), orientation=self._identity),
                    thickness=2.0,
                    scale_invariant=True,
                    points=[fm.Point3(x=n, y=e, z=d), fm.Point3(x=gn, y=ge, z=gd)],
                    color=self._goal_colour,
                )
            )
        n, e, d = s.pos_ned_m
        label = fm.TextPrimitive(
            pose=fm.Pose(position=_v3(n, e, d - 0.8), orientation=self._identity),
            billboard=True,
            font_size=14.0,
            scale_invariant=True,
            color=self._white,
            text=f"{s.vehicle_id} {s.mode.name}",
        )
        return fm.SceneEntity(
            timestamp=stamp,
            frame_id=NED_FRAME,
            id=frame,
            lifetime=self._lifetime,
            metadata=[
                fm.KeyValuePair(key="mode", value=s.mode.name),
                fm.KeyValuePair(key="armed", value=str(s.armed)),
            ],
            cubes=[body],
            cylinders=[ring],
            arrows=arrows,
            spheres=spheres,
            lines=lines,
            texts=[label],
        )

    def traffic(self, r: schema.TrafficReport, recv_ns: int) -> Out:
        """Traffic that does not cooperate, in the scene: a magenta sphere, a ring at the
        separation, its velocity and a label; it fades with the vehicles' entity lifetime."""
        position = _v3(*r.pos_ned_m)
        colour = _colour(TRAFFIC_RGB)
        arrows = _velocity_arrows(position, r.vel_ned_m_s, colour, (0.1, 0.4, 0.3))
        n, e, d = r.pos_ned_m
        kind = "manned" if r.manned else "unmanned"
        entity = fm.SceneEntity(
            timestamp=_ts(recv_ns),
            frame_id=NED_FRAME,
            id=f"traffic/{r.reporter_id}/{r.track_id}",
            lifetime=self._lifetime,
            metadata=[
                fm.KeyValuePair(key="source", value=r.source.name),
                fm.KeyValuePair(key="manned", value=str(r.manned)),
                fm.KeyValuePair(key="reporter", value=f"{r.reporter_role.name} {r.reporter_id}"),
            ],
            spheres=[
                fm.SpherePrimitive(
                    pose=fm.Pose(position=position, orientation=self._identity),
                    size=_v3(1.0, 1.0, 1.0),
                    color=colour,
                )
            ],
            cylinders=[
                fm.CylinderPrimitive(
                    pose=fm.Pose(position=position, orientation=self._identity),
                    size=self._ring_size,
                    bottom_scale=1.0,
                    top_scale=1.0,
                    color=_colour(TRAFFIC_RGB, 0.25),
                )
            ],
            arrows=arrows,
            texts=[
                fm.TextPrimitive(
                    pose=fm.Pose(position=_v3(n, e, d - 1.0), orientation=self._identity),
                    billboard=True,
                    font_size=14.0,
                    scale_invariant=True,
                    color=colour,
                    text=f"TRF {r.track_id:X} {r.source.name} {kind}",
                )
            ],
        )
        return Out(SCENE_TOPIC, SCENE_UPDATE, fm.SceneUpdate(entities=[entity]).encode(), recv_ns)

    def plan(self, plan: FleetPlan, recv_ns: int) -> Out:
        """The fleet plan on the ground (frame ned, z = 0): the fence as an orange loop, each
        keep-out zone a red loop with its name; one entity, replaced by the next plan's. The
        plan as it was put on the mesh, signed or not (the recorder shows what was sent)."""
        loops = []
        if plan.fence is not None:
            loops.append((plan.fence.vertices_ne_m, _colour(GEOFENCE_RGB), 3.0))
        loops += [(z.vertices_ne_m, _colour(KEEP_OUT_RGB), 2.0) for z in plan.keep_out]
        lines = [
            fm.LinePrimitive(
                type=fm.LinePrimitiveLineType.LineLoop,
                pose=fm.Pose(position=_v3(0.0, 0.0, 0.0), orientation=self._identity),
                thickness=thickness,
                scale_invariant=True,
                points=[fm.Point3(x=n, y=e, z=0.0) for n, e in vertices],
                color=colour,
            )
            for vertices, colour, thickness in loops
        ]
        texts = []
        for z in plan.keep_out:
            n = sum(v[0] for v in z.vertices_ne_m) / len(z.vertices_ne_m)
            e = sum(v[1] for v in z.vertices_ne_m) / len(z.vertices_ne_m)
            texts.append(
                fm.TextPrimitive(
                    pose=fm.Pose(position=_v3(n, e, -0.5), orientation=self._identity),
                    billboard=True,
                    font_size=14.0,
                    scale_invariant=True,
                    color=_colour(KEEP_OUT_RGB),
                    text=f"keep out: {z.name}" if z.name else "keep out",
                )
            )
        entity = fm.SceneEntity(
            timestamp=_ts(recv_ns),
            frame_id=NED_FRAME,
            id="plan",
            metadata=[
                fm.KeyValuePair(key="version", value=str(plan.version)),
                fm.KeyValuePair(key="signer", value=str(plan.signer_id)),
            ],
            lines=lines,
            texts=texts,
        )
        return Out(SCENE_TOPIC, SCENE_UPDATE, fm.SceneUpdate(entities=[entity]).encode(), recv_ns)

    def scene_update(self, states: list[schema.VehicleState]) -> fm.SceneUpdate:
        return fm.SceneUpdate(entities=[self.scene_entity(s) for s in states])

    def event(self, ev: schema.EventMessage, recv_ns: int) -> Out:
        """An event, or an autopilot outcome ("[ACTION] <nonce> done|failed: <detail>", as
        outcomes read when they travelled as events)."""
        if isinstance(ev, schema.ActionOutcome):
            word = "done" if ev.ok else "failed"
            text = f"{ev.nonce:016x} {word}: {ev.detail}"
        else:
            text = ev.text
        log = fm.Log(
            timestamp=_ts(ev.stamp_ns),
            level=_LOG_LEVEL[ev.severity],
            message=f"[{ev.kind.name}] {text}",
            name=vehicle_frame(ev.vehicle_id),
        )
        return Out(EVENTS_TOPIC, LOG, log.encode(), recv_ns)

    def command(self, c: schema.Command | schema.Mission, recv_ns: int) -> Out:
        """A command (or a mission upload: kind MISSION, params [mission id, items], seq 0)."""
        if len(self._commands) >= self.MAX_COMMANDS:
            self._commands.pop(next(iter(self._commands)))
        self._commands[c.nonce] = c
        params: list[float]
        if isinstance(c, schema.Mission):
            kind, params, seq = c.kind, [c.mission_id, len(c.items)], 0
        else:
            kind, params, seq = c.kind.name, list(c.params), c.seq
        body = {
            "nonce": c.nonce,
            "stamp_ns": c.stamp_ns,
            "source_id": c.source_id,
            "kind": kind,
            "params": params,
            "targets": list(c.targets),
            "seq": seq,
            "signed": any(c.tag),
        }
        return Out(COMMANDS_TOPIC, COMMAND_JSON, json.dumps(body).encode(), recv_ns)

    def ack(self, a: schema.CommandAck, recv_ns: int) -> Out:
        # The command's kind and sender when it reached us first; an ack can overtake its
        # command (it travels another Zenoh path): then "" and -1, and /commands has it by nonce.
        cmd = self._commands.get(a.nonce)
        body = {
            "vehicle_id": a.vehicle_id,
            "nonce": a.nonce,
            "stamp_ns": a.stamp_ns,
            "result": a.result.name,
            "accepted": a.accepted,
            "mode": a.mode.name,
            "reason": a.reason,
            "command_kind": _kind_name(cmd) if cmd else "",
            "source_id": cmd.source_id if cmd else -1,
        }
        return Out(ACKS_TOPIC, ACK_JSON, json.dumps(body).encode(), recv_ns)

    def route(self, vehicle_id: int, m: schema.Mission, recv_ns: int) -> Out:
        """The route vehicle `vehicle_id` accepted: its waypoints (local NED, frame ned) as one
        line and a dot each, in the MISSION colour, labelled "mission N" at the first; one
        entity per vehicle, replaced by its next accepted upload, deleted when it leaves."""
        ned = mission_route_ned_m(m.items, self.cfg.origin)
        pts = [fm.Point3(x=n, y=e, z=d) for n, e, d in ned]
        colour = self._mode_colours[schema.Mode.MISSION]
        lines, spheres, texts = [], [], []
        if len(pts) >= 2:
            lines.append(
                fm.LinePrimitive(
                    type=fm.LinePrimitiveLineType.LineStrip,
                    pose=fm.Pose(position=self._zero, orientation=self._identity),
                    thickness=2.0,
                    scale_invariant=True,
                    points=pts,
                    color=colour,
                )
            )
        for n, e, d in ned:
            spheres.append(
                fm.SpherePrimitive(
                    pose=fm.Pose(position=_v3(n, e, d), orientation=self._identity),
                    size=self._goal_size,
                    color=colour,
                )
            )
        if ned:
            n, e, d = ned[0]
            texts.append(
                fm.TextPrimitive(
                    pose=fm.Pose(position=_v3(n, e, d - 0.6), orientation=self._identity),
                    billboard=True,
                    font_size=12.0,
                    scale_invariant=True,
                    color=colour,
                    text=f"mission {m.mission_id} ({vehicle_id})",
                )
            )
        entity = fm.SceneEntity(
            timestamp=_ts(recv_ns),
            frame_id=NED_FRAME,
            id=route_entity_id(vehicle_id),
            metadata=[
                fm.KeyValuePair(key="mission_id", value=str(m.mission_id)),
                fm.KeyValuePair(key="items", value=str(len(m.items))),
            ],
            lines=lines,
            spheres=spheres,
            texts=texts,
        )
        return Out(SCENE_TOPIC, SCENE_UPDATE, fm.SceneUpdate(entities=[entity]).encode(), recv_ns)

    def _accepted_route(self, a: schema.CommandAck, recv_ns: int) -> list[Out]:
        """A vehicle accepted a mission upload: its route. An accept that overtook its
        mission is kept (bounded) until the mission comes."""
        if not a.accepted:
            return []
        cmd = self._commands.get(a.nonce)
        if isinstance(cmd, schema.Mission):
            return [self.route(a.vehicle_id, cmd, recv_ns)]
        if cmd is None:
            if a.nonce not in self._early_accepts and len(self._early_accepts) >= self.MAX_COMMANDS:
                self._early_accepts.pop(next(iter(self._early_accepts)))
            early = self._early_accepts.setdefault(a.nonce, [])
            if len(early) < self.MAX_EARLY_ACCEPTS:
                early.append(a.vehicle_id)
        return []

    def _early_routes(self, m: schema.Mission, recv_ns: int) -> list[Out]:
        return [self.route(v, m, recv_ns) for v in self._early_accepts.pop(m.nonce, [])]

    def _alive(self, vid: int, data: bytes, recv_ns: int) -> list[Out]:
        if data != b"\x00":
            return []
        self._links.pop(vid, None)
        self._names.pop(vid, None)
        self._scene_due_ns.pop(vid, None)
        self._scene_mode.pop(vid, None)
        self._routed.pop(vid, None)
        entity_ids = [vehicle_frame(vid), route_entity_id(vid)]
        if vid in self._routes_drawn:
            self._routes_drawn.discard(vid)
            entity_ids.append(plan_route_entity_id(vid))
        gone = fm.SceneUpdate(
            deletions=[
                fm.SceneEntityDeletion(
                    timestamp=_ts(recv_ns),
                    type=fm.SceneEntityDeletionType.MatchingId,
                    id=entity_id,
                )
                for entity_id in entity_ids
            ]
        )
        log = fm.Log(
            timestamp=_ts(recv_ns),
            level=fm.LogLevel.Warning,
            message="left the mesh",
            name=vehicle_frame(vid),
        )
        return [
            Out(SCENE_TOPIC, SCENE_UPDATE, gone.encode(), recv_ns),
            Out(EVENTS_TOPIC, LOG, log.encode(), recv_ns),
        ]

    def _link(self, s: schema.VehicleState | StateRow, recv_ns: int) -> dict | None:
        """Every link_interval_s: rate = states / window, loss = 1 - states / seq advance."""
        link = self._links.get(s.vehicle_id)
        if link is None or s.seq < link.last_seq:  # new vehicle, or its agent restarted
            link = self._links[s.vehicle_id] = _Link(s.seq, s.seq, recv_ns, window_first_seq=s.seq)
        link.states += 1
        link.window_states += 1
        link.last_seq = s.seq
        window_s = (recv_ns - link.window_start_ns) / 1e9
        if window_s < self.cfg.link_interval_s:
            return None
        expected = s.seq - link.window_first_seq + 1
        body = {
            "vehicle_id": s.vehicle_id,
            "rate_hz": link.window_states / window_s,
            "age_s": (recv_ns - s.stamp_ns) / 1e9,
            "loss_share": max(0.0, 1.0 - link.window_states / expected) if expected > 0 else 0.0,
            "states": link.states,
        }
        link.window_start_ns, link.window_states, link.window_first_seq = recv_ns, 0, s.seq + 1
        return body
