"""PX4's geofence over the MAVLink mission protocol (mission_type FENCE), as much as MAVSDK's
geofence plugin uses: upload (MISSION_COUNT, MISSION_REQUEST_INT / MISSION_ITEM_INT per item,
MISSION_ACK), download (MISSION_REQUEST_LIST, MISSION_COUNT, items on request, the GCS's ack)
and clear (MISSION_CLEAR_ALL). A stored fence also refuses a reposition target outside its
inclusion polygons or circles or inside an exclusion one, as PX4's geofence does for a goto.

`FenceStore.handle(msg, now_s)` takes one received message and returns the replies; bad input
(an item out of order, a polygon whose vertex count does not add up) is answered with the MAVLink
error PX4 sends, never raised. Mission and rally transfers are answered MAV_MISSION_UNSUPPORTED.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from comms.plan import point_in_polygon

FENCE = mavlink.MAV_MISSION_TYPE_FENCE
MAX_FENCE_ITEMS = 512
"""Most fence items the emulator stores (PX4's default dataman holds a few hundred)."""
TRANSFER_TIMEOUT_S = 5.0
"""An upload whose next item does not come within this long is dropped."""
POLYGON_COMMANDS = {
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION: True,
    mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION: False,
}
CIRCLE_COMMANDS = {
    mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION: True,
    mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION: False,
}
MISSION_MESSAGES = frozenset(
    ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_REQUEST_LIST", "MISSION_REQUEST_INT",
     "MISSION_REQUEST", "MISSION_CLEAR_ALL", "MISSION_ACK")
)  # fmt: skip


@dataclass(frozen=True)
class FenceShape:
    """One stored fence shape: a polygon (lat, lon vertices) or a circle (one centre, radius)."""

    inclusion: bool
    points_deg: tuple[tuple[float, float], ...]
    radius_m: float = 0.0
    """0 for a polygon."""


class FenceStore:
    """The vehicle's geofence and the transfer in progress."""

    def __init__(self, system_id: int) -> None:
        self.system_id = system_id
        self.items: list[Any] = []
        """The stored MISSION_ITEM_INTs, as uploaded (downloads send them back)."""
        self.shapes: tuple[FenceShape, ...] = ()
        self.uploads = 0
        """Fences accepted since start."""
        self._incoming: list[Any] | None = None
        self._expected = 0
        self._last_s = -math.inf

    def handle(self, msg: Any, now_s: float, peer: tuple[int, int]) -> list[Any]:
        """Replies to one mission-protocol message (`peer`: its (system, component))."""
        kind = msg.get_type()
        mission_type = getattr(msg, "mission_type", 0)
        if kind == "MISSION_ACK":
            return []  # the end of a download: nothing to answer
        if mission_type != FENCE:
            return [self._ack(peer, mavlink.MAV_MISSION_UNSUPPORTED, mission_type)]
        if kind == "MISSION_COUNT":
            return self._count(msg.count, peer, now_s)
        if kind == "MISSION_ITEM_INT":
            return self._item(msg, peer, now_s)
        if kind == "MISSION_REQUEST_LIST":
            return [mavlink.MAVLink_mission_count_message(*peer, len(self.items), FENCE)]
        if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            if not 0 <= msg.seq < len(self.items):
                return [self._ack(peer, mavlink.MAV_MISSION_INVALID_SEQUENCE)]
            item = self.items[msg.seq]
            item.target_system, item.target_component = peer
            return [item]
        if kind == "MISSION_CLEAR_ALL":
            self.items, self.shapes, self._incoming = [], (), None
            return [self._ack(peer, mavlink.MAV_MISSION_ACCEPTED)]
        return []

    def _ack(self, peer: tuple[int, int], result: int, mission_type: int = FENCE) -> Any:
        return mavlink.MAVLink_mission_ack_message(*peer, result, mission_type)

    def _count(self, count: int, peer: tuple[int, int], now_s: float) -> list[Any]:
        if count > MAX_FENCE_ITEMS:
            return [self._ack(peer, mavlink.MAV_MISSION_NO_SPACE)]
        if count == 0:
            self.items, self.shapes, self._incoming = [], (), None
            self.uploads += 1
            return [self._ack(peer, mavlink.MAV_MISSION_ACCEPTED)]
        self._incoming, self._expected, self._last_s = [], count, now_s
        return [mavlink.MAVLink_mission_request_int_message(*peer, 0, FENCE)]

    def _item(self, msg: Any, peer: tuple[int, int], now_s: float) -> list[Any]:
        incoming = self._incoming
        if incoming is None or now_s - self._last_s > TRANSFER_TIMEOUT_S:
            self._incoming = None
            return [self._ack(peer, mavlink.MAV_MISSION_ERROR)]
        if msg.seq != len(incoming):  # a repeat or a gap: ask again for the one we need
            return [mavlink.MAVLink_mission_request_int_message(*peer, len(incoming), FENCE)]
        incoming.append(msg)
        self._last_s = now_s
        if len(incoming) < self._expected:
            return [mavlink.MAVLink_mission_request_int_message(*peer, len(incoming), FENCE)]
        self._incoming = None
        shapes, result = parse_items(incoming)
        if result == mavlink.MAV_MISSION_ACCEPTED:
            self.items, self.shapes = incoming, shapes
            self.uploads += 1
        return [self._ack(peer, result)]

    def refusal(self, lat_deg: float, lon_deg: float, home_lat_deg: float) -> str | None:
        """Why a target breaks the stored fence, or None (no fence: None)."""
        inclusions = [s for s in self.shapes if s.inclusion]
        if inclusions and not any(_inside(s, lat_deg, lon_deg, home_lat_deg) for s in inclusions):
            return "outside the geofence"
        for s in self.shapes:
            if not s.inclusion and _inside(s, lat_deg, lon_deg, home_lat_deg):
                return "inside a geofence exclusion zone"
        return None


def parse_items(items: list[Any]) -> tuple[tuple[FenceShape, ...], int]:
    """Fence items -> shapes, or a MAVLink mission error: a polygon is its vertex count (param1)
    consecutive items of one command; a circle one item (param1 the radius in m)."""
    shapes, k = [], 0
    while k < len(items):
        item = items[k]
        if item.command in POLYGON_COMMANDS:
            n = int(item.param1)
            group = items[k : k + n]
            if n < 3 or len(group) < n or any(i.command != item.command for i in group):
                return (), mavlink.MAV_MISSION_INVALID_PARAM1
            pts = tuple((i.x * 1e-7, i.y * 1e-7) for i in group)
            shapes.append(FenceShape(POLYGON_COMMANDS[item.command], pts))
            k += n
        elif item.command in CIRCLE_COMMANDS:
            if not (math.isfinite(item.param1) and item.param1 > 0):
                return (), mavlink.MAV_MISSION_INVALID_PARAM1
            pts = ((item.x * 1e-7, item.y * 1e-7),)
            shapes.append(FenceShape(CIRCLE_COMMANDS[item.command], pts, float(item.param1)))
            k += 1
        elif item.command == mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT:
            k += 1
        else:
            return (), mavlink.MAV_MISSION_UNSUPPORTED
    return tuple(shapes), mavlink.MAV_MISSION_ACCEPTED


def _inside(s: FenceShape, lat: float, lon: float, home_lat: float) -> bool:
    # Local equirectangular metres around the target: fences span a few km at most.
    m_per_deg = 111_320.0
    cos_lat = math.cos(math.radians(home_lat))
    if s.radius_m:
        c_lat, c_lon = s.points_deg[0]
        d = math.hypot((lat - c_lat) * m_per_deg, (lon - c_lon) * m_per_deg * cos_lat)
        return d <= s.radius_m
    return point_in_polygon(lat, lon, s.points_deg)
