"""Traffic reports (MAVLink ADSB_VEHICLE) the autopilot holds, per ICAO address."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

ADSB_FLAGS_VALID_COORDS = 1
ADSB_FLAGS_VALID_ALTITUDE = 2
ADSB_FLAGS_VALID_HEADING = 4
ADSB_FLAGS_VALID_VELOCITY = 8
ADSB_FLAGS_VALID_CALLSIGN = 16
ADSB_FLAGS_SIMULATED = 64
ADSB_FLAGS_VERTICAL_VELOCITY_VALID = 128


@dataclass(frozen=True)
class TrafficEntry:
    """One neighbour as last reported, in WGS-84."""

    icao_address: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    heading_rad: float
    """Course over ground: 0 = north, positive clockwise."""
    hor_speed_m_s: float
    ver_speed_m_s: float
    """Positive up (ADSB_VEHICLE convention)."""
    callsign: str
    received_s: float
    """Receive time on the autopilot's clock."""
    emitter_type: int = 14
    """ADSB_EMITTER_TYPE (14: UAV), streamed back out as received."""


def entry_from_adsb(msg: Any, now_s: float) -> TrafficEntry | None:
    """Validate an ADSB_VEHICLE message; None if it carries no usable position."""
    flags = int(msg.flags)
    if not flags & ADSB_FLAGS_VALID_COORDS:
        return None
    lat_deg, lon_deg = msg.lat * 1e-7, msg.lon * 1e-7
    if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0):
        return None
    alt_m = msg.altitude * 1e-3 if flags & ADSB_FLAGS_VALID_ALTITUDE else math.nan
    heading_rad = math.radians(msg.heading * 0.01) if flags & ADSB_FLAGS_VALID_HEADING else math.nan
    speed_ok = flags & ADSB_FLAGS_VALID_VELOCITY
    hor_m_s = msg.hor_velocity * 0.01 if speed_ok else 0.0
    ver_m_s = msg.ver_velocity * 0.01 if flags & ADSB_FLAGS_VERTICAL_VELOCITY_VALID else 0.0
    callsign = (
        msg.callsign
        if isinstance(msg.callsign, str)
        else bytes(msg.callsign).decode("ascii", "replace")
    )
    return TrafficEntry(
        int(msg.ICAO_address),
        lat_deg,
        lon_deg,
        alt_m,
        heading_rad,
        hor_m_s,
        ver_m_s,
        callsign.rstrip("\x00"),
        now_s,
        int(msg.emitter_type) if 0 <= int(msg.emitter_type) <= 19 else 0,
    )


class TrafficStore:
    """Latest report per ICAO address; stale entries age out."""

    def __init__(self, timeout_s: float, own_icao: int | None = None) -> None:
        self.timeout_s = timeout_s
        self.own_icao = own_icao
        self._entries: dict[int, TrafficEntry] = {}

    def add(self, entry: TrafficEntry) -> bool:
        if entry.icao_address == self.own_icao:
            return False  # our own report echoed back: not a neighbour
        self._entries[entry.icao_address] = entry
        return True

    def fresh(self, now_s: float) -> list[TrafficEntry]:
        """Entries younger than the timeout, oldest ones dropped."""
        for icao in [k for k, e in self._entries.items() if now_s - e.received_s > self.timeout_s]:
            del self._entries[icao]
        return sorted(self._entries.values(), key=lambda e: e.icao_address)
