"""MAVSDK 4.x (native binding) against the PX4 emulator in its own process, over real UDP.

First raw MAVSDK calls (what DESIGN.md measured), then the same flight through MavsdkBackend.
Waits are bounded polls of telemetry; nothing asserts on timing.
"""

from __future__ import annotations

import asyncio
import math
import socket
import time

import pytest

from agent.backends.base import BackendError, Capability, NotSupported
from agent.backends.mavsdk_backend import MavsdkBackend, MavsdkConfig
from comms.geo import GeoOrigin
from firmware.sitl.process import SitlProcess, free_udp_port

pytestmark = pytest.mark.e2e

HOME = GeoOrigin(48.7490, 9.1050, 450.0)
ORIGIN = GeoOrigin(48.7489, 9.1049, 450.0)
"""The fleet origin: about 11 m south and 7 m west of the emulator's home."""
HOME_NED_M = ORIGIN.to_local(HOME.lat_deg, HOME.lon_deg, HOME.alt_m)
FAST = [
    "--takeoff-speed-m-s",
    "5",
    "--pos-gain-1-s",
    "3",
    "--accel-m-s2",
    "15",
    "--land-speed-m-s",
    "4",
    "--cruise-speed-m-s",
    "8",
    "--disarm-after-land-s",
    "0.3",
]


def sitl(port: int, *extra: str) -> SitlProcess:
    home = f"{HOME.lat_deg},{HOME.lon_deg},{HOME.alt_m}"
    return SitlProcess(
        ["--id", "1", "--connect", f"udpout:127.0.0.1:{port}", "--home", home, *FAST, *extra]
    )


# ---- raw MAVSDK ----------------------------------------------------------------------------------


async def until(gen, pred, timeout_s: float = 15.0):
    """First item of an async telemetry stream that satisfies `pred` (bounded wait)."""

    async def first():
        async for item in gen:
            if pred(item):
                return item
        raise AssertionError("stream ended")

    try:
        return await asyncio.wait_for(first(), timeout_s)
    finally:
        await gen.aclose()


async def raw_flight(port: int) -> None:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync, ActionError
    from mavsdk.asyncio.plugins.offboard import OffboardAsync, OffboardError, VelocityNedYaw
    from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync

    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await sdk.first_autopilot(timeout_s=10.0)
        assert system is not None, "no autopilot discovered"
        tel, action, offboard = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
        await until(tel.subscribe_health_all_ok(), bool)
        health = await until(tel.subscribe_health(), lambda h: True)
        assert health.is_global_position_ok and health.is_home_position_ok and health.is_armable
        home = await until(tel.subscribe_home(), lambda h: True)
        assert home.latitude_deg == pytest.approx(HOME.lat_deg, abs=1e-6)

        # Offboard without a setpoint: MAVSDK refuses on its own side already.
        with pytest.raises(OffboardError):
            await offboard.start()

        await action.set_takeoff_altitude(4.0)
        assert await action.get_takeoff_altitude() == pytest.approx(4.0)
        await action.arm()
        await action.takeoff()
        await until(tel.subscribe_position(), lambda p: p.relative_altitude_m > 3.7)
        assert await tel.in_air()
        with pytest.raises(ActionError):  # PX4: "Disarming denied: not landed"
            await action.disarm()

        start = await tel.position()
        await offboard.set_velocity_ned(VelocityNedYaw(0.0, 3.0, 0.0, 90.0))
        await offboard.start()
        await until(tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD)
        moved = await until(
            tel.subscribe_position(), lambda p: p.longitude_deg > start.longitude_deg + 4e-5
        )
        assert abs(moved.latitude_deg - start.latitude_deg) < 1e-5  # east, not north
        await offboard.stop()
        await until(tel.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD)

        # goto: COMMAND_INT DO_REPOSITION.
        lat, lon, alt = HOME.to_global(10.0, 5.0, -6.0)
        await action.goto_location(lat, lon, alt, 0.0)
        await until(
            tel.subscribe_position(),
            lambda p: (
                abs(p.latitude_deg - lat) < 2e-6
                and abs(p.longitude_deg - lon) < 3e-6
                and abs(p.absolute_altitude_m - alt) < 0.3
            ),
        )
        with pytest.raises(ActionError):  # out of range: denied
            await action.goto_location(123.0, lon, alt, 0.0)
        with pytest.raises(ActionError):  # NaN: denied (MAVSDK sends it as an out-of-range degE7)
            await action.goto_location(math.nan, math.nan, alt, 0.0)

        await action.hold()
        await until(
            tel.subscribe_velocity_ned(), lambda v: math.hypot(v.north_m_s, v.east_m_s) < 0.1
        )
        assert await tel.flight_mode() == FlightMode.HOLD

        await action.land()
        await until(tel.subscribe_armed(), lambda a: not a)
        assert not await tel.in_air()

        await action.arm()
        await action.takeoff()
        await until(tel.subscribe_position(), lambda p: p.relative_altitude_m > 2.0)
        await action.kill()
        await until(tel.subscribe_position(), lambda p: p.relative_altitude_m < 0.05)
        assert not await tel.armed()


def test_raw_mavsdk_flies_the_emulator() -> None:
    port = free_udp_port()
    with sitl(port) as proc:
        try:
            asyncio.run(asyncio.wait_for(raw_flight(port), 60.0))
        finally:
            assert proc.alive(), proc.output()


# ---- MavsdkBackend -------------------------------------------------------------------------------


def wait_for(backend, pred, timeout_s: float = 15.0, what: str = "condition"):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        t = backend.telemetry()
        if t is not None and pred(t):
            return t
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}; last telemetry {backend.telemetry()}")


def fly_until(backend, vel_ned_m_s, heading_rad, pred, timeout_s: float = 15.0):
    """Stream velocity setpoints at 20 Hz, as the agent's loop does, until `pred(telemetry)`."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        backend.set_velocity_ned(vel_ned_m_s, heading_rad)
        t = backend.telemetry()
        if t is not None and pred(t) and backend.flight_mode == "OFFBOARD":
            return t
        time.sleep(0.05)
    raise AssertionError(f"offboard flight did not get there; last telemetry {backend.telemetry()}")


def test_backend_flies_the_emulator_in_the_fleet_frame() -> None:
    port = free_udp_port()
    cfg = MavsdkConfig(
        connection=f"udpin://127.0.0.1:{port}", link_timeout_s=1.0, action_timeout_s=4.0
    )
    with sitl(port) as proc, MavsdkBackend(cfg, ORIGIN) as vb:
        assert vb.capabilities == {
            Capability.VELOCITY_SETPOINT,
            Capability.TRAFFIC_RECEIVER,
            Capability.GEOFENCE,
        }
        assert vb.wait_connected()
        t = wait_for(vb, lambda t: True, what="first telemetry")
        assert t.pos_ned_m == pytest.approx(
            HOME_NED_M, abs=0.05
        )  # home, seen from the fleet origin
        assert t.link_ok and not t.armed and not t.in_air
        with pytest.raises(BackendError, match="disarmed"):
            vb.set_velocity_ned((1.0, 0.0, 0.0), 0.0)
        with pytest.raises(NotSupported):
            vb.goto_local((0.0, 0.0, -5.0))

        vb.takeoff(4.0)
        t = wait_for(vb, lambda t: t.pos_ned_m[2] < -3.7, what="takeoff altitude")
        assert t.armed and t.in_air and t.battery_pct <= 100.0

        start = t.pos_ned_m
        t = fly_until(
            vb,
            (2.0, -2.0, 0.0),
            -math.pi / 4,
            lambda t: t.pos_ned_m[0] - start[0] > 1.5 and start[1] - t.pos_ned_m[1] > 1.5,
        )
        assert vb.flight_mode == "OFFBOARD"
        assert t.vel_ned_m_s[0] > 1.0 and t.vel_ned_m_s[1] < -1.0
        # The agent goes quiet: the backend's re-send turns into a hover, not a fly-away.
        time.sleep(cfg.setpoint_stale_s + 0.2)
        wait_for(
            vb, lambda t: math.hypot(*t.vel_ned_m_s[:2]) < 0.05, what="stale setpoint -> hover"
        )
        assert vb.flight_mode == "OFFBOARD"
        wait_for(vb, lambda t: abs(t.heading_rad - 7 * math.pi / 4) < 0.05, what="heading")

        vb.hold()
        wait_for(vb, lambda t: vb.flight_mode == "HOLD", what="HOLD mode (heartbeat at 1 Hz)")
        wait_for(vb, lambda t: math.hypot(*t.vel_ned_m_s[:2]) < 0.05, what="hold")

        vb.land()
        wait_for(vb, lambda t: not t.armed and not t.in_air, what="landed and disarmed")

        vb.takeoff(3.0)
        wait_for(vb, lambda t: t.pos_ned_m[2] < -2.0, what="second takeoff")
        vb.kill()
        t = wait_for(vb, lambda t: t.pos_ned_m[2] > -0.05, what="drop")
        assert not t.armed

        proc.stop()  # heartbeat loss
        wait_for(vb, lambda t: not t.link_ok, what="link loss")
        with pytest.raises(BackendError, match="land"):
            vb.land()


def test_backend_reports_refusals_as_backend_errors() -> None:
    port = free_udp_port()
    # A bare URL, as `covey agent --vehicle mavsdk:<url>` passes it.
    url = f"udpin://127.0.0.1:{port}"
    with sitl(port, "--unhealthy") as proc, MavsdkBackend(url, origin=ORIGIN) as vb:
        assert vb.wait_connected()
        with pytest.raises(BackendError, match="takeoff altitude"):
            vb.takeoff(math.nan)
        with pytest.raises(
            BackendError, match="arm"
        ):  # PX4: "Arming denied: preflight checks failed"
            vb.takeoff(3.0)
        with pytest.raises(BackendError, match="finite"):
            vb.set_velocity_ned((math.inf, 0.0, 0.0), 0.0)
        assert proc.alive()


def test_backend_without_an_autopilot_fails_with_a_reason() -> None:
    cfg = MavsdkConfig(connection=f"udpin://127.0.0.1:{free_udp_port()}", connect_timeout_s=0.5)
    with MavsdkBackend(cfg, ORIGIN) as vb:
        assert not vb.wait_connected(0.2)
        assert vb.telemetry() is None
        with pytest.raises(BackendError, match="no autopilot"):
            vb.land()
    with pytest.raises(BackendError, match="closed"):
        vb.hold()


def test_backend_reports_a_bad_connection_url() -> None:
    with pytest.raises(ValueError, match="connection"):
        MavsdkConfig(connection="14540")
    with (
        MavsdkBackend(MavsdkConfig(connection="udpin://256.0.0.1:1"), ORIGIN) as vb,
        pytest.raises(BackendError, match="connection"),
    ):
        vb.land()


def test_backend_picks_its_vehicle_among_several_on_one_port() -> None:
    port = free_udp_port()
    other = GeoOrigin(48.7500, 9.1070, 455.0)
    cfg = MavsdkConfig(connection=f"udpin://127.0.0.1:{port}", system_id=2)
    with sitl(port) as first, MavsdkBackend(cfg, ORIGIN) as vb:
        # Vehicle 1 is heard first; the backend must keep waiting for vehicle 2.
        assert not vb.wait_connected(1.0)
        second = SitlProcess(
            [
                "--id",
                "2",
                "--connect",
                f"udpout:127.0.0.1:{port}",
                "--home",
                f"{other.lat_deg},{other.lon_deg},{other.alt_m}",
            ]
        )
        with second:
            assert vb.wait_connected(), first.output() + second.output()
            t = wait_for(vb, lambda t: True, what="telemetry of vehicle 2")
            assert t.pos_ned_m == pytest.approx(
                ORIGIN.to_local(other.lat_deg, other.lon_deg, other.alt_m), abs=0.05
            )


def test_backend_does_not_grab_control_back_after_a_takeover() -> None:
    """A ground station on PX4's other link switches to HOLD mid-offboard: the agent is told."""
    from pymavlink.dialects.v20 import common as mavlink

    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.settimeout(5.0)
        cfg = MavsdkConfig(connection=f"udpin://127.0.0.1:{port}", action_timeout_s=4.0)
        with (
            sitl(port, "--connect", f"udpout:127.0.0.1:{gcs.getsockname()[1]}") as proc,
            MavsdkBackend(cfg, ORIGIN) as vb,
        ):
            assert vb.wait_connected(), proc.output()
            _, emulator = gcs.recvfrom(65535)
            vb.takeoff(3.0)
            wait_for(vb, lambda t: t.pos_ned_m[2] < -2.7, what="takeoff")
            fly_until(vb, (1.0, 0.0, 0.0), 0.0, lambda t: True)
            hold = mavlink.MAVLink_command_long_message(
                1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 3, 0, 0, 0, 0
            )
            gcs.sendto(hold.pack(mavlink.MAVLink(None, srcSystem=250, srcComponent=190)), emulator)
            wait_for(
                vb, lambda t: vb.flight_mode == "HOLD", what="HOLD by the other ground station"
            )
            with pytest.raises(BackendError, match="left offboard"):
                vb.set_velocity_ned((1.0, 0.0, 0.0), 0.0)
            # The agent decides to take over again.
            fly_until(vb, (1.0, 0.0, 0.0), 0.0, lambda t: True)
