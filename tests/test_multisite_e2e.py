"""A keyed fleet split across three `covey router` processes on loopback, end to end.

    R1 <-> R2 <-> R3          a chain: R3's traffic to R1 must cross R2 (two router hops)
    |      |      |
    station agent 2  agent 3   every member is a client of its site's router
           agent 4 (far)

Agents 2 (on R2) and 3 (on R3) start 10 m apart in adjacent grid cells: neighbours on different
routers. Agent 4 (on R2) is 300 m away: no neighbour of theirs. The station is this process, a
keyed client of R1 (a FleetModel fed by a Mesh, as the browser station wires it). Checked:
- the station sees every vehicle's presence and state (through one and two router hops), and
  the agents see the station's (no ground-station-lost failsafe);
- a take-off to all gets every ack back, a goto to each vehicle its own ack;
- each of 2 and 3 flies with the other in its guidance (their guidance traces list each other,
  with fresh states), and neither hears 4 (scoped cell subscriptions through routers);
- killing agent 3 is presence loss at the station, and agent 2 flags its neighbour stale;
- a land to all gets the acks of the vehicles that are left.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from comms import keys
from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.schema import (
    Command,
    CommandKind,
    DecodeError,
    GuidanceTrace,
    Mode,
    Role,
    StateFlag,
    VehicleState,
)
from comms.session import MeshConfig, free_tcp_port
from groundstation.fleet import FleetModel
from tests.conftest import keyed_agent_argv, views_by_id
from trust.auth import load_auth
from trust.authority import throwaway_fleet
from trust.heartbeat import HeartbeatPublisher

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

FLEET = "sites"
ALT_M = 5.0
STARTS = {2: (0.0, -5.0), 3: (0.0, 5.0), 4: (300.0, 300.0)}
"""Start north, east in metres: 2 in cell (0, -1), 3 in cell (0, 0), 10 m apart; 4 far away."""
SITE_OF = {2: 1, 3: 2, 4: 1}
"""Which router (0-based: R1, R2, R3) each agent is a client of."""
IDS = tuple(STARTS)


class Station:
    """Station 1 on R1: presence and states in a FleetModel, guidance traces and the flags of
    every state as they come."""

    def __init__(self, mesh: Mesh) -> None:
        self.mesh = mesh
        self.fleet = FleetModel()
        self.lock = threading.Lock()
        self.neighbours: dict[int, dict[int, float]] = {}
        """vehicle id -> {neighbour id: age in s} of its latest guidance trace."""
        self.flags_since: dict[int, StateFlag] = {}
        """vehicle id -> the state flags seen since `mark()`."""
        mesh.subscribe_states(self.fleet.on_state, on_refused=self.fleet.on_state_refused)
        mesh.subscribe_states(self.on_state)
        for vid in IDS:
            mesh.session.declare_subscriber(keys.trace(FLEET, vid), self.on_trace)
        self.presence = mesh.presence(
            lambda kind, vid, alive: (
                kind == "vehicle" and self.fleet.on_presence(vid, alive, time.time_ns())
            )
        )
        mesh.declare_gcs(1)
        HeartbeatPublisher(mesh, 1)  # what the vehicles' station-lost failsafe trusts

    def on_state(self, s: VehicleState, _t: int) -> None:
        with self.lock:
            self.flags_since[s.vehicle_id] = self.flags_since.get(s.vehicle_id, 0) | s.flags

    def on_trace(self, sample) -> None:
        try:
            trace = GuidanceTrace.decode(sample.payload.to_bytes())
        except DecodeError:
            return
        with self.lock:
            self.neighbours[trace.vehicle_id] = {vid: age for vid, _, age in trace.neighbours}

    def mark(self) -> None:
        with self.lock:
            self.flags_since.clear()

    def views(self):
        return views_by_id(self.fleet.snapshot(time.time_ns(), trails=False))

    def wait(self, pred, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                ok = _holds(pred, self)
            if ok:
                return
            time.sleep(0.05)
        with self.lock:
            raise AssertionError(
                f"timed out waiting for {what}: neighbours {self.neighbours}, views {self.views()}"
            )

    def send(self, cmd: Command, expect) -> None:
        result = self.mesh.send_command(cmd, expect=expect, timeout_s=5)
        assert result.ok, result.summary()
        assert set(result.outcomes) == set(expect), result.summary()


def _holds(pred, station: Station) -> bool:
    try:
        return bool(pred(station))
    except KeyError:  # present but not heard from yet
        return False


def test_a_fleet_across_three_routers(procs, tmp_path) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=list(IDS), stations=[1])
    ports = [free_tcp_port() for _ in range(3)]
    ep = [f"tcp/127.0.0.1:{p}" for p in ports]
    # The chain, started all at once: R2 and R3 keep trying until their neighbour listens.
    links = {0: [], 1: [ep[0]], 2: [ep[1]]}
    routers = [
        procs.start(
            "-m",
            "covey_cli",
            "router",
            "--listen",
            ep[i],
            *[a for e in links[i] for a in ("--connect", e)],
            "--count-period-s",
            "0.5",
        )
        for i in range(3)
    ]
    for i, router in enumerate(routers):
        assert router.wait_for("READY").split()[-1] == ep[i]
    routers[1].wait_for("covey router: 2 router(s)", 20)  # R2 linked to R1 and R3
    station_cfg = MeshConfig(fleet=FLEET, mode="client", connect=(ep[0],))
    with Mesh(station_cfg, auth=load_auth(str(authority.member_path(Role.STATION, 1)))) as mesh:
        st = Station(mesh)
        t0 = time.monotonic()
        agents = {
            vid: procs.start(
                *keyed_agent_argv(authority, vid),
                "--fleet",
                FLEET,
                "--mesh-mode",
                "client",
                "--connect",
                ep[SITE_OF[vid]],
                f"--start-ne-m={n:g},{e:g}",
                "--cruise-speed-m-s",
                "2",
                "--trace-guidance",
            )
            for vid, (n, e) in STARTS.items()
        }
        assert st.presence.wait_for(lambda v, _g: v >= set(IDS), timeout_s=60), (
            f"presence: {st.presence.vehicles}"
        )
        st.wait(lambda s: all(s.views()[v].state is not None for v in IDS), 30, "first states")
        up_s = time.monotonic() - t0

        st.send(Command.takeoff(ALT_M, nonce=new_nonce(), stamp_ns=0), expect=IDS)
        st.wait(lambda s: all(s.views()[v].mode is Mode.HOLDING for v in IDS), 30, "all holding")
        st.mark()  # from here on no vehicle may miss the station (its token crosses the routers)

        # Neighbours on different routers hear each other, fresh; the far vehicle is heard by
        # the station only. Both traces listed the other at a sub-second age at least once.
        st.wait(
            lambda s: s.neighbours[2].get(3, 9.0) < 1.0 and s.neighbours[3].get(2, 9.0) < 1.0,
            20,
            "2 and 3 in each other's guidance",
        )
        st.wait(lambda s: 4 in s.neighbours, 10, "a trace of vehicle 4")
        with st.lock:
            assert 4 not in st.neighbours[2] and 4 not in st.neighbours[3], st.neighbours
            assert st.neighbours[4] == {}, st.neighbours
        assert mesh.stats.states_refused == 0

        # A goto to each vehicle, by its own key, through one and two router hops.
        for vid in (2, 3):
            n, e = STARTS[vid]
            st.send(
                Command.goto_local(n + 3, e, -ALT_M, nonce=new_nonce(), stamp_ns=0, targets=(vid,)),
                expect=(vid,),
            )
        st.wait(
            lambda s: all(s.views()[v].state.pos_ned_m[0] > 2.0 for v in (2, 3)), 20, "the gotos"
        )

        with st.lock:
            missed = [v for v, f in st.flags_since.items() if f & StateFlag.FAILSAFE_GCS_LOST]
        assert not missed, f"vehicles {missed} lost the station"

        # Vehicle 3 dies: the station sees it go, and vehicle 2 flags its neighbour stale.
        st.mark()
        os.kill(agents[3].pid, signal.SIGKILL)
        assert st.presence.wait_for(lambda v, _g: 3 not in v, timeout_s=10), "3 still present"
        st.wait(lambda s: s.flags_since[2] & StateFlag.NEIGHBOURS_STALE, 10, "2 flags 3 stale")
        assert not st.views()[3].alive

        result = mesh.send_command(Command(CommandKind.LAND, new_nonce(), 0), expect=IDS)
        assert {v for v, o in result.outcomes.items() if o.status is OutcomeStatus.ACCEPTED} == {
            2,
            4,
        }, result.summary()
        assert result.outcomes[3].status is OutcomeStatus.TIMEOUT
        print(
            f"fleet up across 3 routers in {up_s:.1f} s; whole test {time.monotonic() - t0:.1f} s"
        )
