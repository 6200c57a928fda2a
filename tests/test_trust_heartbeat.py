"""Failsafes from signed facts (issue 34, findings 4 and 6; issue 39, finding 12).

- the StationHeartbeat message: round trip, a decoder that says why, a fuzz pass in which no
  mutated heartbeat verifies;
- the receiver (trust/heartbeat.py) with real keys: unsigned, replayed, out-of-order, forged and
  vehicle-signed heartbeats refused; freshness; the clock offset; the take-off refusals;
- end to end on real keyed agent processes: a take-off from `covey cmd` with no station is
  refused with the reason; with a station it flies; with the station gone and a keyless process
  holding a fake station token, the agents hold within gcs_lost_hold_s;
- a vehicle whose clock is 10 s off refuses take-off saying so, and the station shows its clock.
"""

from __future__ import annotations

import dataclasses
import random
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from comms import keys
from comms.schema import (
    MAX_VEHICLE_ID,
    ClockReport,
    DecodeError,
    Event,
    EventKind,
    Role,
    StationHeartbeat,
    decode,
)
from tests.conftest import REPO, views_by_id, wait_until
from tests.test_fuzz_decoders import mutate
from trust.auth import FleetAuth, FleetKeyError, load_auth
from trust.authority import throwaway_fleet
from trust.heartbeat import NO_STATION, HeartbeatConfig, HeartbeatPublisher, StationHeartbeats

FLEET = "covey"
NOW_NS = 1_800_000_000 * 10**9


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("hb") / "keys"
    return throwaway_fleet(d, FLEET, vehicles=[1, 2, 3], stations=[1, 2])


def member(fleet, role: Role, mid: int, clock_ns=lambda: NOW_NS) -> FleetAuth:
    return load_auth(str(fleet.member_path(role, mid)), clock_ns=clock_ns)


# -- the message -----------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(
    st.builds(
        StationHeartbeat,
        gcs_id=st.integers(1, MAX_VEHICLE_ID),
        seq=st.integers(0, 2**32 - 1),
        stamp_ns=st.integers(0, 2**64 - 1),
        sig=st.sampled_from([b""]) | st.binary(min_size=64, max_size=64),
    )
)
def test_a_heartbeat_round_trips(hb) -> None:
    data = hb.encode()
    assert data[0] == 8 and len(data) in (16, 80)
    assert decode(data) == hb and StationHeartbeat.decode(data).encode() == data


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (StationHeartbeat(1, 2, 3).encode()[:-1], "must be 16 bytes"),
        (StationHeartbeat(1, 2, 3).encode() + bytes(10), "must be 16 bytes"),
        (b"\x08\x01" + bytes(14), "gcs_id=0"),
        (b"\x08\x02" + bytes(14), "unsupported STATION_HEARTBEAT version 2"),
    ],
)
def test_the_heartbeat_decoder_says_why(data, why) -> None:
    with pytest.raises(DecodeError, match=why):
        decode(data)


def test_no_mutated_heartbeat_decodes_wrongly_or_verifies(fleet) -> None:
    station, vehicle = member(fleet, Role.STATION, 1), member(fleet, Role.VEHICLE, 1)
    signed = station.sign_heartbeat(StationHeartbeat(1, 7, NOW_NS)).encode()
    assert vehicle.check_heartbeat(StationHeartbeat.decode(signed)) is None  # control
    rng, decoded = random.Random(34), 0
    for _ in range(3000):
        data = mutate(signed, rng)
        try:
            msg = decode(data)
        except DecodeError as exc:
            assert str(exc)
            continue
        assert msg.encode() == data
        if isinstance(msg, StationHeartbeat) and data != signed:
            decoded += 1
            assert vehicle.check_heartbeat(msg) is not None, data.hex()
    assert decoded > 100


def test_a_clock_report_travels_in_an_event() -> None:
    report = ClockReport(3, 10.04, 1)
    event = report.to_event(NOW_NS)
    assert event.kind is EventKind.CLOCK and event.text == "clock +10.0 s against station 1"
    assert ClockReport.from_event(Event.decode(event.encode())) == dataclasses.replace(
        report, offset_s=10.0
    )
    back = ClockReport.from_event(ClockReport(3, -0.2, 2, ok=True).to_event(1))
    assert back.ok and back.offset_s == -0.2 and back.gcs_id == 2
    for text in ("clock x s against station 1", "clock +1 s against station 0", "clock +1 s"):
        with pytest.raises(DecodeError):
            ClockReport.from_event(Event(3, 1, text, kind=EventKind.CLOCK))
    with pytest.raises(DecodeError, match="CLOCK event"):
        ClockReport.from_event(Event(3, 1, "clock +1.0 s against station 1"))


def test_only_a_station_signs_its_own_heartbeats(fleet) -> None:
    with pytest.raises(FleetKeyError, match="only a station key"):
        member(fleet, Role.VEHICLE, 1).sign_heartbeat(StationHeartbeat(1, 1, NOW_NS))
    with pytest.raises(FleetKeyError, match="only station 1's"):
        member(fleet, Role.STATION, 1).sign_heartbeat(StationHeartbeat(2, 1, NOW_NS))


# -- the receiver ----------------------------------------------------------------------------
class Clocks:
    def __init__(self, offset_s: float = 0.0) -> None:
        self.wall_ns, self.mono_s, self.offset_s = NOW_NS, 100.0, offset_s

    def local_ns(self) -> int:
        return self.wall_ns + int(self.offset_s * 1e9)

    def advance(self, dt_s: float) -> None:
        self.wall_ns += int(dt_s * 1e9)
        self.mono_s += dt_s


def receiver(auth, clocks: Clocks, **cfg) -> StationHeartbeats:
    mesh = SimpleNamespace(auth=auth, fleet=FLEET, clock_ns=clocks.local_ns)
    return StationHeartbeats(
        mesh, HeartbeatConfig(**cfg), clock_s=lambda: clocks.mono_s, subscribe=False
    )


def offer(rx: StationHeartbeats, hb: StationHeartbeat, clocks: Clocks) -> str | None:
    return rx.receive(keys.gcs_heartbeat(FLEET, hb.gcs_id), hb.encode())


def test_keyed_members_trust_only_fresh_heartbeats_signed_by_a_roster_station(fleet) -> None:
    clocks = Clocks()
    rx = receiver(member(fleet, Role.VEHICLE, 1, clocks.local_ns), clocks)
    s1, s2 = member(fleet, Role.STATION, 1), member(fleet, Role.STATION, 2)
    beat = lambda auth, sid, seq, dt_s=0.0: auth.sign_heartbeat(  # noqa: E731
        StationHeartbeat(sid, seq, clocks.wall_ns + int(dt_s * 1e9))
    )
    assert not rx.alive(clocks.mono_s)
    assert rx.takeoff_problem(clocks.mono_s, require_gcs=True) == NO_STATION
    assert rx.takeoff_problem(clocks.mono_s, require_gcs=False) is None
    assert offer(rx, StationHeartbeat(1, 1, clocks.wall_ns), clocks) == "unsigned"
    vehicle_signed = dataclasses.replace(StationHeartbeat(1, 1, clocks.wall_ns), sig=bytes(64))
    assert offer(rx, vehicle_signed, clocks) == "forged"
    first = beat(s1, 1, 1)
    assert offer(rx, dataclasses.replace(first, seq=2), clocks) == "forged"  # tampered
    as_station_1 = dataclasses.replace(beat(s2, 2, 1), gcs_id=1)  # station 2's key, relabelled
    assert offer(rx, as_station_1, clocks) == "forged"
    assert rx.receive(keys.gcs_heartbeat(FLEET, 2), first.encode()) == "misaddressed"
    assert rx.stations(clocks.mono_s) == set() and rx.accepted == 0
    assert offer(rx, first, clocks) is None
    assert rx.stations(clocks.mono_s) == {1} and rx.alive(clocks.mono_s)
    assert rx.takeoff_problem(clocks.mono_s, require_gcs=True) is None
    assert offer(rx, first, clocks) == "replayed"
    assert offer(rx, beat(s1, 1, 9, -1.0), clocks) == "out of order"
    clocks.advance(HeartbeatConfig().alive_s)
    assert not rx.alive(clocks.mono_s), "no heartbeat for alive_s: no station"
    # A recording of station 1's heartbeats, replayed when fresh ones stop: old, refused.
    assert offer(rx, first, clocks) == "replayed"
    assert not rx.alive(clocks.mono_s)
    assert rx.refused == {
        "unsigned": 1,
        "forged": 3,
        "misaddressed": 1,
        "replayed": 2,
        "out of order": 1,
    }


def test_a_heartbeat_outside_the_freshness_window_keeps_no_station_but_gives_the_offset(
    fleet,
) -> None:
    clocks = Clocks(offset_s=10.0)  # this vehicle's clock is 10 s ahead of the station's
    rx = receiver(member(fleet, Role.VEHICLE, 1, clocks.local_ns), clocks)
    s1 = member(fleet, Role.STATION, 1)
    for seq in range(1, 12):
        clocks.advance(0.5)
        assert (
            offer(rx, s1.sign_heartbeat(StationHeartbeat(1, seq, clocks.wall_ns)), clocks) is None
        )
    assert not rx.alive(clocks.mono_s), "a 10 s old stamp is not fresh"
    off = rx.offset(clocks.mono_s)
    assert off.gcs_id == 1 and off.offset_s == pytest.approx(10.0) and off.samples == 9
    why = rx.takeoff_problem(clocks.mono_s, require_gcs=False)
    assert why == rx.clock_problem() and len(why.encode()) <= 96
    assert why.startswith("vehicle clock +10.0 s against station 1 (limit 5 s)"), why
    # Reports: at once, then every report_period_s, then once "ok" when the clock is set.
    (report, stamp_ns), *_ = rx.clock_reports(clocks.mono_s, (1,))
    assert report == ClockReport(1, pytest.approx(10.0), 1) and stamp_ns == clocks.wall_ns
    assert rx.clock_reports(clocks.mono_s + 1.0, (1,)) == []
    assert len(rx.clock_reports(clocks.mono_s + 5.0, (1, 2))) == 2
    clocks.offset_s = 0.0
    for seq in range(12, 24):
        clocks.advance(0.5)
        offer(rx, s1.sign_heartbeat(StationHeartbeat(1, seq, clocks.wall_ns)), clocks)
    assert rx.alive(clocks.mono_s) and rx.clock_problem() is None
    ((ok, _),) = rx.clock_reports(clocks.mono_s, (1,))
    assert ok.ok and abs(ok.offset_s) < 0.01
    assert rx.clock_reports(clocks.mono_s + 10.0, (1,)) == []


def test_open_mode_accepts_unsigned_heartbeats_from_a_bounded_set_of_stations() -> None:
    clocks = Clocks()
    rx = receiver(None, clocks, max_stations=3)
    for sid in range(1, 6):
        offer(rx, StationHeartbeat(sid, 1, clocks.wall_ns), clocks)
    assert rx.stations(clocks.mono_s) == {1, 2, 3} and rx.refused == {"too many stations": 2}
    assert rx.alive(clocks.mono_s) and rx.tokens is None


def test_a_station_beats_signed_and_a_member_that_joins_asks_at_once(fleet) -> None:
    """Real Zenoh sessions: a member that starts after the station knows it from the answer to
    its query (the station's period here is an hour), then from each beat."""
    from comms.mesh import Mesh
    from comms.session import embedded_peer, embedded_router, free_tcp_port

    port = free_tcp_port()
    slow = HeartbeatConfig(period_s=3600.0, alive_s=3600.0)
    with (
        Mesh(
            embedded_router(port, fleet=FLEET), auth=member(fleet, Role.STATION, 2, time.time_ns)
        ) as gcs,
        HeartbeatPublisher(gcs, 2, slow) as pub,
    ):
        with pytest.raises(ValueError, match="need station 1's key"):
            HeartbeatPublisher(gcs, 1)
        time.sleep(0.2)  # the thread's first beat is out: nobody heard it
        vehicle = member(fleet, Role.VEHICLE, 1, time.time_ns)
        with Mesh(embedded_peer(port, fleet=FLEET), auth=vehicle) as mesh:
            rx = StationHeartbeats(mesh, slow)
            assert wait_until(lambda: rx.stations(time.monotonic()) == {2}, 10), rx.refused
            assert rx.accepted == 1 and rx.tokens is None
            hb = pub.beat()
            assert wait_until(lambda: rx.accepted == 2, 10)
            assert vehicle.check_heartbeat(hb) is None and hb.seq == pub.seq
            off = rx.offset(time.monotonic())
            assert off.gcs_id == 2 and abs(off.offset_s) < 1.0
            rx.close()


# -- real processes --------------------------------------------------------------------------
def run_cmd(authority, port: int, *argv: str) -> subprocess.CompletedProcess:
    key = str(authority.member_path(Role.STATION, 2))
    return subprocess.run(
        [sys.executable, "-m", "covey_cli", "cmd", *argv, "--fleet", FLEET, "--key-file", key]
        + ["--connect", f"tcp/127.0.0.1:{port}", "--timeout-s", "5"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=90,
    )


@pytest.mark.e2e
@pytest.mark.slow
def test_cli_only_take_off_is_refused_and_a_fake_station_token_cannot_stop_the_failsafe(
    fleet, procs
) -> None:
    """Keyed agents with the station failsafe on (hold after 1.5 s). No station: `covey cmd
    takeoff` is refused with the reason. Station 1 up (heartbeats): the take-off flies. Then a
    keyless process declares a station token and station 1 goes: the agents hold anyway."""
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.schema import Command
    from comms.session import embedded_peer, embedded_router, free_tcp_port
    from groundstation.fleet import FleetConfig, FleetModel

    hold_s = 1.5
    port = free_tcp_port()
    with Mesh(
        embedded_router(port, fleet=FLEET), auth=member(fleet, Role.STATION, 2, time.time_ns)
    ) as hub:
        model = FleetModel(FleetConfig(verified_only=True))
        events: list[tuple[float, Event]] = []
        hub.subscribe_states(model.on_state, on_refused=model.on_state_refused)
        hub.subscribe_events(lambda e, _t: events.append((time.monotonic(), e)))
        hub.presence(
            lambda kind, vid, alive: kind == "vehicle" and model.on_presence(vid, alive, 0)
        )
        for vid, east_m in ((1, 0.0), (2, 12.0)):
            procs.start(
                "-m",
                "covey_cli",
                "agent",
                "--id",
                str(vid),
                "--key-file",
                str(fleet.member_path(Role.VEHICLE, vid)),
                "--fleet",
                FLEET,
                "--connect",
                f"tcp/127.0.0.1:{port}",
                f"--start-ne-m=0,{east_m:g}",
                "--gcs-lost-hold-s",
                str(hold_s),
                "--gcs-lost-land-s",
                "60",
            )
        views = lambda: views_by_id(model.snapshot(time.time_ns(), trails=False))  # noqa: E731
        assert wait_until(lambda: {1, 2} <= views().keys(), 90), "agents did not come up"

        refused = run_cmd(fleet, port, "takeoff", "3", "--to", "all")
        assert refused.returncode == 1, refused.stdout + refused.stderr
        for vid in (1, 2):
            assert f"vehicle     {vid}: rejected {NO_STATION}" in refused.stdout, refused.stdout

        station = Mesh(
            embedded_peer(port, fleet=FLEET), auth=member(fleet, Role.STATION, 1, time.time_ns)
        )
        station.declare_gcs(1)
        beats = HeartbeatPublisher(station, 1)
        time.sleep(1.0)  # a few heartbeats reach the agents
        ok = run_cmd(fleet, port, "takeoff", "3", "--to", "all")
        assert ok.returncode == 0, ok.stdout + ok.stderr
        assert wait_until(lambda: all(views()[v].alt_m > 2.5 for v in (1, 2)), 60), views()
        going = hub.send_command(
            Command.goto_local(40.0, 0.0, -3.0, nonce=new_nonce(), stamp_ns=0, targets=(1,)),
            timeout_s=5,
        )
        assert going.ok, going.summary()
        assert wait_until(lambda: views()[1].mode.name == "GOTO", 10)

        with Mesh(embedded_peer(port, fleet=FLEET)) as keyless:  # no key: an outsider
            keyless.declare_gcs(7)
            time.sleep(0.5)
            beats.close()
            station.close()
            gone = time.monotonic()
            assert wait_until(lambda: views()[1].mode.name == "HOLDING", hold_s + 10), views()
            held_after_s = time.monotonic() - gone

            def holding_events() -> list[float]:
                return [
                    t - gone
                    for t, e in events
                    if e.vehicle_id == 1 and e.kind is EventKind.FAILSAFE and "holding" in e.text
                ]

            # the event and the state that shows the hold travel apart: either may come first
            wait_until(lambda: bool(holding_events()), 5)
            holding = holding_events()
            print(
                f"vehicle 1 held {held_after_s:.2f} s after the station went (event at {holding})"
            )
            assert holding and holding[0] <= hold_s + HeartbeatConfig().alive_s + 1.0, holding
            assert views()[1].state.flags & 2  # FAILSAFE_GCS_LOST


@pytest.mark.e2e
@pytest.mark.slow
def test_a_vehicle_whose_clock_is_10_s_off_refuses_take_off_and_the_station_shows_it(
    fleet,
) -> None:
    """Two in-process agents on real Zenoh sessions, vehicle 3's clock (its mesh and its key's)
    10 s ahead; a real keyed GroundStation (station 1) on the same router."""
    from agent.backends.sim import SimBackend, SimConfig
    from agent.hosts import Agent
    from agent.shell_config import AgentConfig
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.schema import Command
    from comms.session import MeshConfig, embedded_router, free_tcp_port
    from groundstation.station import GcsConfig, GroundStation
    from groundstation.tables import fleet_table

    port = free_tcp_port()
    peer = MeshConfig(fleet=FLEET, mode="peer", connect=(f"tcp/127.0.0.1:{port}",))
    stop = threading.Event()
    threads = []
    with (
        Mesh(embedded_router(port, fleet=FLEET)) as _router,
        GroundStation(
            GcsConfig(mesh=peer, port=0, key_file=str(fleet.member_path(Role.STATION, 1)))
        ) as gcs,
    ):
        meshes, agents = [], []
        try:
            for vid, offset_s in ((2, 0.0), (3, 10.0)):
                clock_ns = lambda o=offset_s: time.time_ns() + int(o * 1e9)  # noqa: E731
                auth = member(fleet, Role.VEHICLE, vid, clock_ns)
                mesh = Mesh(peer, clock_ns=clock_ns, auth=auth)
                meshes.append(mesh)
                backend = SimBackend(
                    SimConfig(start_ned_m=(0.0, 8.0 * vid, 0.0)), now_s=time.monotonic()
                )
                agent = Agent(AgentConfig(vehicle_id=vid, open_mode=False), backend, mesh)
                agents.append(agent)
                threads.append(threading.Thread(target=agent.run, args=(stop,), daemon=True))
                threads[-1].start()
            snap = lambda: views_by_id(gcs.fleet.snapshot(time.time_ns(), trails=False))  # noqa: E731
            assert wait_until(
                lambda: 2 in snap() and 3 in snap() and snap()[3].clock_offset_s is not None, 30
            ), snap()
            assert snap()[3].clock_offset_s == pytest.approx(10.0, abs=0.5)
            assert snap()[2].clock_offset_s is None
            # the table shows the offset with the vehicle's row, which needs a state of it too
            # (an idle vehicle sends one a second): wait for it as for the offset
            table = lambda: fleet_table(gcs.fleet.snapshot(time.time_ns()))  # noqa: E731
            assert wait_until(lambda: "CLOCK +10.0 s" in table(), 10), table()
            assert table().count("data-clock") == 1
            res = gcs.mesh.send_command(
                Command.takeoff(3.0, nonce=new_nonce(), stamp_ns=0, targets=(2, 3)),
                expect=(2, 3),
                timeout_s=5,
            )
            assert res.outcomes[2].status.value == "accepted", res.summary()
            why = res.outcomes[3].reason
            assert res.outcomes[3].status.value == "rejected", res.summary()
            assert why.startswith("stale command: vehicle clock +10.0 s against station 1"), why
            clock_events = [e for _, e in gcs.events.latest(EventKind.CLOCK)]
            assert clock_events and all(e.vehicle_id == 3 for e in clock_events)
            assert clock_events[-1].text == "clock +10.0 s against station 1"
        finally:
            stop.set()
            for t in threads:
                t.join(5)
            for agent in agents:
                agent.close()
            for mesh in meshes:
                mesh.close()
