"""Record a real 3-agent flight (separate processes on loopback), then inspect and replay it.

One flight serves every test in this module: three `covey agent` processes take off and cross
over, while two recorder processes record the fleet; one is stopped with SIGTERM, the other is
killed with SIGKILL.
"""

from __future__ import annotations

import io
import os
import signal
import sys
import threading
import time
import uuid

import pytest

from comms import keys
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, StateFlag, VehicleState
from comms.session import embedded_peer, embedded_router, free_tcp_port
from kit.procs import ChildGroup
from recording.record import read_recording, summarise
from recording.replay import LiveFleetError, ReplayConfig, replay
from tools.record_cli import info_main, record_cli
from tools.replay_cli import replay_cli

pytestmark = pytest.mark.e2e

VEHICLES = (1, 2, 3)
STARTS = {1: (0.0, 0.0), 2: (0.0, 8.0), 3: (8.0, 4.0)}
GOALS = {1: (8.0, 8.0, -3.0), 2: (8.0, 0.0, -3.0), 3: (0.0, 4.0, -3.0)}
RECORD = "import sys; from tools.record_cli import record_cli; sys.exit(record_cli(sys.argv[1:]))"


def _command_all(mesh: Mesh, make, deadline_s: float = 10.0) -> None:
    """Send a command to each vehicle until every one has accepted it (agents start racing)."""
    pending = set(VEHICLES)
    end = time.monotonic() + deadline_s
    while pending and time.monotonic() < end:
        for vid in sorted(pending):
            res = mesh.send_command(make(vid), timeout_s=1.0)
            if res.ok:
                pending.discard(vid)
        if pending:
            time.sleep(0.2)
    assert not pending, f"vehicles {pending} did not accept"


PROBE_ID = 99


def _has_command(path) -> bool:
    """Reading a recording that is still being written works (the reader stops at its tail)."""
    return path.exists() and any(m.topic.endswith("/cmd") for m in read_recording(path).messages)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("flight")
    fleet = "rec" + uuid.uuid4().hex[:8]
    port = free_tcp_port()
    clean, killed = tmp / "clean.mcap", tmp / "killed.mcap"
    children = ChildGroup(
        prefix=[sys.executable],
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        output="discard",
        stderr="discard",
        grace_s=10.0,
    )
    with Mesh(embedded_router(port, fleet=fleet)) as mesh, children:
        connect = f"tcp/127.0.0.1:{port}"
        recorders = [
            children.start("-c", RECORD, "-o", str(out), "--fleet", fleet, "--connect", connect)
            for out in (clean, killed)
        ]
        # Both recorders must be on the mesh before the agents start. Probe with commands
        # to a vehicle that does not exist until both (still open) files hold one.
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            probe = Command(CommandKind.HOLD, new_nonce(), time.time_ns(), targets=(PROBE_ID,))
            mesh.send_command(probe, timeout_s=0.2)
            time.sleep(0.3)
            if all(_has_command(p) for p in (clean, killed)):
                break
        assert all(_has_command(p) for p in (clean, killed)), "recorders did not come up"
        for vid in VEHICLES:
            n, e = STARTS[vid]
            children.start(
                "-m",
                "covey_cli",
                "agent",
                "--id",
                str(vid),
                "--fleet",
                fleet,
                "--connect",
                connect,
                f"--start-ne-m={n},{e}",
                "--no-gcs-failsafe",
                "--trace-guidance",
            )
        assert mesh.presence().wait_for(lambda v, _g: set(VEHICLES) <= v, 20.0)
        stamp = time.time_ns
        _command_all(
            mesh,
            lambda v: Command.takeoff(3.0, nonce=new_nonce(), stamp_ns=stamp(), targets=(v,)),
        )
        time.sleep(3.5)
        _command_all(
            mesh,
            lambda v: Command.goto_local(
                *GOALS[v], nonce=new_nonce(), stamp_ns=stamp(), targets=(v,)
            ),
        )
        time.sleep(5.0)
        recorders[1].send_signal(signal.SIGKILL)
        recorders[0].send_signal(signal.SIGTERM)
        assert recorders[0].wait(20) == 0
        recorders[1].wait(5)
        yield {"fleet": fleet, "port": port, "clean": clean, "killed": killed, "mesh": mesh}


def test_info_summarises_the_flight(flight):
    out = io.StringIO()
    assert info_main(str(flight["clean"]), out=out) == 0
    text = out.getvalue()
    assert f"fleet       {flight['fleet']}" in text and "vehicles    1, 2, 3" in text
    info = summarise(read_recording(flight["clean"]))
    assert info["complete"] and info["vehicles"] == [1, 2, 3]
    assert info["counts"]["commands"] >= 6  # 3 takeoffs + 3 gotos, as queries
    assert info["counts"]["presence"] >= 3 and info["counts"]["events"] >= 3
    seqs: dict[int, list[int]] = {}
    for m in read_recording(flight["clean"]).messages:
        if m.topic.endswith("/state"):
            s = VehicleState.decode(m.data)
            seqs.setdefault(s.vehicle_id, []).append(s.seq)
    for vid in VEHICLES:
        assert info["state_rate_hz_by_vehicle"][vid] > 0
        # Each state the recorder heard is there once, and nearly every one published while it
        # recorded: states go out with congestion control DROP (a state is worth less than the
        # next), so a loaded machine may drop a few on the way; the recorder loses none it got.
        got = seqs[vid]
        assert len(got) == len(set(got)), "a state recorded twice"
        span = max(got) - min(got) + 1
        assert len(got) >= 0.97 * span, f"vehicle {vid}: {span - len(got)} of {span} states missing"
    assert record_cli(["--info", str(flight["clean"]), "--json"]) == 0


def test_kill_9_leaves_a_readable_file(flight):
    rec = read_recording(flight["killed"])
    clean = read_recording(flight["clean"])
    states = [m for m in rec.messages if m.topic.endswith("/state")]
    assert {VehicleState.decode(m.data).vehicle_id for m in states} == set(VEHICLES)
    assert len(states) >= 0.8 * sum(m.topic.endswith("/state") for m in clean.messages)
    info = summarise(rec)  # no summary section or footer was ever written
    assert info["vehicles"] == [1, 2, 3] and info["messages"] == len(rec.messages)
    assert not info["complete"] and rec.truncated


def _replay_and_watch(flight, target: str, **kw):
    """Replay the clean recording into `target`; return (result, fleet model track, queries)."""
    from groundstation.fleet import FleetModel

    model, track, queries = FleetModel(), {}, []
    lock = threading.Lock()

    def on_state(state: VehicleState, recv_ns: int) -> None:
        model.on_state(state, recv_ns)
        with lock:
            track[(state.vehicle_id, state.stamp_ns)] = (
                model.positions()[state.vehicle_id],
                state.flags,
            )

    with Mesh(embedded_peer(flight["port"], fleet=target)) as watcher:
        watcher.subscribe_states(on_state)
        for vid in VEHICLES:  # vehicles of the target fleet: nothing may query them
            watcher.serve_commands(vid, lambda c: queries.append(c))
        watcher.session.declare_queryable(
            keys.everything(target), lambda q: queries.append(q), complete=False
        )
        time.sleep(0.5)
        cfg = ReplayConfig(
            str(flight["clean"]), embedded_peer(flight["port"], fleet=target), speed=4.0, **kw
        )
        result = replay(cfg)
        time.sleep(0.5)
        with lock:
            return result, dict(track), list(queries)


def test_replay_reproduces_the_tracks_and_sends_no_commands(flight):
    target = flight["fleet"] + "r"
    result, track, queries = _replay_and_watch(flight, target)
    assert queries == []
    assert result.commands_skipped >= 6
    recorded = {}
    for m in read_recording(flight["clean"]).messages:
        if m.topic.endswith("/state"):
            s = VehicleState.decode(m.data)
            recorded[(s.vehicle_id, s.stamp_ns)] = s.pos_ned_m
    assert result.states == len(recorded)
    assert len(track) >= 0.95 * len(recorded)
    moved = 0
    for key, (pos, flags) in track.items():
        assert flags & StateFlag.REPLAY
        err_m = max(abs(a - b) for a, b in zip(pos, recorded[key], strict=True))
        assert err_m <= 0.01, f"vehicle {key[0]} at {key[1]}: {pos} vs {recorded[key]}"
        moved += abs(recorded[key][2]) > 1.0
    assert moved >= 30  # the tracks include the flight, not just the ground


def test_replay_refuses_a_live_fleet(flight, capsys):
    with pytest.raises(LiveFleetError, match=r"live vehicles \[1, 2, 3\]"):
        replay(
            ReplayConfig(str(flight["clean"]), embedded_peer(flight["port"], fleet=flight["fleet"]))
        )
    code = replay_cli([str(flight["clean"]), "--connect", f"tcp/127.0.0.1:{flight['port']}"])
    assert code == 1 and "Replay into another fleet" in capsys.readouterr().err


def test_closed_loop_on_the_real_flight(flight):
    from tools.closed_loop import ClosedLoopConfig, run_closed_loop

    rep = run_closed_loop(ClosedLoopConfig(str(flight["clean"]), vehicle_id=1))
    assert rep["ticks"] >= 10
    assert rep["exact"], "the agent published no usable guidance traces"
    assert rep["max_diff_m_s"] < 1e-4  # every tick it could compare, it reproduced exactly
    # A tick is skipped when the recording lacks its trace or a neighbour state the agent used:
    # both go out with congestion control DROP, and a loaded 2-core machine drops a few. One
    # lost message skips every tick up to the policy's next decision (its held decision cannot
    # be replayed), up to 10 ticks at the 1 s decision period: 6 of 67 once in CI, 17 of 56
    # another time (two losses). Most ticks must still be compared.
    assert rep["skipped_ticks"] <= 0.4 * rep["ticks"], rep
