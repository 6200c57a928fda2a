"""Companion mode: fly a PX4 vehicle with velocity setpoints through the native MAVSDK 4.x binding.

MAVSDK's asyncio API runs on its own event loop in a background thread; the synchronous
`VehicleBackend` methods hand coroutines to it and wait with a timeout. Telemetry arrives through
subscriptions and is converted to the fleet's local NED frame with the fleet origin (the one
WGS-84 conversion, `comms.geo`). Every failure is a `BackendError` with the reason.

Offboard, as PX4 wants it: a setpoint must be streaming before the switch, and keep streaming
(>= 2 Hz). A background task re-sends the latest setpoint at `setpoint_hz`; if the agent stops
updating it for `setpoint_stale_s`, the task sends zero velocity instead, so a hung agent leaves a
hovering vehicle, not one flying off at its last velocity.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import math
import threading
import time
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass
from typing import Any

from agent.backends.base import (
    BackendError,
    Capability,
    Telemetry,
    VehicleBackend,
    pos_sigma_of,
)
from comms.geo import GeoOrigin
from comms.plan import FleetPlan
from comms.traffic import TrafficTrack, track_from_adsb


@dataclass(frozen=True)
class MavsdkConfig:
    """How to reach the autopilot and how patient to be with it."""

    connection: str = "udpin://0.0.0.0:14540"
    """MAVSDK connection URL (`udpin://0.0.0.0:14540`; MAVSDK rejects `udpin://:14540`)."""
    connect_timeout_s: float = 10.0
    """How long `wait_connected` and the first command wait for the autopilot to appear."""
    action_timeout_s: float = 6.0
    """Upper bound on one action (MAVSDK itself gives up after about 2 s without COMMAND_ACK)."""
    setpoint_hz: float = 20.0
    """Offboard setpoint re-send rate (PX4 needs >= 2 Hz; MAVSDK also streams at 20 Hz)."""
    setpoint_stale_s: float = 1.0
    """Agent silence after which the re-sent setpoint becomes zero velocity (hover)."""
    link_timeout_s: float = 2.0
    """No position for this long means the link is down (`Telemetry.link_ok` False)."""
    system_id: int | None = None
    """Fly the autopilot with this MAVLink system id (several may share one port); None: the first."""

    def __post_init__(self) -> None:
        if not self.connection.startswith(
            ("udpin://", "udpout://", "udp://", "tcpin://", "tcpout://", "tcp://", "serial://")
        ):
            raise ValueError(f"not a MAVSDK connection URL: {self.connection!r}")
        for name in (
            "connect_timeout_s",
            "action_timeout_s",
            "setpoint_hz",
            "setpoint_stale_s",
            "link_timeout_s",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass
class _Latest:
    """The newest telemetry samples, written on the MAVSDK loop, read by the agent."""

    pos_ned_m: tuple[float, float, float] | None = None
    pos_stamp_s: float = -math.inf
    vel_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    heading_rad: float = 0.0
    armed: bool = False
    in_air: bool = False
    battery_pct: float = math.nan
    connected: bool = False
    flight_mode: str = "UNKNOWN"
    pos_sigma_m: float = 0.0
    """The GNSS receiver's horizontal accuracy (RawGps.horizontal_uncertainty_m: GPS_RAW_INT
    h_acc, PX4's eph); 0 until one is reported."""


class MavsdkBackend(VehicleBackend):
    """One PX4 vehicle through MAVSDK. Use as a context manager."""

    capabilities = frozenset(
        {Capability.VELOCITY_SETPOINT, Capability.TRAFFIC_RECEIVER, Capability.GEOFENCE}
    )

    def __init__(
        self,
        cfg: MavsdkConfig | str,
        origin: GeoOrigin,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """`cfg` may be just the connection URL (`covey agent --vehicle mavsdk:<url>`)."""
        cfg = MavsdkConfig(connection=cfg) if isinstance(cfg, str) else cfg
        self.cfg, self.origin, self.clock = cfg, origin, clock
        self._latest = _Latest()
        self._lock = threading.Lock()
        self._setpoint: tuple[float, float, float, float] | None = None  # n, e, d m/s, yaw deg
        self._setpoint_s = -math.inf
        self._streaming = False
        self._seen_offboard = False  # PX4 confirmed OFFBOARD since we started streaming
        self._fatal: str | None = None
        self._closed = False
        self._system: Any = None
        self._plugins: dict[str, Any] = {}
        self._traffic: dict[int, TrafficTrack] = {}  # newest per ICAO since the last read
        self.traffic_reports = 0
        """ADS-B reports the transponder stream delivered (covey's own and unusable included)."""
        self._ready = threading.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="mavsdk-backend", daemon=True
        )
        self._thread.start()
        self._submit(self._start())

    # ---- lifecycle -----------------------------------------------------------------------------

    def _submit(self, coro: Coroutine[Any, Any, Any]) -> concurrent.futures.Future[Any]:
        return asyncio.run_coroutine_threadsafe(coro, self._loop)

    async def _start(self) -> None:
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk

        try:
            self._sdk = Mavsdk(
                Configuration.create_with_component_type(ComponentType.GROUND_STATION)
            )
            await self._sdk.add_any_connection(self.cfg.connection)
        except Exception as exc:  # noqa: BLE001 - MavsdkConnectionError, bad URL, port in use
            self._fatal = f"cannot open MAVSDK connection {self.cfg.connection}: {exc}"
            self._ready.set()
            return
        self._tasks.append(asyncio.create_task(self._discover()))

    async def _discover(self) -> None:
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.geofence import GeofenceAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
        from mavsdk.asyncio.plugins.transponder import TransponderAsync

        system = None
        while system is None and not self._closed:
            if self.cfg.system_id is None:
                system = await self._sdk.first_autopilot(timeout_s=1.0)
                continue
            for candidate in await self._sdk.get_systems():
                if (
                    await candidate.has_autopilot()
                    and await candidate.get_system_id() == self.cfg.system_id
                ):
                    system = candidate
            if system is None:
                await asyncio.sleep(0.1)
        if system is None:
            return
        self._system = system
        self._plugins = {
            "action": ActionAsync(system),
            "offboard": OffboardAsync(system),
            "telemetry": TelemetryAsync(system),
            "transponder": TransponderAsync(system),
            "geofence": GeofenceAsync(system),
        }
        tel = self._plugins["telemetry"]
        watchers = [
            (tel.subscribe_position(), self._on_position),
            (tel.subscribe_velocity_ned(), self._on_velocity),
            (tel.subscribe_heading(), self._on_heading),
            (tel.subscribe_armed(), lambda a: setattr(self._latest, "armed", bool(a))),
            (tel.subscribe_in_air(), lambda a: setattr(self._latest, "in_air", bool(a))),
            (
                tel.subscribe_battery(),
                lambda b: setattr(self._latest, "battery_pct", float(b.remaining_percent)),
            ),
            (tel.subscribe_flight_mode(), self._on_flight_mode),
            (tel.subscribe_raw_gps(), self._on_raw_gps),
            (system.is_connected_state(), lambda c: setattr(self._latest, "connected", bool(c))),
            (self._plugins["transponder"].subscribe_transponder(), self._on_transponder),
        ]
        self._latest.connected = await system.is_connected()
        self._tasks += [asyncio.create_task(self._watch(gen, fn)) for gen, fn in watchers]
        self._tasks.append(asyncio.create_task(self._stream_setpoints()))
        self._ready.set()

    @staticmethod
    async def _watch(gen: Any, on_item: Callable[[Any], None]) -> None:
        async for item in gen:
            with contextlib.suppress(Exception):  # a malformed sample must not end the stream
                on_item(item)

    def _on_raw_gps(self, g: Any) -> None:
        self._latest.pos_sigma_m = pos_sigma_of(float(g.horizontal_uncertainty_m))

    def _on_position(self, p: Any) -> None:
        if not all(
            math.isfinite(x) for x in (p.latitude_deg, p.longitude_deg, p.absolute_altitude_m)
        ):
            return
        ned = self.origin.to_local(p.latitude_deg, p.longitude_deg, p.absolute_altitude_m)
        with self._lock:
            self._latest.pos_ned_m, self._latest.pos_stamp_s = ned, self.clock()

    def _on_velocity(self, v: Any) -> None:
        self._latest.vel_ned_m_s = (float(v.north_m_s), float(v.east_m_s), float(v.down_m_s))

    def _on_flight_mode(self, mode: Any) -> None:
        with self._lock:
            self._latest.flight_mode = mode.name
            if self._streaming and mode.name == "OFFBOARD":
                self._seen_offboard = True

    def _on_transponder(self, a: Any) -> None:
        """One AdsbVehicle: traffic unless it is covey's own report (comms/adsb.py)."""
        self.traffic_reports += 1
        track = track_from_adsb(
            icao_address=int(a.icao_address),
            lat_deg=float(a.latitude_deg),
            lon_deg=float(a.longitude_deg),
            alt_m=float(a.absolute_altitude_m),
            heading_deg=float(a.heading_deg),
            hor_speed_m_s=float(a.horizontal_velocity_m_s),
            ver_speed_m_s=float(a.vertical_velocity_m_s),
            callsign=str(a.callsign),
            emitter_type=int(a.emitter_type),
            age_s=float(a.tslc_s),
            origin=self.origin,
            now_s=self.clock(),
        )
        if track is None:
            return
        with self._lock:
            if track.track_id in self._traffic or len(self._traffic) < 256:  # bounded per read
                self._traffic[track.track_id] = track

    def traffic_tracks(self, now_s: float) -> list[TrafficTrack]:
        with self._lock:
            tracks, self._traffic = list(self._traffic.values()), {}
        return tracks

    def _on_heading(self, h: Any) -> None:
        if math.isfinite(h.heading_deg):
            self._latest.heading_rad = math.radians(h.heading_deg)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self._submit(self._shutdown()).result(timeout=5.0)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5.0)
        if not self._thread.is_alive():
            self._loop.close()

    async def _shutdown(self) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        sdk = getattr(self, "_sdk", None)
        if sdk is not None:
            sdk.destroy()

    def wait_connected(self, timeout_s: float | None = None) -> bool:
        """Block until the autopilot has been discovered (True) or the timeout passes (False)."""
        return (
            self._ready.wait(self.cfg.connect_timeout_s if timeout_s is None else timeout_s)
            and not self._fatal
        )

    # ---- calls into the loop -------------------------------------------------------------------

    def _plugin(self, name: str) -> Any:
        if self._closed:
            raise BackendError("MAVSDK backend is closed")
        if not self._ready.wait(self.cfg.connect_timeout_s):
            raise BackendError(
                f"no autopilot on {self.cfg.connection} after {self.cfg.connect_timeout_s} s"
            )
        if self._fatal:
            raise BackendError(self._fatal)
        return self._plugins[name]

    def _call(self, what: str, coro_fn: Callable[[], Coroutine[Any, Any, Any]]) -> Any:
        """Run one MAVSDK coroutine on the loop; any failure becomes BackendError(what: why)."""
        future = self._submit(coro_fn())
        try:
            return future.result(timeout=self.cfg.action_timeout_s)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise BackendError(
                f"{what}: no answer from the autopilot in {self.cfg.action_timeout_s} s"
                f"{self._link_note()}"
            ) from None
        except Exception as exc:  # noqa: BLE001 - ActionError, OffboardError, ... all carry a reason
            raise BackendError(f"{what}: {exc}{self._link_note()}") from exc

    def _link_note(self) -> str:
        t = self.telemetry()
        return (
            "" if t is not None and t.link_ok else " (autopilot link lost: no heartbeat/telemetry)"
        )

    # ---- VehicleBackend ------------------------------------------------------------------------

    def telemetry(self) -> Telemetry | None:
        with self._lock:
            lt = self._latest
            if lt.pos_ned_m is None:
                return None
            fresh = self.clock() - lt.pos_stamp_s < self.cfg.link_timeout_s
            return Telemetry(
                stamp_s=lt.pos_stamp_s,
                pos_ned_m=lt.pos_ned_m,
                vel_ned_m_s=lt.vel_ned_m_s,
                heading_rad=lt.heading_rad,
                armed=lt.armed,
                in_air=lt.in_air,
                battery_pct=lt.battery_pct,
                link_ok=lt.connected and fresh and not self._closed,
                pos_sigma_m=lt.pos_sigma_m,
            )

    @property
    def flight_mode(self) -> str:
        """PX4 flight mode as MAVSDK names it (HOLD, OFFBOARD, LAND, ...)."""
        return self._latest.flight_mode

    def takeoff(self, alt_m: float) -> None:
        if not (math.isfinite(alt_m) and 0.5 <= alt_m <= 120.0):
            raise BackendError(f"takeoff altitude must be within [0.5, 120] m, got {alt_m}")
        action = self._plugin("action")
        self._stop_streaming()
        self._call("set takeoff altitude", lambda: action.set_takeoff_altitude(float(alt_m)))
        self._call("arm", action.arm)
        self._call("takeoff", action.takeoff)

    def land(self) -> None:
        action = self._plugin("action")
        self._stop_streaming()
        self._call("land", action.land)

    def hold(self) -> None:
        action = self._plugin("action")
        if self._stop_streaming() or self._latest.flight_mode == "OFFBOARD":
            # Leaves offboard (PX4 switches to HOLD) and stops MAVSDK's own setpoint stream.
            self._call("hold", self._plugins["offboard"].stop)
        else:
            self._call("hold", action.hold)

    def kill(self) -> None:
        action = self._plugin("action")
        self._stop_streaming()
        self._call("kill", action.kill)

    def upload_fence(self, plan: FleetPlan) -> None:
        """The plan's fence as an INCLUSION polygon and each keep-out zone as an EXCLUSION
        polygon, in WGS-84 around the fleet origin, through MAVSDK's geofence plugin (PX4 keeps
        it and acts on a breach: the backstop if covey's own checks fail). PX4's fence is
        two-dimensional: a zone with a floor or ceiling is uploaded closed at every altitude (the
        safe side), and the plan's ceiling is not sent (PX4's GF_MAX_VER_DIST is a parameter)."""
        from mavsdk.plugins.geofence import FenceType, GeofenceData, Point, Polygon

        def polygon(vertices_ne_m, kind: FenceType) -> Polygon:
            points = []
            for n, e in vertices_ne_m:
                lat, lon, _ = self.origin.to_global(n, e, 0.0)
                points.append(Point(lat, lon))
            return Polygon(points, kind)

        polygons = [polygon(plan.fence.vertices_ne_m, FenceType.INCLUSION)] if plan.fence else []
        polygons += [polygon(z.vertices_ne_m, FenceType.EXCLUSION) for z in plan.keep_out]
        geofence = self._plugin("geofence")
        if not polygons:
            self._call("clear geofence", geofence.clear_geofence)
            return
        data = GeofenceData(polygons, [])
        self._call(
            f"upload geofence (plan v{plan.version})", lambda: geofence.upload_geofence(data)
        )

    def set_velocity_ned(self, vel_ned_m_s: Sequence[float], heading_rad: float) -> None:
        v = tuple(float(x) for x in vel_ned_m_s)
        if len(v) != 3 or not all(math.isfinite(x) for x in v) or not math.isfinite(heading_rad):
            raise BackendError(
                f"velocity setpoint must be 3 finite numbers and a finite heading, got {vel_ned_m_s}, {heading_rad}"
            )
        offboard = self._plugin("offboard")
        if not self._latest.armed:
            raise BackendError(
                "cannot fly a velocity setpoint: vehicle is disarmed (take off first)"
            )
        with self._lock:
            mode = self._latest.flight_mode
            if self._streaming and self._seen_offboard and mode != "OFFBOARD":
                # PX4 left offboard (a failsafe, or a pilot or ground station took over): do not
                # grab control back silently. The agent sees the error; its next setpoint re-enters.
                self._streaming, self._setpoint = False, None
                raise BackendError(
                    f"vehicle left offboard (now {mode}); the next setpoint re-enters it"
                )
            self._setpoint = (v[0], v[1], v[2], math.degrees(heading_rad))
            self._setpoint_s = self.clock()
            if self._streaming:
                return  # the stream task sends it within 1 / setpoint_hz
        # PX4 refuses offboard unless setpoints already stream: send one first, then switch.
        self._call("offboard setpoint", lambda: offboard.set_velocity_ned(self._velocity_ned_yaw()))
        with self._lock:
            self._streaming, self._seen_offboard = True, False
        try:
            self._call("start offboard", offboard.start)
        except BackendError:
            self._stop_streaming()
            raise

    def _velocity_ned_yaw(self) -> Any:
        from mavsdk.asyncio.plugins.offboard import VelocityNedYaw

        with self._lock:
            sp = self._setpoint or (0.0, 0.0, 0.0, math.degrees(self._latest.heading_rad))
            if self.clock() - self._setpoint_s > self.cfg.setpoint_stale_s:
                sp = (0.0, 0.0, 0.0, sp[3])  # the agent went quiet: hover
        return VelocityNedYaw(*sp)

    def _stop_streaming(self) -> bool:
        with self._lock:
            was, self._streaming, self._setpoint = self._streaming, False, None
        return was

    async def _stream_setpoints(self) -> None:
        period_s = 1.0 / self.cfg.setpoint_hz
        while True:
            await asyncio.sleep(period_s)
            if not self._streaming:
                continue
            with contextlib.suppress(Exception):  # a lost link shows in telemetry, not here
                await self._plugins["offboard"].set_velocity_ned(self._velocity_ned_yaw())
