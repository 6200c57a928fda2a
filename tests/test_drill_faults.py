"""Fault drills on real processes: kill -9 an agent, restart the ground station, partition the
mesh, restart the router. Each drill checks what DESIGN.md and agent/failsafe.py promise.
The routers that are not this test's own are `covey router` processes.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest
from conftest import holds

from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, Mode, StateFlag, VehicleState
from comms.session import MeshConfig, embedded_peer, embedded_router, free_tcp_port

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ALT_M = 3.0


class Watch:
    """Latest state per vehicle, and every state seen, through one mesh session."""

    def __init__(self, mesh: Mesh) -> None:
        self.lock = threading.Lock()
        self.states: dict[int, VehicleState] = {}
        self.count = 0
        mesh.subscribe_states(self.on_state)

    def on_state(self, s: VehicleState, _t: int) -> None:
        with self.lock:
            self.states[s.vehicle_id] = s
            self.count += 1

    def wait(self, pred, timeout_s: float, what: str) -> float:
        """Seconds until pred(states) held; AssertionError with the fleet's state if never."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            with self.lock:
                states = dict(self.states)
            if holds(pred, states):
                return time.monotonic() - t0
            time.sleep(0.02)
        with self.lock:
            summary = {
                v: (s.mode.name, f"{int(s.flags):#x}", s.seq) for v, s in self.states.items()
            }
        raise AssertionError(f"timed out after {timeout_s} s waiting for {what}: {summary}")

    def forget(self) -> None:
        with self.lock:
            self.states.clear()


def agent_args(vid: int, *mesh: str, extra: tuple[str, ...] = ()) -> list[str]:
    return [
        "-m",
        "covey_cli",
        "agent",
        "--id",
        str(vid),
        *mesh,
        f"--start-ne-m=0,{4 * vid}",
        "--cruise-speed-m-s",
        "2.0",
        *extra,
    ]


def router_args(listen: str, *connect: str) -> list[str]:
    return ["-m", "covey_cli", "router", "--listen", listen, *(f"--connect={c}" for c in connect)]


def ok(mesh: Mesh, cmd: Command, expect, timeout_s: float = 5.0):
    result = mesh.send_command(cmd, expect=expect, timeout_s=timeout_s)
    assert result.ok, result.summary()
    return result


def fly_away(mesh: Mesh, watch: Watch, ids, north_m: float = 80.0) -> None:
    ok(mesh, Command.takeoff(ALT_M, nonce=new_nonce(), stamp_ns=0), expect=ids)
    watch.wait(lambda s: all(s[v].mode is Mode.HOLDING for v in ids), 20, "holding at altitude")
    for vid in ids:
        ok(
            mesh,
            Command.goto_local(
                north_m, 4.0 * vid, -ALT_M, nonce=new_nonce(), stamp_ns=0, targets=(vid,)
            ),
            expect=(vid,),
        )
    watch.wait(lambda s: all(s[v].mode is Mode.GOTO for v in ids), 5, "flying the goto")


# -- 1. kill -9 an agent ----------------------------------------------------------------------
def test_kill9_agent_is_lost_within_a_second_and_the_others_fly_on(procs) -> None:
    port = free_tcp_port()
    lost_at: dict[int, float] = {}
    with Mesh(embedded_router(port)) as gcs:
        watch = Watch(gcs)
        presence = gcs.presence(
            on_change=lambda kind, vid, alive: (
                None if alive or kind != "vehicle" else lost_at.setdefault(vid, time.monotonic())
            )
        )
        gcs.declare_gcs(1)
        agents = {
            vid: procs.start(*agent_args(vid, "--connect", f"tcp/127.0.0.1:{port}"))
            for vid in (1, 2)
        }
        assert presence.wait_for(lambda v, _g: v >= {1, 2}, timeout_s=60)
        watch.wait(lambda s: set(s) >= {1, 2}, 10, "first states")
        t_kill = time.monotonic()
        os.kill(agents[1].pid, signal.SIGKILL)
        assert presence.wait_for(lambda v, _g: 1 not in v, timeout_s=5), "vehicle 1 still present"
        loss_s = lost_at[1] - t_kill
        print(f"kill -9 -> presence lost in {loss_s * 1000:.0f} ms")
        assert loss_s < 1.0
        # The survivor still answers and publishes (landed and idle: at 1 Hz).
        seq = watch.states[2].seq
        watch.wait(lambda s: s[2].seq > seq + 2, 5, "vehicle 2 still publishing")
        assert presence.vehicles == {2}


# -- 2. restart the ground station -------------------------------------------------------------
def test_ground_station_restart_holds_then_resumes_and_a_fresh_station_rebuilds_the_fleet(
    procs,
) -> None:
    port = free_tcp_port()
    ids = (1, 2)
    with Mesh(
        embedded_router(port)
    ) as hub:  # the mesh's router and the test's eyes; no station token
        watch = Watch(hub)
        presence = hub.presence()
        station = procs.start("tests/gcs_standin.py", str(port))
        station.wait_for("READY")
        for vid in ids:
            procs.start(
                *agent_args(
                    vid,
                    "--connect",
                    f"tcp/127.0.0.1:{port}",
                    extra=("--gcs-lost-hold-s", "1", "--gcs-lost-land-s", "30"),
                )
            )
        assert presence.wait_for(lambda v, g: v >= set(ids) and g, timeout_s=60)
        fly_away(hub, watch, ids)
        os.kill(station.pid, signal.SIGKILL)
        held_s = watch.wait(
            lambda s: all(
                s[v].mode is Mode.HOLDING and s[v].flags & StateFlag.FAILSAFE_GCS_LOST for v in ids
            ),
            6,
            "failsafe hold",
        )
        print(f"station killed -> all holding after {held_s:.1f} s (hold threshold 1 s)")
        time.sleep(1.0)
        assert all(watch.states[v].mode is Mode.HOLDING for v in ids), (
            "they must hold, not land, within gcs_lost_land_s"
        )
        station = procs.start("tests/gcs_standin.py", str(port))
        station.wait_for("READY")
        resumed_s = watch.wait(
            lambda s: all(
                s[v].mode is Mode.GOTO and not s[v].flags & StateFlag.FAILSAFE_GCS_LOST for v in ids
            ),
            5,
            "goto resumed",
        )
        print(f"station back -> goto resumed after {resumed_s:.2f} s")
        # A fresh station knows nothing: presence (liveliness history) and states rebuild the fleet.
        t0 = time.monotonic()
        with Mesh(embedded_peer(port)) as fresh:
            fresh_watch = Watch(fresh)
            fresh_presence = fresh.presence()
            assert fresh_presence.wait_for(lambda v, _g: v >= set(ids), timeout_s=5)
            fresh_watch.wait(lambda s: set(s) >= set(ids), 5, "the fresh station's first states")
            print(
                f"fresh station rebuilt the fleet {sorted(fresh_presence.vehicles)} in {time.monotonic() - t0:.2f} s"
            )
            assert all(fresh_watch.states[v].mode is Mode.GOTO for v in ids)


# -- 3. partition --------------------------------------------------------------------------------
def test_partition_triggers_the_documented_failsafes_and_heals(procs) -> None:
    """Ground side: this test's router (station token). Vehicle side: a router process with the
    agents as its clients. A third router process is the only bridge between them; kill it."""
    gcs_port, veh_port = free_tcp_port(), free_tcp_port()
    ids = (1, 2)
    veh_router = procs.start(*router_args(f"tcp/127.0.0.1:{veh_port}"))
    veh_router.wait_for("READY")
    with (
        Mesh(embedded_router(gcs_port)) as gcs,
        Mesh(MeshConfig(mode="client", connect=(f"tcp/127.0.0.1:{veh_port}",))) as veh_side,
    ):
        gcs.declare_gcs(1)
        gcs_presence = gcs.presence()
        watch = Watch(veh_side)  # eyes on the vehicle side of the cut
        bridge = procs.start(
            *router_args(
                "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{gcs_port}", f"tcp/127.0.0.1:{veh_port}"
            )
        )
        bridge.wait_for("READY")
        for vid in ids:
            procs.start(
                *agent_args(
                    vid,
                    "--mesh-mode",
                    "client",
                    "--connect",
                    f"tcp/127.0.0.1:{veh_port}",
                    extra=("--gcs-lost-hold-s", "1", "--gcs-lost-land-s", "4"),
                )
            )
        assert gcs_presence.wait_for(lambda v, _g: v >= set(ids), timeout_s=60), (
            "agents not visible across the bridge"
        )
        fly_away(gcs, watch, ids)
        os.kill(bridge.pid, signal.SIGKILL)
        t_cut = time.monotonic()
        assert gcs_presence.wait_for(lambda v, _g: not v & set(ids), timeout_s=3), (
            "the station still sees the vehicles"
        )
        print(f"cut -> station lost the vehicles in {time.monotonic() - t_cut:.2f} s")
        hold_s = watch.wait(
            lambda s: all(
                s[v].mode is Mode.HOLDING and s[v].flags & StateFlag.FAILSAFE_GCS_LOST for v in ids
            ),
            6,
            "failsafe hold",
        )
        land_s = watch.wait(
            lambda s: all(s[v].mode in (Mode.LANDING, Mode.LANDED) for v in ids),
            10,
            "failsafe landing",
        )
        print(
            f"cut -> hold after {hold_s:.1f} s, landing after {hold_s + land_s:.1f} s (thresholds 1 s, 4 s)"
        )
        # Heal: the bridge comes back; the station sees the fleet again and can command it.
        bridge = procs.start(
            *router_args(
                "tcp/127.0.0.1:0", f"tcp/127.0.0.1:{gcs_port}", f"tcp/127.0.0.1:{veh_port}"
            )
        )
        bridge.wait_for("READY")
        assert gcs_presence.wait_for(lambda v, _g: v >= set(ids), timeout_s=10), (
            "fleet not back after the heal"
        )
        watch.wait(
            lambda s: all(not s[v].flags & StateFlag.FAILSAFE_GCS_LOST for v in ids),
            5,
            "failsafe flag cleared",
        )
        result = gcs.send_command(
            Command(CommandKind.LAND, new_nonce(), 0), expect=ids, timeout_s=5
        )
        assert set(result.outcomes) == set(ids) and all(
            o.ack is not None for o in result.outcomes.values()
        ), result.summary()


# -- 4. restart the router ---------------------------------------------------------------------
def test_router_restart_on_the_same_port_everything_reconnects(procs) -> None:
    port = free_tcp_port()
    ids = (1, 2)
    router = procs.start(*router_args(f"tcp/127.0.0.1:{port}"))
    router.wait_for("READY")
    client = MeshConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
    with Mesh(client) as gcs:
        gcs.declare_gcs(1)
        watch = Watch(gcs)
        presence = gcs.presence()
        for vid in ids:
            procs.start(
                *agent_args(
                    vid,
                    "--mesh-mode",
                    "client",
                    "--connect",
                    f"tcp/127.0.0.1:{port}",
                    extra=("--gcs-lost-hold-s", "5", "--gcs-lost-land-s", "30"),
                )
            )
        assert presence.wait_for(lambda v, _g: v >= set(ids), timeout_s=60)
        ok(gcs, Command.takeoff(ALT_M, nonce=new_nonce(), stamp_ns=0), expect=ids)
        os.kill(router.pid, signal.SIGKILL)
        router.wait(5)
        time.sleep(1.0)
        count = watch.count
        time.sleep(0.5)
        assert watch.count == count, "states still flow without the router?"
        t0 = time.monotonic()
        router = procs.start(*router_args(f"tcp/127.0.0.1:{port}"))
        router.wait_for("READY")
        watch.forget()
        back_s = watch.wait(lambda s: set(s) >= set(ids), 20, "states after the router restart")
        assert presence.wait_for(lambda v, _g: v >= set(ids), timeout_s=10)
        result = gcs.send_command(
            Command(CommandKind.HOLD, new_nonce(), 0), expect=ids, timeout_s=5
        )
        assert set(result.outcomes) == set(ids) and all(
            o.ack is not None for o in result.outcomes.values()
        ), result.summary()
        print(
            f"router restarted: states back after {back_s:.2f} s ({time.monotonic() - t0:.2f} s incl. start), commands acked"
        )
