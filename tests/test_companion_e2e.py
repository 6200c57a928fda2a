"""Companion mode end to end: `covey agent --vehicle mavsdk:...` flies the PX4 emulator through
the native MAVSDK binding, commanded over the mesh: takeoff, goto (the policy's velocity
setpoints in offboard), hold, land, and kill."""

from __future__ import annotations

import math
import socket
import threading
import time

import pytest

from comms.commands import new_nonce
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, Mode, VehicleState
from comms.session import embedded_router, free_tcp_port

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ORIGIN = GeoOrigin(48.7490, 9.1050, 450.0)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_agent_flies_px4_emulator_through_mavsdk(procs) -> None:
    port, udp = free_tcp_port(), free_udp_port()
    latest: list[VehicleState] = []
    lock = threading.Lock()

    def on_state(s: VehicleState, _t: int) -> None:
        with lock:
            latest[:] = [s]

    def wait(pred, timeout_s: float, what: str) -> VehicleState:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with lock:
                if latest and pred(latest[0]):
                    return latest[0]
            time.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}: {latest}")

    def send(cmd: Command) -> None:
        result = mesh.send_command(cmd, timeout_s=10)
        assert result.ok, result.summary()

    origin = f"{ORIGIN.lat_deg},{ORIGIN.lon_deg},{ORIGIN.alt_m}"
    with Mesh(embedded_router(port)) as mesh:
        mesh.declare_gcs(1)
        mesh.subscribe_states(on_state)
        procs.start(
            "-m",
            "firmware.sitl",
            "--id",
            "1",
            "--connect",
            f"udpout:127.0.0.1:{udp}",
            "--home",
            origin,
            "--takeoff-speed-m-s",
            "4",
            "--land-speed-m-s",
            "3",
            "--accel-m-s2",
            "8",
            output="inherit",
        )
        procs.start(
            "-m",
            "covey_cli",
            "agent",
            "--id",
            "1",
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--vehicle",
            f"mavsdk:udpin://127.0.0.1:{udp}",
            "--origin",
            origin,
            "--cruise-speed-m-s",
            "3",
            output="inherit",
        )
        wait(lambda s: True, 60, "telemetry through MAVSDK")
        send(Command.takeoff(4.0, nonce=new_nonce(), stamp_ns=time.time_ns(), targets=(1,)))
        wait(
            lambda s: s.mode is Mode.HOLDING and s.armed and -s.pos_ned_m[2] > 3.5,
            40,
            "airborne and holding",
        )
        send(
            Command.goto_local(
                12.0, 6.0, -4.0, nonce=new_nonce(), stamp_ns=time.time_ns(), targets=(1,)
            )
        )
        moving = wait(
            lambda s: s.mode is Mode.GOTO and math.hypot(*s.vel_ned_m_s[:2]) > 1.0,
            20,
            "offboard velocity",
        )
        assert moving.vel_ned_m_s[0] > 0  # towards the goal
        arrived = wait(lambda s: s.mode is Mode.HOLDING, 40, "arrival")
        assert math.dist(arrived.pos_ned_m[:2], (12.0, 6.0)) < 1.5
        send(
            Command.goto_local(
                -10.0, 0.0, -4.0, nonce=new_nonce(), stamp_ns=time.time_ns(), targets=(1,)
            )
        )
        wait(lambda s: s.mode is Mode.GOTO, 10, "second goto")
        send(Command(CommandKind.HOLD, new_nonce(), time.time_ns(), targets=(1,)))
        held = wait(
            lambda s: s.mode is Mode.HOLDING and math.hypot(*s.vel_ned_m_s[:2]) < 0.3, 20, "hold"
        )
        time.sleep(2.0)
        assert math.dist(latest[0].pos_ned_m[:2], held.pos_ned_m[:2]) < 1.0
        send(Command(CommandKind.LAND, new_nonce(), time.time_ns(), targets=(1,)))
        wait(lambda s: s.mode is Mode.LANDED and not s.armed, 40, "landed and disarmed")
        send(Command.takeoff(4.0, nonce=new_nonce(), stamp_ns=time.time_ns(), targets=(1,)))
        wait(lambda s: -s.pos_ned_m[2] > 2.5, 40, "second climb")
        send(Command(CommandKind.KILL, new_nonce(), time.time_ns(), targets=(1,)))
        wait(lambda s: s.mode is Mode.KILLED and not s.armed, 10, "killed and disarmed")
        wait(lambda s: -s.pos_ned_m[2] < 0.2, 10, "fallen")
