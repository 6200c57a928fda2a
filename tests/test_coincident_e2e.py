"""Two real agents started at one point separate after take-off (issue 39, finding 7).

The README's multi-site example starts agents without `--start-ne-m`, so simulated vehicles
start at one spot. Before: after take-off they hovered 0.0 m apart indefinitely (the filter had
no direction to push exactly coincident vehicles). Now the pair's ids give one
(policy.safety.untie), and they end at least the separation apart.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import Command, Mode, VehicleState
from comms.session import embedded_router, free_tcp_port

pytestmark = [pytest.mark.e2e]

SEPARATION_M = 3.0
IDS = (1, 7)
ALT_M = 5.0
SEPARATE_WITHIN_S = 40.0
"""Bounded: at 1 m/s each, 3 m take a few seconds; the rest is start-up and climb slack."""


def test_two_agents_started_at_one_point_separate(procs) -> None:
    port = free_tcp_port()
    latest: dict[int, VehicleState] = {}
    lock = threading.Lock()

    def on_state(s: VehicleState, _t: int) -> None:
        with lock:
            latest[s.vehicle_id] = s

    def gap_m() -> float:
        with lock:
            a, b = (latest.get(v) for v in IDS)
        if a is None or b is None:
            return math.nan
        return float(np.hypot(*np.subtract(a.pos_ned_m, b.pos_ned_m)[:2]))

    with Mesh(embedded_router(port)) as mesh:
        mesh.subscribe_states(on_state)
        presence = mesh.presence()
        procs.start("tests/gcs_standin.py", str(port)).wait_for("READY")
        for vid in IDS:  # no --start-ne-m: both start at the simulator's default spot
            procs.start(
                "-m",
                "covey_cli",
                "agent",
                "--id",
                str(vid),
                "--connect",
                f"tcp/127.0.0.1:{port}",
            )
        assert presence.wait_for(lambda v, g: v >= set(IDS) and g, timeout_s=60)
        deadline = time.monotonic() + 20
        while math.isnan(gap_m()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert gap_m() < 0.01, f"both should start at one point, {gap_m():.3f} m apart"
        result = mesh.send_command(
            Command.takeoff(ALT_M, nonce=new_nonce(), stamp_ns=time.time_ns()), expect=IDS
        )
        assert result.ok, result.summary()
        t0 = time.monotonic()
        while time.monotonic() - t0 < SEPARATE_WITHIN_S:
            with lock:
                holding = all(latest[v].mode is Mode.HOLDING for v in IDS)
            if holding and gap_m() >= SEPARATION_M:
                break
            time.sleep(0.1)
        took_s = time.monotonic() - t0
        print(f"coincident pair: {gap_m():.2f} m apart {took_s:.1f} s after the take-off")
        assert gap_m() >= SEPARATION_M, f"still {gap_m():.2f} m apart after {took_s:.0f} s"
        time.sleep(3.0)  # and they stay apart while holding
        assert gap_m() >= SEPARATION_M * 0.95, f"came back to {gap_m():.2f} m"
