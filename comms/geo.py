"""The one place where the local NED frame meets WGS-84.

The fleet origin (lat, lon, alt) is fixed once in the fleet config. Local positions are NED metres
relative to it. Over a swarm's few kilometres a local tangent plane on the WGS-84 ellipsoid is
accurate to centimetres, so we use the curvature radii at the origin rather than a full ECEF
round trip.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from comms.schema import MissionFrame, MissionItem, MissionItemKind

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


@dataclass(frozen=True)
class GeoOrigin:
    """Fleet origin on WGS-84: local NED (0, 0, 0) is here."""

    lat_deg: float = 48.7490
    """Latitude in degrees (default: University of Stuttgart, where the paper flew)."""
    lon_deg: float = 9.1050
    """Longitude in degrees."""
    alt_m: float = 450.0
    """Altitude above the WGS-84 ellipsoid (AMSL is close enough for a local swarm) in metres."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lat_deg) and -90.0 < self.lat_deg < 90.0):
            raise ValueError(
                f"origin latitude must be finite and within (-90, 90), got {self.lat_deg}"
            )
        if not (math.isfinite(self.lon_deg) and -180.0 <= self.lon_deg <= 180.0):
            raise ValueError(f"origin longitude must be within [-180, 180], got {self.lon_deg}")
        if not math.isfinite(self.alt_m):
            raise ValueError(f"origin altitude must be finite, got {self.alt_m}")

    def _radii_m(self) -> tuple[float, float]:
        # Meridian radius M = a(1-e^2)/(1-e^2 sin^2 phi)^1.5, prime vertical N = a/sqrt(1-e^2 sin^2 phi).
        s = math.sin(math.radians(self.lat_deg))
        w = 1.0 - WGS84_E2 * s * s
        return WGS84_A_M * (1.0 - WGS84_E2) / w**1.5, WGS84_A_M / math.sqrt(w)

    def to_global(self, n_m: float, e_m: float, d_m: float) -> tuple[float, float, float]:
        """Local NED metres -> (lat_deg, lon_deg, alt_m)."""
        m_m, n_rad_m = self._radii_m()
        lat = self.lat_deg + math.degrees(n_m / (m_m + self.alt_m))
        lon = self.lon_deg + math.degrees(
            e_m / ((n_rad_m + self.alt_m) * math.cos(math.radians(self.lat_deg)))
        )
        return lat, lon, self.alt_m - d_m

    def to_local(self, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_m) -> local NED metres."""
        m_m, n_rad_m = self._radii_m()
        dlon = (lon_deg - self.lon_deg + 180.0) % 360.0 - 180.0
        n = math.radians(lat_deg - self.lat_deg) * (m_m + self.alt_m)
        e = math.radians(dlon) * (n_rad_m + self.alt_m) * math.cos(math.radians(self.lat_deg))
        return n, e, self.alt_m - alt_m


def mission_route_ned_m(
    items: Iterable[MissionItem], origin: GeoOrigin
) -> list[tuple[float, float, float]]:
    """The waypoints of mission `items` in local NED, in order: what
    the station and Foxglove draw as a vehicle's route. A global waypoint's altitude is AMSL,
    a local one's above the origin (up); the other items have no position of their own."""
    out = []
    for item in items:
        if item.kind is not MissionItemKind.WAYPOINT:
            continue
        if item.frame is MissionFrame.GLOBAL:
            out.append(origin.to_local(item.x, item.y, item.alt_m))
        else:
            out.append((float(item.x), float(item.y), -float(item.alt_m)))
    return out
