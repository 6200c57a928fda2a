"""Three real agent processes (sim backend) on a real mesh, commanded by a test ground station."""

from __future__ import annotations

import itertools
import math
import os
import signal
import threading
import time

import numpy as np
import pytest
from conftest import holds

from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, Mode, VehicleState
from comms.session import embedded_router, free_tcp_port

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

SEPARATION_M = 3.0
RADIUS_M = 12.0
ALT_M = 8.0
IDS = (1, 2, 3)


class Watch:
    """The test's view of the fleet through the mesh: latest states and min separation."""

    def __init__(self, mesh: Mesh) -> None:
        self.lock = threading.Lock()
        self.states: dict[int, VehicleState] = {}
        self.min_sep_m = math.inf
        mesh.subscribe_states(self.on_state)

    def on_state(self, s: VehicleState, _t: int) -> None:
        with self.lock:
            self.states[s.vehicle_id] = s
            airborne = [v for v in self.states.values() if v.armed and -v.pos_ned_m[2] > 2.0]
            for a, b in itertools.combinations(airborne, 2):
                self.min_sep_m = min(
                    self.min_sep_m, float(np.linalg.norm(np.subtract(a.pos_ned_m, b.pos_ned_m)))
                )

    def wait(self, pred, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                if holds(pred, dict(self.states)):
                    return
            time.sleep(0.05)
        with self.lock:
            summary = {
                v: (s.mode.name, np.round(s.pos_ned_m, 1).tolist()) for v, s in self.states.items()
            }
        raise AssertionError(f"timed out waiting for {what}: {summary}")


def start_positions() -> dict[int, tuple[float, float]]:
    return {
        vid: (
            RADIUS_M * math.cos(2 * math.pi * k / len(IDS)),
            RADIUS_M * math.sin(2 * math.pi * k / len(IDS)),
        )
        for k, vid in enumerate(IDS)
    }


def agent_args(port: int, vid: int, start, *extra: str) -> list[str]:
    return [
        "-m",
        "covey_cli",
        "agent",
        "--id",
        str(vid),
        "--connect",
        f"tcp/127.0.0.1:{port}",
        f"--start-ne-m={start[0]:.3f},{start[1]:.3f}",
        "--cruise-speed-m-s",
        "2.0",
        *extra,
    ]


def send(mesh: Mesh, cmd: Command, expect, timeout_s: float = 5.0):
    result = mesh.send_command(cmd, expect=expect, timeout_s=timeout_s)
    assert result.ok, result.summary()
    return result


@pytest.fixture
def fleet(procs):
    port = free_tcp_port()
    with Mesh(embedded_router(port)) as mesh:
        watch = Watch(mesh)
        presence = mesh.presence()
        gcs = procs.start("tests/gcs_standin.py", str(port))
        gcs.wait_for("READY")
        starts = start_positions()
        agents = {
            vid: procs.start(
                *agent_args(
                    port, vid, starts[vid], "--gcs-lost-hold-s", "1", "--gcs-lost-land-s", "4"
                )
            )
            for vid in IDS
        }
        assert presence.wait_for(lambda v, g: v >= set(IDS) and g, timeout_s=60), (
            "agents did not come up"
        )
        watch.wait(lambda s: set(s) >= set(IDS), 20, "first states")
        yield mesh, watch, gcs, agents, starts


def takeoff_all(mesh: Mesh, watch: Watch) -> None:
    send(mesh, Command.takeoff(ALT_M, nonce=new_nonce(), stamp_ns=time.time_ns()), expect=IDS)
    watch.wait(lambda s: all(s[v].mode is Mode.HOLDING for v in IDS), 30, "all holding at altitude")


def test_swap_through_the_middle_keeps_separation(fleet) -> None:
    mesh, watch, _, _, starts = fleet
    # A goto while landed is refused with its reason.
    refused = mesh.send_command(
        Command.goto_local(0, 0, -5, nonce=new_nonce(), stamp_ns=0, targets=(1,)), timeout_s=5
    )
    assert (
        refused.outcomes[1].status is OutcomeStatus.REJECTED
        and "landed" in refused.outcomes[1].reason
    )
    takeoff_all(mesh, watch)
    for vid in IDS:
        n, e = starts[vid]
        send(
            mesh,
            Command.goto_local(-n, -e, -ALT_M, nonce=new_nonce(), stamp_ns=0, targets=(vid,)),
            expect=(vid,),
        )
    watch.wait(lambda s: all(s[v].mode is Mode.GOTO for v in IDS), 10, "all flying the goto")
    watch.wait(lambda s: all(s[v].mode is Mode.HOLDING for v in IDS), 120, "all arrived")
    for vid in IDS:
        n, e = starts[vid]
        assert (
            np.hypot(watch.states[vid].pos_ned_m[0] + n, watch.states[vid].pos_ned_m[1] + e) < 1.5
        )
    print(f"min separation during the swap: {watch.min_sep_m:.2f} m")
    assert watch.min_sep_m >= SEPARATION_M
    send(mesh, Command(CommandKind.LAND, new_nonce(), 0), expect=IDS)
    watch.wait(
        lambda s: all(s[v].mode is Mode.LANDED and not s[v].armed for v in IDS), 60, "all landed"
    )


def test_kill_drops_one_vehicle_while_the_others_fly_on(fleet) -> None:
    mesh, watch, _, _, _ = fleet
    takeoff_all(mesh, watch)
    send(
        mesh,
        Command.goto_local(0, 20, -ALT_M, nonce=new_nonce(), stamp_ns=0, targets=(2,)),
        expect=(2,),
    )
    t0 = time.monotonic()
    send(mesh, Command(CommandKind.KILL, new_nonce(), 0, targets=(1,)), expect=(1,))
    watch.wait(lambda s: s[1].mode is Mode.KILLED and not s[1].armed, 1.0, "vehicle 1 killed")
    drop_s = time.monotonic() - t0
    watch.wait(lambda s: -s[1].pos_ned_m[2] < ALT_M - 2.0, 3.0, "vehicle 1 falling")
    print(f"kill acknowledged and reported in {drop_s * 1000:.0f} ms")
    assert watch.states[3].mode is Mode.HOLDING and watch.states[3].armed
    assert watch.states[2].mode in (Mode.GOTO, Mode.HOLDING) and watch.states[2].armed
    refused = mesh.send_command(
        Command.takeoff(5.0, nonce=new_nonce(), stamp_ns=0, targets=(1,)), timeout_s=5
    )
    assert refused.outcomes[1].status is OutcomeStatus.REJECTED


def test_losing_the_ground_station_holds_then_lands(fleet) -> None:
    mesh, watch, gcs, _, _ = fleet
    takeoff_all(mesh, watch)
    send(
        mesh,
        Command.goto_local(-30, 0, -ALT_M, nonce=new_nonce(), stamp_ns=0, targets=(1,)),
        expect=(1,),
    )
    watch.wait(lambda s: s[1].mode is Mode.GOTO, 5, "vehicle 1 flying")
    os.kill(gcs.pid, signal.SIGKILL)
    watch.wait(lambda s: s[1].mode is Mode.HOLDING, 10, "failsafe hold")
    watch.wait(
        lambda s: all(s[v].mode in (Mode.LANDING, Mode.LANDED) for v in IDS), 20, "failsafe landing"
    )
    watch.wait(lambda s: all(s[v].mode is Mode.LANDED for v in IDS), 60, "all landed")
