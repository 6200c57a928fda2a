"""Recorder and reader: torn files, command recording beside live acks, replay pacing."""

from __future__ import annotations

import time
import uuid

import pytest

from comms import keys
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandAck, CommandKind, Event, StateFlag, VehicleState
from comms.session import embedded_peer, embedded_router, free_tcp_port
from recording.record import McapSink, RecordConfig, Recorder, read_recording, summarise
from recording.replay import ReplayConfig, play, prepare

PROBE_ID = 99


def _state(vid: int, seq: int, t_ns: int) -> VehicleState:
    return VehicleState(vid, seq, t_ns, (seq * 0.1, vid * 1.0, -3.0), (1.0, 0.0, 0.0), 0.0)


def _write(path, n: int = 300) -> list[bytes]:
    payloads = []
    with open(path, "wb") as f:
        sink = McapSink(f, "core", chunk_bytes=1024, flush_interval_s=0.01)
        for k in range(n):
            data = _state(1 + k % 3, k, 1_000_000_000 + k * 33_000_000).encode()
            payloads.append(data)
            sink.put(keys.state("core", 1 + k % 3), data, 1_000_000_000 + k * 33_000_000)
        sink.close()
    return payloads


def test_reader_survives_a_file_cut_anywhere(tmp_path):
    full = tmp_path / "full.mcap"
    payloads = _write(full)
    rec = read_recording(full)
    assert not rec.truncated and [m.data for m in rec.messages] == payloads and rec.fleet == "core"
    blob = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    last = -1
    for size in range(0, len(blob), max(1, len(blob) // 97)):
        cut.write_bytes(blob[:size])
        part = read_recording(cut)  # never raises
        got = [m.data for m in part.messages]
        assert got == payloads[: len(got)]  # a prefix, in order
        assert len(got) >= last
        last = len(got)
        assert summarise(part)["messages"] == len(got)
    assert last > 250  # most of the file is readable before the summary section


def test_replay_keeps_the_recorded_pace(tmp_path):
    path = tmp_path / "pace.mcap"
    _write(path, n=30)
    items = prepare(read_recording(path), start_s=0.099)
    assert items[0].offset_ns == 0 and len(items) == 27
    assert all(
        isinstance(p.message, VehicleState) and p.message.flags & StateFlag.REPLAY for p in items
    )

    class FakeMesh:
        def __init__(self):
            self.sent = []

        def publish_state(self, s):
            self.sent.append((now[0], s.seq))

    now = [100.0]
    mesh = FakeMesh()

    def sleep(dt):
        now[0] += dt

    result = play(mesh, items, speed=2.0, clock_s=lambda: now[0], sleep=sleep)
    assert result.states == 27
    times = [t - 100.0 for t, _ in mesh.sent]
    assert times == pytest.approx([k * 0.033 / 2 for k in range(27)], abs=0.002)


def test_bad_replay_settings_say_why():
    with pytest.raises(ValueError, match="speed"):
        ReplayConfig("x.mcap", speed=0.0)
    with pytest.raises(ValueError, match="end_s"):
        ReplayConfig("x.mcap", start_s=5.0, end_s=2.0)


def test_recording_commands_does_not_disturb_acks(tmp_path):
    fleet = "c" + uuid.uuid4().hex[:8]
    port = free_tcp_port()
    seen: list[int] = []

    def handler(cmd: Command) -> CommandAck:
        seen.append(cmd.nonce)
        return CommandAck(7, cmd.nonce, time.time_ns(), AckResult.ACCEPTED)

    path = tmp_path / "cmds.mcap"
    with (
        Mesh(embedded_router(port, fleet=fleet)) as gcs,
        Mesh(embedded_peer(port, fleet=fleet)) as veh,
    ):
        veh.serve_commands(7, handler)
        veh.declare_vehicle(7)
        assert gcs.presence().wait_for(lambda v, _g: 7 in v, 10.0)
        with Recorder(RecordConfig(str(path), embedded_peer(port, fleet=fleet))) as rec:
            # Probe with commands to a vehicle that does not exist (only the recorder's
            # v/*/cmd queryable matches) until the recorder has met the mesh and records them.
            deadline = time.monotonic() + 10.0
            while "cmd" not in rec.counts and time.monotonic() < deadline:
                probe = Command(CommandKind.HOLD, new_nonce(), time.time_ns(), targets=(PROBE_ID,))
                assert not gcs.send_command(probe, timeout_s=0.5).ok
                time.sleep(0.05)
            sent = []
            for targets in ((7,), ()):
                cmd = Command(CommandKind.HOLD, new_nonce(), time.time_ns(), targets=targets)
                res = gcs.send_command(cmd, expect=[7])
                assert res.ok and res.errors == () and list(res.outcomes) == [7]
                sent.append(cmd)
            veh.publish_event(Event(7, time.time_ns(), "hello"))
            time.sleep(0.3)
    assert seen == [c.nonce for c in sent]  # each command reached the vehicle exactly once
    rec = read_recording(path)
    cmds = [Command.decode(m.data) for m in rec.messages if m.topic.endswith("/cmd")]
    cmds = [c for c in cmds if c.targets != (PROBE_ID,)]
    assert [c.nonce for c in cmds] == [c.nonce for c in sent]
    topics = {m.topic for m in rec.messages}
    assert keys.cmd(fleet, 7) in topics and keys.all_cmds(fleet) in topics
    assert keys.alive(fleet, 7) in topics and keys.event(fleet, 7) in topics
    # Replies are seen only by the querier; the vehicle's Mesh publishes a copy of each ack.
    acks = [CommandAck.decode(m.data) for m in rec.messages if m.topic == keys.ack(fleet, 7)]
    assert [a.nonce for a in acks] == [c.nonce for c in sent]


def test_published_guidance_traces_are_recorded_on_their_own_key(tmp_path):
    from comms.schema import GuidanceTrace

    fleet = "t" + uuid.uuid4().hex[:8]
    port = free_tcp_port()
    path = tmp_path / "traces.mcap"
    events: list[Event] = []
    with (
        Mesh(embedded_router(port, fleet=fleet)) as gcs,
        Mesh(embedded_peer(port, fleet=fleet)) as veh,
    ):
        gcs.subscribe_events(lambda ev, _t: events.append(ev))
        with Recorder(RecordConfig(str(path), embedded_peer(port, fleet=fleet))) as rec:
            sent = []
            deadline = time.monotonic() + 10.0
            while rec.counts.get("trace", 0) < 3 and time.monotonic() < deadline:
                tr = GuidanceTrace(
                    7, len(sent), time.time_ns(), 0.5, (1.0, 0.0, 0.0), ((2, 3, 0.1),)
                )
                veh.publish_trace(tr)
                sent.append(tr)
                time.sleep(0.05)
            time.sleep(0.2)
    recorded = read_recording(path)
    got = [
        GuidanceTrace.decode(m.data) for m in recorded.messages if m.topic == keys.trace(fleet, 7)
    ]
    assert len(got) >= 3 and all(t in sent for t in got)
    assert summarise(recorded)["counts"]["traces"] == len(got)
    assert events == []  # off the event key: stations following events never see traces
