"""Traffic that does not cooperate: vehicles that are not covey members, as the mesh carries them.

Tracks come from three places, all into one bounded `TrafficTable` per process:
  - the mesh: `TrafficReport`s of stations (`covey intruder`, a hand-flown vehicle) and of
    vehicles whose autopilot hears ADS-B (`TrafficListener`; keyed mode: a roster member's
    signature, fresh stamps, newest wins);
  - the autopilot's own receiver: MAVSDK's transponder stream in companion mode, ADSB_VEHICLE
    reports that are not covey's own in relay mode (`track_from_adsb`, comms/adsb.py);
  - a simulation (policy/scenarios.py `intruder` suite).

The agents merge the table into their guidance's neighbours (agent/traffic.py); the station and
Foxglove draw it. A track is dead-reckoned at constant velocity while fresh, flagged stale past
`stale_s` (guidance slows down near it) and forgotten past `drop_s`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from comms import adsb, keys
from comms.geo import GeoOrigin
from comms.member import MemberAuth
from comms.schema import (
    POSITION_LIMIT_M,
    SPEED_LIMIT_M_S,
    DecodeError,
    Role,
    TrafficFlag,
    TrafficReport,
    TrafficSource,
)

log = logging.getLogger(__name__)

TRAFFIC_ID_BASE = 1 << 32
"""A track's neighbour id is TRAFFIC_ID_BASE + its track id: never a covey vehicle's id."""
SIGN_LABEL = "traffic"
"""Domain label of a TrafficReport signature (trust/auth.py signs label, fleet and bytes)."""


@dataclass(frozen=True)
class TrafficConfig:
    """How long traffic stays useful, and how much of it is kept."""

    stale_s: float = 2.0
    """Older than this, a track is stale: guidance slows down near it (ADS-B comes at ~1-2 Hz)."""
    drop_s: float = 5.0
    """Older than this, a track is forgotten."""
    vertical_band_m: float = 15.0
    """Traffic further than this above or below is not a conflict (a manned aircraft overhead)."""
    max_tracks: int = 64
    """The most tracks held; a new one then replaces the one heard longest ago."""
    max_skew_s: float = 5.0
    """Keyed mode: a mesh report stamped further than this from our clock is refused."""

    def __post_init__(self) -> None:
        for name in ("stale_s", "drop_s", "vertical_band_m", "max_skew_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if self.drop_s < self.stale_s:
            raise ValueError(f"drop_s={self.drop_s} must be at least stale_s={self.stale_s}")
        if not 1 <= self.max_tracks <= 4096:
            raise ValueError(f"max_tracks must be within 1..4096, got {self.max_tracks}")


@dataclass(frozen=True)
class TrafficTrack:
    """One vehicle that does not cooperate, in the fleet's local NED frame."""

    track_id: int
    """ICAO address for ADS-B, else the reporter's own number."""
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    source: TrafficSource
    manned: bool
    stamp_s: float
    """When the position was true, on the receiving agent's clock."""
    emitter_type: int = 0
    callsign: str = ""

    @property
    def neighbour_id(self) -> int:
        return TRAFFIC_ID_BASE + self.track_id

    def at(self, now_s: float) -> np.ndarray:
        """Position dead-reckoned to `now_s`: p + v (now - stamp)."""
        age_s = max(0.0, now_s - self.stamp_s)
        return np.asarray(self.pos_ned_m, float) + np.asarray(self.vel_ned_m_s, float) * age_s

    def report(self, reporter_role: Role, reporter_id: int, stamp_ns: int) -> TrafficReport:
        """This track as a TrafficReport (unsigned) stamped `stamp_ns`."""
        return TrafficReport(
            reporter_role,
            reporter_id,
            self.track_id,
            self.source,
            stamp_ns,
            (float(self.pos_ned_m[0]), float(self.pos_ned_m[1]), float(self.pos_ned_m[2])),
            (float(self.vel_ned_m_s[0]), float(self.vel_ned_m_s[1]), float(self.vel_ned_m_s[2])),
            self.emitter_type,
            TrafficFlag.MANNED if self.manned else TrafficFlag.NONE,
        )


def _plausible(pos: tuple[float, ...], vel: tuple[float, ...]) -> bool:
    return (
        len(pos) == 3
        and len(vel) == 3
        and all(math.isfinite(x) and abs(x) <= POSITION_LIMIT_M for x in pos)
        and all(math.isfinite(x) and abs(x) <= SPEED_LIMIT_M_S for x in vel)
    )


def track_from_report(report: TrafficReport, recv_s: float, age_s: float = 0.0) -> TrafficTrack:
    """A mesh report as a track, stamped `age_s` before its receive time."""
    return TrafficTrack(
        report.track_id,
        report.pos_ned_m,
        report.vel_ned_m_s,
        report.source,
        report.manned,
        recv_s - max(0.0, age_s),
        report.emitter_type,
    )


def track_from_adsb(
    *,
    icao_address: int,
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    heading_deg: float,
    hor_speed_m_s: float,
    ver_speed_m_s: float,
    callsign: str,
    emitter_type: int,
    age_s: float,
    origin: GeoOrigin,
    now_s: float,
    source: TrafficSource = TrafficSource.ADSB,
) -> TrafficTrack | None:
    """An ADS-B report (MAVSDK AdsbVehicle or MAVLink ADSB_VEHICLE fields) as a track in local
    NED, or None when it is covey's own report (comms/adsb.py) or carries no usable position.
    Heading is the course over ground (0 = north, clockwise); vertical speed is positive up."""
    callsign = callsign.rstrip("\x00 ")
    if adsb.is_covey_report(icao_address, callsign, emitter_type):
        return None
    values = (lat_deg, lon_deg, alt_m)
    if not all(math.isfinite(x) for x in values) or abs(lat_deg) > 90 or abs(lon_deg) > 180:
        return None
    pos = origin.to_local(lat_deg, lon_deg, alt_m)
    course = math.radians(heading_deg) if math.isfinite(heading_deg) else 0.0
    speed = hor_speed_m_s if math.isfinite(hor_speed_m_s) else 0.0
    climb = ver_speed_m_s if math.isfinite(ver_speed_m_s) else 0.0
    vel = (speed * math.cos(course), speed * math.sin(course), -climb)
    if not _plausible(pos, vel):
        return None
    return TrafficTrack(
        int(icao_address) & 0xFFFF_FFFF,
        pos,
        vel,
        source,
        adsb.is_manned(emitter_type),
        now_s - max(0.0, age_s if math.isfinite(age_s) else 0.0),
        int(emitter_type),
        callsign,
    )


class TrafficTable:
    """Latest track per (source, track id); thread-safe (mesh and autopilot threads write, the
    guidance tick reads). Bounded by `max_tracks`, expired by `drop_s`."""

    def __init__(self, cfg: TrafficConfig = TrafficConfig()) -> None:
        self.cfg = cfg
        self._lock = threading.Lock()
        self._tracks: dict[tuple[int, int], TrafficTrack] = {}

    def __len__(self) -> int:
        with self._lock:
            return len(self._tracks)

    def put(self, track: TrafficTrack) -> bool:
        """Store `track` unless an as new one of the same traffic is held; False if dropped."""
        key = (int(track.source), track.track_id)
        with self._lock:
            prev = self._tracks.get(key)
            if prev is not None and prev.stamp_s > track.stamp_s:
                return False
            if prev is None and len(self._tracks) >= self.cfg.max_tracks:
                oldest = min(self._tracks, key=lambda k: self._tracks[k].stamp_s)
                if self._tracks[oldest].stamp_s > track.stamp_s:
                    return False
                del self._tracks[oldest]
            self._tracks[key] = track
        return True

    def tracks(self, now_s: float) -> list[TrafficTrack]:
        """The tracks heard within `drop_s`, in track id order (older ones are forgotten)."""
        with self._lock:
            for key in [k for k, t in self._tracks.items() if now_s - t.stamp_s > self.cfg.drop_s]:
                del self._tracks[key]
            return sorted(self._tracks.values(), key=lambda t: (t.track_id, t.source))


def is_traffic_id(neighbour_id: int) -> bool:
    return neighbour_id >= TRAFFIC_ID_BASE


class TrafficListener:
    """Mesh traffic reports into a table. Keyed mode (`mesh.auth`): only a roster member's
    signed report, stamped within `max_skew_s` of our clock and newer than the last accepted
    one of that reporter's track; open mode: every well-formed report. Use as a context manager."""

    def __init__(
        self,
        mesh: Any,
        table: TrafficTable,
        clock_s: Callable[[], float],
        on_track: Callable[[TrafficTrack, TrafficReport], None] | None = None,
    ) -> None:
        self.mesh, self.table, self.clock_s, self.on_track = mesh, table, clock_s, on_track
        self.accepted = 0
        self.refused: dict[str, int] = {}
        """Refusals per cause (unsigned, stale, out of order, unknown signer or forged, bad)."""
        self._last_ns: dict[tuple[int, int, int], int] = {}
        self._lock = threading.Lock()
        self._sub = mesh.session.declare_subscriber(keys.all_traffic(mesh.fleet), self._on_sample)

    def _refuse(self, cause: str) -> None:
        with self._lock:
            self.refused[cause] = self.refused.get(cause, 0) + 1

    def _on_sample(self, sample: Any) -> None:
        try:
            report = TrafficReport.decode(sample.payload.to_bytes())
        except DecodeError:
            self._refuse("malformed")
            return
        try:
            self.admit(report)
        except Exception:  # noqa: BLE001 - one bad report must never stop the listener
            log.exception("traffic report not handled")

    def admit(self, report: TrafficReport) -> str | None:
        """Take `report` into the table; None if accepted, else the cause of its refusal."""
        now_ns = self.mesh.clock_ns()
        auth = self.mesh.auth
        cause = None
        key = (int(report.reporter_role), report.reporter_id, report.track_id)
        if auth is not None:
            with self._lock:
                last = self._last_ns.get(key)
            if not report.sig:
                cause = "unsigned"
            elif abs(now_ns - report.stamp_ns) > self.table.cfg.max_skew_s * 1e9:
                cause = "stale"
            elif last is not None and report.stamp_ns <= last:
                cause = "out of order"
            else:
                why = auth.check_signature(
                    report.reporter_role,
                    report.reporter_id,
                    SIGN_LABEL,
                    report.signed_bytes(),
                    report.sig,
                )
                cause = None if why is None else "forged or unknown signer"
        if cause is not None:
            self._refuse(cause)
            return cause
        with self._lock:
            self._last_ns[key] = report.stamp_ns
            if len(self._last_ns) > 4 * self.table.cfg.max_tracks:  # bounded: drop the oldest
                del self._last_ns[min(self._last_ns, key=self._last_ns.__getitem__)]
            self.accepted += 1
        # The reporter's clock and ours agree within the skew window (keyed mode checks it): the
        # report's age is how long it took to get here, dead reckoning covers it.
        age_s = max(0.0, (now_ns - report.stamp_ns) * 1e-9) if auth is not None else 0.0
        track = track_from_report(report, self.clock_s(), min(age_s, self.table.cfg.stale_s))
        self.table.put(track)
        if self.on_track is not None:
            self.on_track(track, report)
        return None

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closed already
            pass

    def __enter__(self) -> TrafficListener:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def sign_report(auth: MemberAuth, report: TrafficReport) -> TrafficReport:
    """`report` signed by `auth` (its role and member id must be the reporter's)."""
    if auth.role is not report.reporter_role or auth.member_id != report.reporter_id:
        raise ValueError(
            f"a report of {report.reporter_role.name.lower()} {report.reporter_id} needs that "
            f"member's key, not {auth.key.name}'s"
        )
    return dataclasses.replace(report, sig=auth._sign(SIGN_LABEL, report.signed_bytes()))


def publish_report(mesh: Any, report: TrafficReport) -> None:
    """Put `report` on its reporter's traffic key, signed with the mesh's key in keyed mode."""
    if mesh.auth is not None:
        report = sign_report(mesh.auth, report)
    key = (
        keys.gcs_traffic(mesh.fleet, report.reporter_id)
        if report.reporter_role is Role.STATION
        else keys.vehicle_traffic(mesh.fleet, report.reporter_id)
    )
    mesh.session.put(key, report.encode())
