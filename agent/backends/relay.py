"""Onboard mode: the paper's Raspberry Pi relay between the mesh and a PX4 that runs the policy.

The autopilot flies goto targets with the policy itself; this backend only relays. It reads the
autopilot's own state (GLOBAL_POSITION_INT, LOCAL_POSITION_NED, ATTITUDE, HEARTBEAT, ...) as
`Telemetry` in the fleet's local NED frame, forwards the neighbours as ADSB_VEHICLE traffic
reports (PX4 ingests them as transponder reports), and sends ground-station commands as MAVLink
commands, waiting for COMMAND_ACK. A refusal or a missing ack is a `BackendError` that carries
the MAV_RESULT and the autopilot's own STATUSTEXT explanation when it sent one.
"""

from __future__ import annotations

import logging
import math
import select
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from agent.backends.base import (
    BackendError,
    Capability,
    Telemetry,
    Traffic,
    VehicleBackend,
    pos_sigma_of,
)
from comms import adsb
from comms.geo import GeoOrigin
from comms.mavlink_udp import LinkUrl, UdpLink
from comms.schema import POSITION_LIMIT_M, SPEED_LIMIT_M_S
from comms.traffic import TRAFFIC_ID_BASE, TrafficTrack, track_from_adsb

log = logging.getLogger(__name__)

KILL_MAGIC = 21196.0
"""ARM_DISARM param2 that forces a disarm in the air."""
PX4_HOLD = (4, 3)
"""PX4 (main, sub) mode of HOLD (AUTO_LOITER)."""
ADSB_FLAGS = (
    mavlink.ADSB_FLAGS_VALID_COORDS
    | mavlink.ADSB_FLAGS_VALID_ALTITUDE
    | mavlink.ADSB_FLAGS_VALID_HEADING
    | mavlink.ADSB_FLAGS_VALID_VELOCITY
    | mavlink.ADSB_FLAGS_VALID_CALLSIGN
    | mavlink.ADSB_FLAGS_SIMULATED
    | mavlink.ADSB_FLAGS_VERTICAL_VELOCITY_VALID
)
HEARTBEAT = mavlink.MAVLink_heartbeat_message(
    mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
    mavlink.MAV_AUTOPILOT_INVALID,
    0,
    0,
    mavlink.MAV_STATE_ACTIVE,
    3,
)
"""Ours: a companion computer, not an autopilot."""
_CHECKED = frozenset({"GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "ATTITUDE"})
"""Messages whose values become the vehicle's published state: checked before use."""


def _plausible(msg: Any) -> bool:
    """Whether a state message's values can be a real vehicle's (finite, within the wire limits).

    A corrupt or hostile autopilot message is dropped rather than copied into Telemetry, where it
    would stop the agent from encoding its VehicleState."""
    kind = msg.get_type()
    if kind == "GLOBAL_POSITION_INT":
        return (
            abs(msg.lat) <= 90e7
            and abs(msg.lon) <= 180e7
            and abs(msg.alt) <= POSITION_LIMIT_M * 1e3
        )
    if kind == "LOCAL_POSITION_NED":
        vals = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
        return all(math.isfinite(v) for v in vals) and all(
            abs(v) < SPEED_LIMIT_M_S for v in vals[3:]
        )
    if kind == "ATTITUDE":
        return math.isfinite(msg.yaw) and abs(msg.yaw) <= 4.0 * math.pi
    return True


RESULT_BY_VALUE = {k: v.name for k, v in mavlink.enums["MAV_RESULT"].items()}


@dataclass(frozen=True)
class RelayConfig:
    """How the relay reaches its autopilot."""

    connection: str = "udpin:0.0.0.0:14550"
    """`udpin:HOST:PORT` (listen; the autopilot sends here) or `udpout:HOST:PORT` (send to it)."""
    source_system: int = 245
    """Our MAVLink system id."""
    source_component: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
    """Our MAVLink component id (a companion computer)."""
    target_system: int | None = None
    """The autopilot's system id; None: the first PX4 heartbeat heard."""
    ack_timeout_s: float = 1.0
    """Wait for COMMAND_ACK per attempt."""
    attempts: int = 3
    """Sends of one command before giving up (MAVLink's command protocol retransmits)."""
    connect_timeout_s: float = 10.0
    """How long a command waits for the autopilot's first heartbeat."""
    link_timeout_s: float = 2.0
    """No heartbeat for this long means the link is down (`Telemetry.link_ok` False)."""
    heartbeat_hz: float = 1.0
    """Our own heartbeat rate (PX4 watches companion heartbeats)."""
    echo_window_s: float = 10.0
    """An ADSB_VEHICLE the autopilot streams under an address we sent it as mesh traffic within
    this long is our own report's echo, not new traffic."""

    def __post_init__(self) -> None:
        LinkUrl.parse(self.connection)  # raises ValueError with the expected form
        if self.attempts < 1:
            raise ValueError(f"attempts must be at least 1, got {self.attempts}")
        for name in (
            "ack_timeout_s",
            "connect_timeout_s",
            "link_timeout_s",
            "heartbeat_hz",
            "echo_window_s",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


SEPARATION_PARAM = "CVY_SEP_M"
"""The covey PX4 module's separation (firmware/px4/covey_guidance): the relay reads it, so that
the flight core's goal rule keeps the clearance the autopilot's filter keeps."""
SEPARATION_ASKS = 5
"""PARAM_REQUEST_READs of SEPARATION_PARAM once the autopilot is heard (an autopilot without
the module stays silent: the configured --separation-m is then assumed)."""
SEPARATION_ASK_PERIOD_S = 2.0
MAX_SEPARATION_M = 1000.0
"""A CVY_SEP_M above this (or not finite, or not positive) is refused as implausible."""


@dataclass
class _State:
    """Latest autopilot state (written by the receive thread, read under the lock)."""

    pos_ned_m: tuple[float, float, float] | None = None
    pos_stamp_s: float = -math.inf
    vel_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    heading_rad: float = 0.0
    armed: bool = False
    landed_state: int = mavlink.MAV_LANDED_STATE_UNDEFINED
    rel_alt_m: float = 0.0
    battery_pct: float = math.nan
    pos_sigma_m: float = 0.0
    """GPS_RAW_INT h_acc in metres (PX4 sends its eph there); 0 until one is reported."""
    onboard_separation_m: float | None = None
    """The PX4 module's CVY_SEP_M once the autopilot answered for it (`SEPARATION_PARAM`)."""
    custom_mode: int = 0
    heartbeat_s: float = -math.inf


class RelayBackend(VehicleBackend):
    """Relay to one PX4 autopilot that runs the policy onboard. Use as a context manager."""

    takes_global_targets = True
    capabilities = frozenset(
        {Capability.ONBOARD_GUIDANCE, Capability.TRAFFIC_INPUT, Capability.TRAFFIC_RECEIVER}
    )

    def __init__(
        self,
        cfg: RelayConfig | str,
        origin: GeoOrigin,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """`cfg` may be just the connection URL (`covey agent --vehicle relay:<url>`)."""
        cfg = RelayConfig(connection=cfg) if isinstance(cfg, str) else cfg
        self.cfg, self.origin, self.clock = cfg, origin, clock
        try:
            self._link = UdpLink(cfg.connection, cfg.source_system, cfg.source_component)
        except OSError as exc:
            raise BackendError(f"cannot open {cfg.connection}: {exc}") from exc
        self._target = cfg.target_system
        self._state = _State()
        self._cond = threading.Condition()
        self._acks: dict[int, int] = {}  # command id -> MAV_RESULT of the newest ack
        self._texts: list[tuple[float, str]] = []
        self._param: tuple[str, float] | None = None  # newest PARAM_VALUE (name, value)
        self._send_lock = threading.Lock()
        self._closed = False
        self.rejected_messages = 0
        """Autopilot state messages dropped as implausible (NaN, inf, out of range)."""
        self._traffic: dict[int, TrafficTrack] = {}  # real traffic heard since the last read
        self._sent_traffic_s: dict[int, float] = {}  # ICAO -> when we last sent it as traffic
        self._heard_traffic_s: dict[int, float] = {}  # ICAO -> when the autopilot last had it
        self.own_echoes = 0
        """ADSB_VEHICLE reports that were covey's own (neighbours or forwarded traffic) echoed
        back by the autopilot: never taken for traffic."""
        self._thread = threading.Thread(target=self._receive_loop, name="relay-rx", daemon=True)
        self._thread.start()

    # ---- link ----------------------------------------------------------------------------------

    def _receive_loop(self) -> None:
        next_hb_s = 0.0
        next_ask_s, asked = 0.0, 0
        while not self._closed:
            now = self.clock()
            if now >= next_hb_s:
                next_hb_s = now + 1.0 / self.cfg.heartbeat_hz
                self._send(HEARTBEAT)
            if (  # ask for the onboard separation until the autopilot answers
                now >= next_ask_s
                and asked < SEPARATION_ASKS
                and self._target is not None
                and self._state.onboard_separation_m is None
            ):
                next_ask_s, asked = now + SEPARATION_ASK_PERIOD_S, asked + 1
                self._send(
                    mavlink.MAVLink_param_request_read_message(
                        self._target, 1, SEPARATION_PARAM.encode(), -1
                    )
                )
            try:
                select.select([self._link], [], [], 0.05)
            except (OSError, ValueError):  # closed under us
                return
            for msg in self._link.receive():  # garbage is dropped there, never raised
                self._on_message(msg)

    def _send(self, msg: Any) -> None:
        try:
            with self._send_lock:
                self._link.send(msg)
        except Exception as exc:  # noqa: BLE001 - struct.error on an out-of-range field
            raise BackendError(f"cannot encode {msg.get_type()}: {exc}") from exc

    def _on_message(self, msg: Any) -> None:
        kind, src = msg.get_type(), msg.get_srcSystem()
        if (
            kind == "HEARTBEAT"
            and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
            and self._target in (None, src)
        ):
            with self._cond:
                self._target = src
                s = self._state
                s.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                s.custom_mode, s.heartbeat_s = msg.custom_mode, self.clock()
                self._cond.notify_all()
            return
        if src != self._target:
            return
        with self._cond:
            s = self._state
            if kind in _CHECKED and not _plausible(msg):
                self.rejected_messages += 1  # one bad value must not poison the vehicle's state
                if self.rejected_messages in (1, 10, 100, 1000):
                    log.warning(
                        "ignored implausible %s from the autopilot (%d so far): %s",
                        kind,
                        self.rejected_messages,
                        msg,
                    )
                return
            if kind == "GLOBAL_POSITION_INT":
                pos = self.origin.to_local(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
                if not all(abs(v) <= POSITION_LIMIT_M for v in pos):
                    self.rejected_messages += 1
                    log.warning("ignored a position %s m from the fleet origin", pos)
                    return
                s.pos_ned_m = pos
                s.pos_stamp_s, s.rel_alt_m = self.clock(), msg.relative_alt * 1e-3
                s.vel_ned_m_s = (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)
                if msg.hdg != 65535:
                    s.heading_rad = math.radians(msg.hdg * 0.01) % (2.0 * math.pi)
            elif kind == "LOCAL_POSITION_NED":
                s.vel_ned_m_s = (msg.vx, msg.vy, msg.vz)  # finer than GLOBAL_POSITION_INT's cm/s
            elif kind == "ATTITUDE":
                s.heading_rad = msg.yaw % (2.0 * math.pi)
            elif kind == "EXTENDED_SYS_STATE":
                s.landed_state = msg.landed_state
            elif kind == "GPS_RAW_INT":  # h_acc (mm) is a MAVLink 2 extension: 0 if absent
                s.pos_sigma_m = pos_sigma_of(getattr(msg, "h_acc", 0) * 1e-3)
            elif kind == "SYS_STATUS" and msg.battery_remaining >= 0:
                s.battery_pct = float(min(msg.battery_remaining, 100))
            elif kind == "COMMAND_ACK" and msg.target_system in (0, self.cfg.source_system):
                self._acks[msg.command] = msg.result
                self._cond.notify_all()
            elif kind == "STATUSTEXT":
                self._texts = [*self._texts[-19:], (self.clock(), msg.text.rstrip("\x00"))]
            elif kind == "PARAM_VALUE":
                self._param = (msg.param_id.rstrip("\x00"), msg.param_value)
                if self._param[0] == SEPARATION_PARAM:
                    value = float(msg.param_value)
                    if math.isfinite(value) and 0.0 < value <= MAX_SEPARATION_M:
                        s.onboard_separation_m = value
                    else:
                        log.warning("ignored %s = %r from the autopilot", SEPARATION_PARAM, value)
                self._cond.notify_all()
            elif kind == "ADSB_VEHICLE":
                self._on_adsb(msg)

    def _on_adsb(self, msg: Any) -> None:
        """A traffic report the autopilot holds (called under the lock): real traffic becomes a
        track; covey's own neighbour reports and the echo of traffic we forwarded do not."""
        callsign = (
            msg.callsign
            if isinstance(msg.callsign, str)
            else bytes(msg.callsign).decode("ascii", "replace")
        )
        callsign = callsign.rstrip("\x00 ")
        icao, now = int(msg.ICAO_address), self.clock()
        sent_s = self._sent_traffic_s.get(icao, -math.inf)
        if adsb.is_covey_report(icao, callsign, msg.emitter_type) or (
            callsign.startswith(adsb.TRAFFIC_CALLSIGN_PREFIX)
            and now - sent_s <= self.cfg.echo_window_s
        ):
            self.own_echoes += 1
            return
        flags = int(msg.flags)
        if not flags & mavlink.ADSB_FLAGS_VALID_COORDS:
            return
        track = track_from_adsb(
            icao_address=icao,
            lat_deg=msg.lat * 1e-7,
            lon_deg=msg.lon * 1e-7,
            alt_m=msg.altitude * 1e-3 if flags & mavlink.ADSB_FLAGS_VALID_ALTITUDE else math.nan,
            heading_deg=msg.heading * 0.01 if flags & mavlink.ADSB_FLAGS_VALID_HEADING else 0.0,
            hor_speed_m_s=msg.hor_velocity * 0.01
            if flags & mavlink.ADSB_FLAGS_VALID_VELOCITY
            else 0.0,
            ver_speed_m_s=msg.ver_velocity * 0.01
            if flags & mavlink.ADSB_FLAGS_VERTICAL_VELOCITY_VALID
            else 0.0,
            callsign=callsign,
            emitter_type=int(msg.emitter_type),
            age_s=float(msg.tslc),
            origin=self.origin,
            now_s=now,
        )
        if track is None:  # no altitude, or not a position covey can use
            return
        self._heard_traffic_s[icao] = now
        if icao in self._traffic or len(self._traffic) < 256:  # bounded between reads
            self._traffic[icao] = track
        if len(self._heard_traffic_s) > 1024:
            cutoff = now - self.cfg.echo_window_s
            self._heard_traffic_s = {k: t for k, t in self._heard_traffic_s.items() if t >= cutoff}

    def traffic_tracks(self, now_s: float) -> list[TrafficTrack]:
        with self._cond:
            tracks, self._traffic = list(self._traffic.values()), {}
        return tracks

    # ---- lifecycle -----------------------------------------------------------------------------

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._thread.join(timeout=2.0)
        self._link.close()

    def wait_connected(self, timeout_s: float | None = None) -> bool:
        """Block until a PX4 heartbeat has been heard (True) or the timeout passes (False)."""
        with self._cond:
            return self._cond.wait_for(
                lambda: self._target is not None and self._link.peer is not None,
                self.cfg.connect_timeout_s if timeout_s is None else timeout_s,
            )

    def _require_link(self) -> int:
        if self._closed:
            raise BackendError("relay is closed")
        if not self.wait_connected():
            raise BackendError(
                f"no autopilot heartbeat on {self.cfg.connection} after {self.cfg.connect_timeout_s} s"
            )
        assert self._target is not None
        return self._target

    # ---- commands ------------------------------------------------------------------------------

    def _command(
        self,
        what: str,
        command: int,
        params: Sequence[float],
        *,
        global_xyz: tuple[int, int, float] | None = None,
    ) -> None:
        """Send COMMAND_LONG (or COMMAND_INT with x/y/z) and wait for an ACCEPTED ack."""
        target = self._require_link()
        sent_s = self.clock()
        p = [float(x) for x in params] + [math.nan] * (7 - len(params))
        for attempt in range(self.cfg.attempts):
            with self._cond:
                self._acks.pop(command, None)
            if global_xyz is None:
                self._send(mavlink.MAVLink_command_long_message(target, 1, command, attempt, *p))
            else:
                x, y, z = global_xyz
                self._send(
                    mavlink.MAVLink_command_int_message(
                        target, 1, mavlink.MAV_FRAME_GLOBAL, command, 0, 0, *p[:4], x, y, z
                    )
                )
            with self._cond:
                got = self._cond.wait_for(
                    lambda: self._acks.get(command, -1) not in (-1, mavlink.MAV_RESULT_IN_PROGRESS),
                    self.cfg.ack_timeout_s,
                )
                result = self._acks.get(command)
            if got and result == mavlink.MAV_RESULT_ACCEPTED:
                return
            if got:
                raise BackendError(
                    f"{what} refused: {RESULT_BY_VALUE.get(result, result)}{self._explain(sent_s)}"
                )
        raise BackendError(
            f"{what}: no COMMAND_ACK after {self.cfg.attempts} tries of {self.cfg.ack_timeout_s} s"
            f"{'' if self.link_ok else ' (autopilot link lost)'}"
        )

    def _explain(self, since_s: float) -> str:
        """The autopilot's STATUSTEXTs since the command was sent (PX4 says why it refused)."""
        time.sleep(0.05)  # PX4 may send its explanation just after the ack
        with self._cond:
            texts = [t for s, t in self._texts if s >= since_s]
        return f" ({'; '.join(texts)})" if texts else ""

    def _set_param(self, name: str, value: float) -> None:
        target = self._require_link()
        for _ in range(self.cfg.attempts):
            with self._cond:
                self._param = None
            self._send(
                mavlink.MAVLink_param_set_message(
                    target, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32
                )
            )
            with self._cond:
                if self._cond.wait_for(
                    lambda: self._param is not None and self._param[0] == name,
                    self.cfg.ack_timeout_s,
                ):
                    if self._param is not None and math.isclose(
                        self._param[1], value, rel_tol=1e-6
                    ):
                        return
                    raise BackendError(f"parameter {name} = {value} refused by the autopilot")
        raise BackendError(f"parameter {name}: no PARAM_VALUE after {self.cfg.attempts} tries")

    @property
    def link_ok(self) -> bool:
        return not self._closed and self.clock() - self._state.heartbeat_s < self.cfg.link_timeout_s

    def telemetry(self) -> Telemetry | None:
        with self._cond:
            s = self._state
            if s.pos_ned_m is None:
                return None
            in_air = (
                s.landed_state
                in (
                    mavlink.MAV_LANDED_STATE_IN_AIR,
                    mavlink.MAV_LANDED_STATE_TAKEOFF,
                    mavlink.MAV_LANDED_STATE_LANDING,
                )
                if s.landed_state != mavlink.MAV_LANDED_STATE_UNDEFINED
                else s.rel_alt_m > 0.3
            )
            return Telemetry(
                stamp_s=s.pos_stamp_s,
                pos_ned_m=s.pos_ned_m,
                vel_ned_m_s=s.vel_ned_m_s,
                heading_rad=s.heading_rad,
                armed=s.armed,
                in_air=in_air,
                battery_pct=s.battery_pct,
                link_ok=self.link_ok,
                pos_sigma_m=s.pos_sigma_m,
                onboard_separation_m=s.onboard_separation_m,
            )

    def takeoff(self, alt_m: float) -> None:
        if not (math.isfinite(alt_m) and 0.5 <= alt_m <= 120.0):
            raise BackendError(f"takeoff altitude must be within [0.5, 120] m, got {alt_m}")
        self._set_param("MIS_TAKEOFF_ALT", float(alt_m))
        self._command("arm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [1.0, 0.0])
        # param7 NaN: PX4 climbs to MIS_TAKEOFF_ALT above home.
        self._command("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF, [])

    def land(self) -> None:
        self._command("land", mavlink.MAV_CMD_NAV_LAND, [])

    def hold(self) -> None:
        main, sub = PX4_HOLD
        self._command(
            "hold",
            mavlink.MAV_CMD_DO_SET_MODE,
            [mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub],
        )

    def kill(self) -> None:
        self._command("kill", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [0.0, KILL_MAGIC])

    def goto_local(self, pos_ned_m: Sequence[float]) -> None:
        p = [float(x) for x in pos_ned_m]
        if len(p) != 3 or not all(math.isfinite(x) for x in p):
            raise BackendError(f"goto position must be 3 finite numbers (NED m), got {pos_ned_m}")
        self.goto_global(*self.origin.to_global(*p))

    def goto_global(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        g = [float(lat_deg), float(lon_deg), float(alt_m)]
        if not all(math.isfinite(x) for x in g) or abs(g[0]) > 90 or abs(g[1]) > 180:
            raise BackendError(f"goto target must be a finite lat, lon, alt, got {tuple(g)}")
        # DO_REPOSITION: speed default (-1), switch mode (flag 1), yaw unchanged (NaN).
        self._command(
            "goto",
            mavlink.MAV_CMD_DO_REPOSITION,
            [-1.0, mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0.0, math.nan],
            global_xyz=(round(g[0] * 1e7), round(g[1] * 1e7), g[2]),
        )

    def send_traffic(self, traffic: Sequence[Traffic]) -> None:
        """Neighbours under covey's marking; traffic that does not cooperate under its own
        address, unless the autopilot heard it itself (never echoed back as new)."""
        self._require_link()
        bad = []
        now = self.clock()
        for t in traffic:
            values = (*t.pos_ned_m, *t.vel_ned_m_s, t.heading_rad, t.age_s)
            vid = t.vehicle_id
            ok_id = 0 < vid < 0x1_0000 if t.cooperative else vid >= TRAFFIC_ID_BASE
            if not all(math.isfinite(x) for x in values) or not ok_id:
                bad.append(vid)
                continue
            if not t.cooperative:
                icao = (vid - TRAFFIC_ID_BASE) & 0xFFFF_FFFF
                with self._cond:
                    heard_s = self._heard_traffic_s.get(icao, -math.inf)
                    if now - heard_s <= self.cfg.echo_window_s:
                        continue  # the autopilot's own receiver has it: do not echo it back
                    self._sent_traffic_s[icao] = now
                    if len(self._sent_traffic_s) > 1024:
                        cutoff = now - self.cfg.echo_window_s
                        self._sent_traffic_s = {
                            k: s for k, s in self._sent_traffic_s.items() if s >= cutoff
                        }
            self._send(adsb_vehicle(t, self.origin))
        if bad:
            raise BackendError(
                f"traffic of vehicles {bad} not sent: non-finite fields, or a vehicle id outside "
                "covey's ICAO block (1..65535)"
            )


def adsb_vehicle(t: Traffic, origin: GeoOrigin) -> Any:
    """One neighbour as an ADSB_VEHICLE report under covey's marking (ICAO address in covey's
    block, callsign CVY<id>, emitter UAV: comms/adsb.py); traffic that does not cooperate under
    its own address (the track id), callsign TRF, and its emitter class (manned or not)."""
    lat, lon, alt = origin.to_global(*t.pos_ned_m)
    if t.cooperative:
        icao, callsign, emitter = (
            adsb.covey_icao(t.vehicle_id),
            adsb.covey_callsign(t.vehicle_id),
            mavlink.ADSB_EMITTER_TYPE_UAV,
        )
    else:
        icao = (t.vehicle_id - TRAFFIC_ID_BASE) & 0xFFFF_FFFF
        callsign = f"{adsb.TRAFFIC_CALLSIGN_PREFIX}{icao & 0xFFFFF:X}"
        emitter = mavlink.ADSB_EMITTER_TYPE_LIGHT if t.manned else mavlink.ADSB_EMITTER_TYPE_NO_INFO
    vn, ve, vd = t.vel_ned_m_s
    heading_cdeg = round(math.degrees(t.heading_rad) * 100.0) % 36000
    return mavlink.MAVLink_adsb_vehicle_message(
        icao,
        round(lat * 1e7),
        round(lon * 1e7),
        mavlink.ADSB_ALTITUDE_TYPE_GEOMETRIC,
        round(alt * 1000.0),
        heading_cdeg,
        min(65535, round(math.hypot(vn, ve) * 100.0)),
        max(-32767, min(32767, round(-vd * 100.0))),
        callsign.encode()[:8],
        emitter,
        min(255, round(t.age_s)),
        ADSB_FLAGS,
        0,
    )
