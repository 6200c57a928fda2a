"""Onboard mode end to end: two PX4 emulators run the C policy, each behind a relay agent on the
mesh. The agents forward each other's states as ADSB_VEHICLE; a head-on swap only stays
separated if that traffic reaches the autopilots (without it they fly straight through)."""

from __future__ import annotations

import itertools
import math
import socket
import threading
import time

import numpy as np
import pytest
from conftest import holds

from comms.commands import new_nonce
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, Mode, VehicleState
from comms.session import embedded_router, free_tcp_port

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ORIGIN = GeoOrigin(48.7490, 9.1050, 450.0)
STARTS = {1: (-12.0, 0.5), 2: (12.0, -0.5)}
ALT_M = 5.0
SEPARATION_M = 3.0


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_onboard_emulators_swap_behind_relay_agents(procs) -> None:
    pytest.importorskip("firmware.cpolicy")
    port = free_tcp_port()
    states: dict[int, VehicleState] = {}
    lock = threading.Lock()
    closest = [math.inf]

    def on_state(s: VehicleState, _t: int) -> None:
        with lock:
            states[s.vehicle_id] = s
            up = [v for v in states.values() if -v.pos_ned_m[2] > 2.0]
            for a, b in itertools.combinations(up, 2):
                closest[0] = min(closest[0], math.dist(a.pos_ned_m[:2], b.pos_ned_m[:2]))

    def wait(pred, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with lock:
                if set(states) >= set(STARTS) and holds(pred, states):
                    return
            time.sleep(0.05)
        raise AssertionError(
            f"timed out waiting for {what}: { {v: (s.mode.name, s.pos_ned_m) for v, s in states.items()} }"
        )

    with Mesh(embedded_router(port)) as mesh:
        mesh.declare_gcs(1)
        mesh.subscribe_states(on_state)
        presence = mesh.presence()
        for vid, (n, e) in STARTS.items():
            udp = free_udp_port()
            lat, lon, alt = ORIGIN.to_global(n, e, 0.0)
            procs.start(
                "-m",
                "firmware.sitl",
                "--id",
                str(vid),
                "--connect",
                f"udpout:127.0.0.1:{udp}",
                "--home",
                f"{lat:.9f},{lon:.9f},{alt:.3f}",
                "--onboard",
                "--separation-m",
                str(SEPARATION_M),
                "--policy-speed-m-s",
                "2",
                "--takeoff-speed-m-s",
                "3",
                "--pos-gain-1-s",
                "2",
                "--accel-m-s2",
                "8",
                output="inherit",
            )
            procs.start(
                "-m",
                "covey_cli",
                "agent",
                "--id",
                str(vid),
                "--connect",
                f"tcp/127.0.0.1:{port}",
                "--vehicle",
                f"relay:udpin:127.0.0.1:{udp}",
                "--origin",
                f"{ORIGIN.lat_deg},{ORIGIN.lon_deg},{ORIGIN.alt_m}",
                output="inherit",
            )
        assert presence.wait_for(lambda v, g: v >= set(STARTS), timeout_s=60)
        wait(
            lambda s: all(abs(s[v].pos_ned_m[0] - STARTS[v][0]) < 0.5 for v in STARTS),
            30,
            "telemetry from both",
        )
        result = mesh.send_command(
            Command.takeoff(ALT_M, nonce=new_nonce(), stamp_ns=time.time_ns()),
            expect=STARTS,
            timeout_s=10,
        )
        assert result.ok, result.summary()
        wait(lambda s: all(s[v].mode is Mode.HOLDING for v in STARTS), 40, "both at altitude")
        for vid, (n, e) in STARTS.items():
            goal = Command.goto_local(
                -n, -e, -ALT_M, nonce=new_nonce(), stamp_ns=time.time_ns(), targets=(vid,)
            )
            result = mesh.send_command(goal, timeout_s=10)
            assert result.ok, result.summary()
        wait(lambda s: all(s[v].mode is Mode.GOTO for v in STARTS), 10, "both flying")
        wait(lambda s: all(s[v].mode is Mode.HOLDING for v in STARTS), 90, "both arrived")
        for vid, (n, e) in STARTS.items():
            assert np.hypot(states[vid].pos_ned_m[0] + n, states[vid].pos_ned_m[1] + e) < 1.5
        print(f"closest approach during the onboard swap: {closest[0]:.2f} m")
        assert closest[0] >= SEPARATION_M
        result = mesh.send_command(
            Command(CommandKind.LAND, new_nonce(), time.time_ns()), expect=STARTS, timeout_s=10
        )
        assert result.ok, result.summary()
