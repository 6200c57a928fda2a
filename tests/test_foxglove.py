"""Foxglove's standard channels: in a real recording, added to an old one, and live over the
Foxglove WebSocket protocol. Everything is read back with the schemas' own decoders (protobuf from
the FileDescriptorSet in the file, JSON), never with covey's.

One real flight serves the e2e tests: two `covey agent` processes take off and fly to goals while
an in-process Recorder records and the live bridge serves, and a WebSocket client listens.
"""

from __future__ import annotations

import base64
import json
import math
import os
import random
import struct
import subprocess
import sys
import threading
import time
import uuid

import numpy as np
import pytest
import shapely
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from mcap.records import Channel
from websockets.sync.client import connect

from comms import keys, schema
from comms.commands import new_nonce
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.plan import FleetPlan, Zone
from comms.session import embedded_peer, embedded_router, free_tcp_port
from groundstation.state_routes import planned_routes
from groundstation.target_check import router_for
from kit.procs import ChildGroup
from recording import foxglove_channels as fc
from recording.foxglove_bridge import BridgeConfig, FoxgloveBridge
from recording.foxglove_worker import FoxgloveChunks
from recording.mcap_chunks import MAX_ID, ChunkBuilder
from recording.record import (
    FoxgloveIncomplete,
    McapSink,
    RecordConfig,
    Recorder,
    add_foxglove_channels,
    read_recording,
)
from tools.record_cli import record_cli

VEHICLES = (1, 2)
STARTS = {1: (0.0, 0.0), 2: (0.0, 8.0)}
GOALS = {1: (6.0, 6.0, -3.0), 2: (6.0, 0.0, -3.0)}
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
ORIGIN = GeoOrigin(47.3977, 8.5456, 488.0)
MISSIONS = {  # vehicle -> its uploaded waypoints (north, east, altitude up)
    1: ((10.0, 0.0, 5.0), (10.0, 10.0, 6.0), (0.0, 10.0, 7.0)),
    2: ((5.0, 5.0, 150.0), (0.0, 0.0, 5.0)),
}


def _mission(vid: int, route, stamp_ns: int, mission_id: int = 40) -> schema.Mission:
    items = tuple(
        schema.MissionItem(schema.MissionItemKind.WAYPOINT, x=n, y=e, alt_m=a) for n, e, a in route
    )
    return schema.Mission(new_nonce(), stamp_ns, items, mission_id=mission_id + vid, targets=(vid,))


def proto_class(name: str, fds: bytes):
    """The message class that protobuf itself builds from a channel's FileDescriptorSet."""
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(fds).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def read_standard(path) -> dict[str, list]:
    """topic -> decoded messages (protobuf objects or JSON dicts), via the mcap library."""
    out: dict[str, list] = {}
    classes: dict[int, object] = {}
    with open(path, "rb") as f:
        for sch, ch, msg in make_reader(f).iter_messages():
            if ch.message_encoding == "protobuf":
                assert sch.encoding == "protobuf"
                cls = classes.get(sch.id) or classes.setdefault(
                    sch.id, proto_class(sch.name, sch.data)
                )
                out.setdefault(ch.topic, []).append(cls.FromString(msg.data))
            elif ch.message_encoding == "json":
                assert sch.encoding == "jsonschema" and json.loads(sch.data)["type"] == "object"
                out.setdefault(ch.topic, []).append(json.loads(msg.data))
    return out


def _ns(ts) -> int:
    return ts.seconds * 1_000_000_000 + ts.nanos


# -- the conversion alone ----------------------------------------------------------------------
def test_state_converts_to_every_standard_message():
    conv = fc.Converter(fc.FoxgloveConfig(origin=ORIGIN))
    s = schema.VehicleState(
        7,
        3,
        1_700_000_000_123_456_789,
        (10.0, -4.0, -12.5),
        (0.0, 2.0, 0.0),
        math.pi / 2,
        mode=schema.Mode.GOTO,
        flags=schema.StateFlag.HAS_GOAL,
        goal_ned_m=(20.0, 0.0, -12.0),
    )
    outs = {o.topic: o for o in conv.convert(keys.state("f", 7), s.encode(), 5)}
    assert set(outs) == {"/tf", "/vehicles/7/pose", "/vehicles/7/fix", "/scene"}
    pose = proto_class("foxglove.PoseInFrame", fc.POSE_IN_FRAME.data).FromString(
        outs["/vehicles/7/pose"].data
    )
    assert pose.frame_id == "ned" and _ns(pose.timestamp) == s.stamp_ns
    p = pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx(s.pos_ned_m, abs=1e-6)
    assert pose.pose.orientation.z == pytest.approx(math.sqrt(0.5))
    fix = proto_class("foxglove.LocationFix", fc.LOCATION_FIX.data).FromString(
        outs["/vehicles/7/fix"].data
    )
    assert (fix.latitude, fix.longitude, fix.altitude) == pytest.approx(
        ORIGIN.to_global(*s.pos_ned_m), abs=1e-9
    )
    assert fix.heading == pytest.approx(90.0)
    scene = proto_class("foxglove.SceneUpdate", fc.SCENE_UPDATE.data).FromString(
        outs["/scene"].data
    )
    (ent,) = scene.entities
    assert ent.id == "vehicle/7" and len(ent.cubes) == len(ent.arrows) == len(ent.spheres) == 1
    assert ent.cylinders[0].size.x == pytest.approx(6.0)  # ring diameter = 2 * separation
    arrow = ent.arrows[0]
    assert arrow.shaft_length == pytest.approx(2.0)
    # the arrow's +x, turned by its quaternion, points east (NED y)
    q = arrow.pose.orientation
    x_axis = (1 - 2 * (q.y**2 + q.z**2), 2 * (q.x * q.y + q.w * q.z), 2 * (q.x * q.z - q.w * q.y))
    assert x_axis == pytest.approx((0.0, 1.0, 0.0), abs=1e-9)
    # no link health before a full interval of states
    later = schema.VehicleState(7, 13, s.stamp_ns, s.pos_ned_m, s.vel_ned_m_s, 0.0)
    outs = {o.topic: o for o in conv.convert(keys.state("f", 7), later.encode(), 5 + 2_000_000_000)}
    link = json.loads(outs["/vehicles/7/link"].data)
    assert link["rate_hz"] == pytest.approx(1.0) and link["loss_share"] == pytest.approx(1 - 2 / 11)


@pytest.mark.parametrize(
    ("severity", "level"),
    [
        (schema.Severity.DEBUG, 1),
        (schema.Severity.INFO, 2),
        (schema.Severity.WARNING, 3),
        (schema.Severity.ERROR, 4),
        (schema.Severity.CRITICAL, 5),
    ],
)
def test_event_becomes_a_log_with_its_level(severity, level):
    ev = schema.Event(4, 123, "geofence", severity, schema.EventKind.FAILSAFE)
    (out,) = fc.Converter().convert(keys.event("f", 4), ev.encode(), 9)
    log = proto_class("foxglove.Log", fc.LOG.data).FromString(out.data)
    assert log.level == level and log.name == "vehicle/4" and "geofence" in log.message


@pytest.mark.parametrize(("ok", "level"), [(True, 2), (False, 4)])
def test_an_action_outcome_becomes_an_action_log_line(ok, level):
    msg = schema.ActionOutcome(4, 0x5FBFE957, ok, "takeoff to 5 m", stamp_ns=123)
    (out,) = fc.Converter().convert(keys.event("f", 4), msg.encode(), 9)
    log = proto_class("foxglove.Log", fc.LOG.data).FromString(out.data)
    word = "done" if ok else "failed"
    assert out.topic == fc.EVENTS_TOPIC and log.level == level and log.name == "vehicle/4"
    assert log.message == f"[ACTION] 000000005fbfe957 {word}: takeoff to 5 m"


def _scene_entities(outs) -> list:
    cls = proto_class("foxglove.SceneUpdate", fc.SCENE_UPDATE.data)
    return [e for o in outs if o.topic == "/scene" for e in cls.FromString(o.data).entities]


def test_an_accepted_mission_upload_becomes_its_vehicles_route_line():
    """A route per vehicle that accepted the upload (none for a refusal), its waypoints in
    order (a global one at its local position), also when the ack overtook the mission; a
    vehicle that leaves takes its route along; /commands lists the upload."""
    conv = fc.Converter(fc.FoxgloveConfig(origin=ORIGIN))
    lat, lon, amsl = ORIGIN.to_global(0.0, 20.0, -8.0)
    items = (
        schema.MissionItem(schema.MissionItemKind.TAKEOFF, alt_m=5.0),
        schema.MissionItem(schema.MissionItemKind.WAYPOINT, x=10.0, y=0.0, alt_m=5.0),
        schema.MissionItem(
            schema.MissionItemKind.WAYPOINT, schema.MissionFrame.GLOBAL, lat, lon, amsl
        ),
        schema.MissionItem(schema.MissionItemKind.LAND),
    )
    m = schema.Mission(77, 1, items, mission_id=3, targets=(1, 2, 3))
    # vehicle 3's ack overtakes the upload (another Zenoh path)
    early = schema.CommandAck(3, 77, 2, schema.AckResult.ACCEPTED, "")
    assert _scene_entities(conv.convert(keys.ack("f", 3), early.encode(), 2)) == []
    outs = conv.convert(keys.all_cmds("f"), m.encode(), 3)
    cmd = json.loads(next(o.data for o in outs if o.topic == "/commands"))
    assert (cmd["kind"], cmd["params"], cmd["targets"]) == ("MISSION", [3, 4], [1, 2, 3])
    (r3,) = _scene_entities(outs)
    ok = schema.CommandAck(1, 77, 4, schema.AckResult.ACCEPTED, "")
    no = schema.CommandAck(2, 77, 4, schema.AckResult.REJECTED, "item 2: outside the fence")
    (r1,) = _scene_entities(conv.convert(keys.ack("f", 1), ok.encode(), 4))
    assert _scene_entities(conv.convert(keys.ack("f", 2), no.encode(), 4)) == []
    for ent, vid in ((r1, 1), (r3, 3)):
        assert ent.id == f"route/{vid}" and ent.frame_id == "ned"
        (line,) = ent.lines
        pts = [c for p in line.points for c in (p.x, p.y, p.z)]
        assert pts == pytest.approx([10.0, 0.0, -5.0, 0.0, 20.0, -8.0], abs=1e-3)
        assert len(ent.spheres) == 2 and ent.texts[0].text == f"mission 3 ({vid})"
    outs = conv.convert(keys.ack("f", 1), ok.encode(), 5)
    (ack,) = [json.loads(o.data) for o in outs if o.topic == "/acks"]
    assert ack["command_kind"] == "MISSION"
    outs = conv.convert(keys.alive("f", 1), b"\x00", 6)
    scene = proto_class("foxglove.SceneUpdate", fc.SCENE_UPDATE.data).FromString(outs[0].data)
    assert {d.id for d in scene.deletions} == {"vehicle/1", "route/1"}


def test_garbage_and_departures():
    conv = fc.Converter()
    assert conv.convert(keys.state("f", 1), b"\x01\x01junk", 0) == []
    outs = conv.convert(keys.alive("f", 1), b"\x00", 0)
    scene = proto_class("foxglove.SceneUpdate", fc.SCENE_UPDATE.data).FromString(outs[0].data)
    assert scene.deletions[0].id == "vehicle/1"


def test_convert_all_equals_convert_one_by_one():
    """The batch path (states decoded as arrays) gives what convert() gives, message by message,
    on a fleet's traffic mixed with presence bytes, garbage and corrupt states."""
    rng = random.Random(4)
    items = _fleet_traffic(40)
    for k in range(200):
        topic, data, recv_ns = rng.choice(items)
        kind = k % 4
        if kind == 0:
            data = bytes([1]) + rng.randbytes(rng.choice([63, 64, 127]))
        elif kind == 1:
            data = bytearray(data)
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            data = bytes(data)
        elif kind == 2:
            topic, data = keys.alive("w", rng.randint(1, 3)), rng.choice([b"\x00", b"\x01"])
        items.insert(rng.randrange(len(items)), (topic, data, recv_ns))
    one, many = fc.Converter(), fc.Converter()
    want = [one.convert(*item) for item in items]
    got = list(many.convert_all(items))
    assert got == want and sum(map(len, got)) > len(items)


WALL = ((-10.0, 8.0), (10.0, 8.0), (10.0, 12.0), (-10.0, 12.0))
"""A keep-out zone across the way of a vehicle at N 0, E 0 told to go to N 0, E 20."""


def _route_traffic(t0: int) -> list[tuple[str, bytes, int]]:
    """A plan with the wall, then vehicle 1 flying a goto across it at 10 Hz for 2.5 s, then
    holding for 1.5 s; vehicle 2 holds throughout."""
    plan = FleetPlan("w", 3, 0, keep_out=(Zone(WALL, "wall"),))
    out = [(keys.plan("w"), schema.PlanMessage(plan).encode(), t0)]
    for k in range(40):
        t = t0 + (k + 1) * 100_000_000
        for vid, mode in ((1, schema.Mode.GOTO if k < 25 else schema.Mode.HOLDING),
                          (2, schema.Mode.HOLDING)):  # fmt: skip
            s = schema.VehicleState(
                vid, k, t, (0.0, -0.1 * k if vid == 1 else 30.0, -5.0), (0.0, 0.0, 0.0), 0.0,
                mode=mode, flags=schema.StateFlag.HAS_GOAL, goal_ned_m=(0.0, 20.0, -5.0),
            )  # fmt: skip
            out.append((keys.state("w", vid), s.encode(), t))
    return out


def test_the_planned_route_goes_round_the_zone_and_is_deleted_when_the_vehicle_holds(tmp_path):
    """The station's route computation (planned_routes with router_for's planner) drawn in
    Foxglove: an entity "plan_route/1" in frame ned from the vehicle round the wall to its goal
    (the station's very points; every leg clear of the zone), at most once per route interval,
    deleted when the vehicle holds; none for a vehicle that holds; the planner built once for
    a plan put again. The recording (worker process, MCAP) carries the same."""
    t0 = 1_700_000_000_000_000_000
    traffic = _route_traffic(t0)
    conv = fc.Converter(fc.FoxgloveConfig(origin=ORIGIN))
    routes: list[tuple[int, object]] = []  # (recv_ns, route entity)
    deleted: list[tuple[int, str]] = []
    for topic, data, recv_ns in traffic:
        for o in conv.convert(topic, data, recv_ns):
            if o.topic != "/scene":
                continue
            update = proto_class("foxglove.SceneUpdate", fc.SCENE_UPDATE.data).FromString(o.data)
            routes += [(recv_ns, e) for e in update.entities if e.id.startswith("plan_route/")]
            deleted += [(recv_ns, d.id) for d in update.deletions]
    assert {e.id for _, e in routes} == {"plan_route/1"}
    times = [t for t, _ in routes]
    assert times[0] == t0 + 100_000_000 and len(times) == 3  # 0, 1 and 2 s into the goto
    assert all(b - a >= 1_000_000_000 for a, b in zip(times, times[1:], strict=False))
    assert deleted == [(t0 + 3_100_000_000, "plan_route/1")]  # the first tick it holds
    wall = shapely.Polygon(WALL)
    router = router_for(FleetPlan("w", 3, 0, keep_out=(Zone(WALL, "wall"),)), 3.0)
    for recv_ns, e in routes:
        assert e.frame_id == fc.NED_FRAME and e.lifetime.seconds == 5
        (line,) = e.lines
        pts = np.array([(p.x, p.y, p.z) for p in line.points])
        k = round((recv_ns - t0) / 100_000_000) - 1
        here = schema.VehicleState(
            1, k, 0, (0.0, -0.1 * k, -5.0), (0.0, 0.0, 0.0), 0.0, mode=schema.Mode.GOTO,
            flags=schema.StateFlag.HAS_GOAL, goal_ned_m=(0.0, 20.0, -5.0),
        )  # fmt: skip
        np.testing.assert_allclose(pts, planned_routes(router, [here])[1], atol=1e-6)
        assert pts[0] == pytest.approx((0.0, -0.1 * k, -5.0)) and len(pts) >= 3
        assert pts[-1] == pytest.approx((0.0, 20.0, -5.0))
        assert shapely.LineString(pts[:, :2]).distance(wall) > 1.8  # round it, not through
        assert shapely.LineString([(0.0, -0.1 * k), (0.0, 20.0)]).intersects(wall)
    # the same plan put again builds no new planner; a changed one does
    built = conv._router
    t = t0 + 5_000_000_000
    conv.convert(keys.plan("w"), traffic[0][1], t)
    conv.convert(*traffic[1][:2], t + 1)
    assert conv._router is built
    moved = FleetPlan("w", 4, 0, keep_out=(Zone(((-10, 28), (10, 28), (10, 32), (-10, 32))),))
    conv.convert(keys.plan("w"), schema.PlanMessage(moved).encode(), t + 2_000_000_000)
    conv.convert(*traffic[1][:2], t + 3_000_000_000)
    assert conv._router is not built and conv._router is not None
    # a recording (the worker process) draws the same routes
    _record_sink(tmp_path / "r.mcap", traffic, foxglove=fc.FoxgloveConfig(origin=ORIGIN))
    scene = read_standard(tmp_path / "r.mcap")["/scene"]
    recorded = [e for u in scene for e in u.entities if e.id == "plan_route/1"]
    assert [[(p.x, p.y) for p in e.lines[0].points] for e in recorded] == [
        [(p.x, p.y) for p in e.lines[0].points] for _, e in routes
    ]
    assert [d.id for u in scene for d in u.deletions] == ["plan_route/1"]


# -- the worker process ------------------------------------------------------------------------
def _fleet_traffic(n_steps: int = 60) -> list[tuple[str, bytes, int]]:
    """Three vehicles at 10 Hz with goals, a mode change, events, a command and a departure."""
    out = []
    t0 = 1_700_000_000_000_000_000
    for k in range(n_steps):
        t = t0 + k * 100_000_000
        for vid in (1, 2, 3):
            mode = schema.Mode.GOTO if k > 20 else schema.Mode.HOLDING
            s = schema.VehicleState(
                vid,
                k,
                t - 3_000_000,
                (0.1 * k, 2.0 * vid, -4.0),
                (1.0, 0.5 * vid, 0.0),
                0.3,
                mode=mode,
                armed=True,
                flags=schema.StateFlag.HAS_GOAL,
                goal_ned_m=(10.0, 2.0 * vid, -4.0),
            )
            out.append((keys.state("w", vid), s.encode(), t + vid))
        if k % 15 == 0:
            out.append((keys.event("w", 2), schema.Event(2, t, f"step {k}").encode(), t + 5))
        if k == 10:
            cmd = schema.Command.takeoff(3.0, nonce=77, stamp_ns=t, targets=(1, 2))
            out.append((keys.cmd("w", 1), cmd.encode(), t + 6))
    out.append((keys.alive("w", 3), b"\x00", t0 + n_steps * 100_000_000))
    return out


def _record_sink(path, traffic, **kw) -> dict[str, int]:
    with open(path, "wb") as f:
        sink = McapSink(f, "w", chunk_bytes=2048, flush_interval_s=0.05, **kw)
        for item in traffic:
            sink.put(*item)
        sink.close()
    return sink.counts


def _by_topic(path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        for _s, ch, m in make_reader(f).iter_messages():
            out.setdefault(ch.topic, []).append((m.log_time, m.data))
    return out


def test_the_worker_process_writes_what_the_writer_thread_would(tmp_path):
    """The fast path (a child process) equals the reference (conversion in the writer thread):
    the same standard messages, and covey's own unchanged."""
    traffic = _fleet_traffic()
    fox = fc.FoxgloveConfig(origin=ORIGIN)
    inline = _record_sink(tmp_path / "inline.mcap", traffic, foxglove=fox, foxglove_worker=False)
    worker = _record_sink(tmp_path / "worker.mcap", traffic, foxglove=fox)
    assert inline == worker and worker["foxglove"] > len(traffic)
    a, b = _by_topic(tmp_path / "inline.mcap"), _by_topic(tmp_path / "worker.mcap")
    assert a == b
    assert [
        (m.topic, m.log_time_ns, m.data) for m in read_recording(tmp_path / "worker.mcap").messages
    ] == sorted(((t, r, d) for t, d, r in traffic), key=lambda m: m[1])
    std = read_standard(tmp_path / "worker.mcap")  # protobuf from the file's own schemas
    assert all(len(std[f"/vehicles/{v}/pose"]) == 60 for v in (1, 2, 3))
    assert std["/commands"][0]["targets"] == [1, 2]
    assert std["/scene"][-1].deletions[0].id == "vehicle/3"


def _until(done, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert done()


def test_the_worker_waits_while_the_recorder_is_busy(tmp_path):
    """Faster than foxglove_defer_hz, the raw chunks are held back from the worker; the first
    quiet flush hands them all over, and nothing is missing at the end."""
    now = [0.0]
    traffic = _fleet_traffic(40)
    fox = fc.FoxgloveConfig(origin=ORIGIN)
    with open(tmp_path / "busy.mcap", "wb") as f:
        sink = McapSink(
            f, "w", 2048, 0.05, clock_s=lambda: now[0], foxglove=fox, foxglove_defer_hz=100.0
        )
        for item in traffic:
            sink.put(*item)
        _until(lambda: sum(sink.counts.values()) == len(traffic))
        now[0] = 0.05  # the next flush sees len(traffic) / 0.05 s: thousands per second
        _until(lambda: sink._flushed_s == 0.05)
        assert sink._worker.sent == 0 and sink._plains
        now[0] = 0.10  # a quiet flush: all of it goes
        _until(lambda: sink._worker.sent == 1)
        sink.close()
    _record_sink(tmp_path / "ref.mcap", traffic, foxglove=fox, foxglove_worker=False)
    assert _by_topic(tmp_path / "busy.mcap") == _by_topic(tmp_path / "ref.mcap")


def test_a_dead_worker_is_said_and_covey_channels_stay_whole(tmp_path):
    traffic = _fleet_traffic(20)
    path = tmp_path / "dead.mcap"
    with open(path, "wb") as f:
        sink = McapSink(f, "w", 2048, 0.05, foxglove=fc.FoxgloveConfig())
        sink._worker._proc.kill()
        for item in traffic:
            sink.put(*item)
        # still recording covey's channels, flushed as ever (a kill now would keep them)
        deadline = time.monotonic() + 20.0
        while len(read_recording(path).messages) < len(traffic) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(read_recording(path).messages) == len(traffic)
        with pytest.raises(FoxgloveIncomplete, match="--foxglove-from"):
            sink.close()
    rec = read_recording(path)
    assert not rec.truncated and len(rec.messages) == len(traffic)


def test_the_worker_leaves_when_its_recorder_is_killed(tmp_path):
    """SIGKILL the recording process: its worker reads the end of its pipe and exits."""
    script = (
        "import os, sys, time\n"
        "from recording.foxglove_channels import FoxgloveConfig\n"
        "from recording.record import McapSink\n"
        f"sink = McapSink(open({str(tmp_path / 'k.mcap')!r}, 'wb'), 'w', 2048, 0.05,"
        " foxglove=FoxgloveConfig())\n"
        "print(sink._worker._proc.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    worker_pid = int(proc.stdout.readline())
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 20.0
    while _running(worker_pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _running(worker_pid), "the Foxglove worker outlived its recorder"


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False


def test_channel_ids_run_out_without_breaking_the_recording():
    chunks = FoxgloveChunks(fc.FoxgloveConfig())
    chunks._next_id = MAX_ID - 4  # room for a few schemas and channels only
    plain = _plain(_fleet_traffic(3))
    built = chunks.add([plain])
    ids = [c.id for b in built for c in b.channels] + [s.id for b in built for s in b.schemas]
    assert ids and max(ids) <= MAX_ID and chunks.refused > 0 and chunks.messages > 0


def test_covey_topics_beyond_the_ids_are_refused_not_fatal(tmp_path, monkeypatch):
    monkeypatch.setattr("recording.record.FIRST_ID", 4)  # room for 3 covey topics
    traffic = _fleet_traffic(5)  # states of 3 vehicles, an event, a command, a departure
    counts = _record_sink(tmp_path / "full.mcap", traffic)
    rec = read_recording(tmp_path / "full.mcap")
    assert counts["refused"] == len(traffic) - len(rec.messages) > 0 and not rec.truncated
    assert {m.topic for m in rec.messages} == {keys.state("w", v) for v in (1, 2, 3)}


def _plain(traffic) -> bytes:
    """Raw records as the recorder's writer thread hands them to the worker."""
    b = ChunkBuilder()
    ids: dict[str, int] = {}
    for topic, data, recv_ns in traffic:
        if topic not in ids:
            ids[topic] = len(ids) + 1
            b.add_channel(Channel(ids[topic], topic, "covey-v1", {}, 0))
        b.add(ids[topic], recv_ns, data, recv_ns)
    return b.build(keep_plain=True).plain


# -- a real flight -------------------------------------------------------------------------------
def _command_all(mesh: Mesh, make, deadline_s: float = 15.0) -> None:
    pending = set(VEHICLES)
    end = time.monotonic() + deadline_s
    while pending and time.monotonic() < end:
        for vid in sorted(pending):
            if mesh.send_command(make(vid), timeout_s=1.0).ok:
                pending.discard(vid)
        if pending:
            time.sleep(0.2)
    assert not pending, f"vehicles {pending} did not accept"


class WsListener(threading.Thread):
    """A Foxglove WebSocket client: collects advertisements and subscribes to the pose topics."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port, self.stop = port, threading.Event()
        self.channels: dict[int, dict] = {}
        self.poses: list[tuple[str, bytes]] = []
        self.subprotocol = None
        self.subs_sent: list = []
        self.resubscribed: list[str] = []

    def run(self) -> None:
        uri = f"ws://127.0.0.1:{self.port}"
        # foxglove-sdk 0.30 names the protocol foxglove.sdk.v1 and refuses the old
        # foxglove.websocket.v1 name with HTTP 400; current Foxglove offers both.
        with connect(uri, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
            self.subprotocol = ws.subprotocol
            subs: dict[int, str] = {}
            asked: dict[int, tuple[int, float]] = {}  # sub id -> (channel id, when subscribed)
            heard: set[int] = set()
            while not self.stop.is_set():
                # Seen twice on a loaded machine: a subscription that never delivers. Ask again
                # (unsubscribe + subscribe) after 3 s of silence, and say so.
                for sub_id, (ch_id, t) in list(asked.items()):
                    if sub_id not in heard and time.monotonic() - t > 3.0:
                        new_id = len(subs) + 1
                        subs[new_id] = subs[sub_id]
                        ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [sub_id]}))
                        ws.send(
                            json.dumps(
                                {
                                    "op": "subscribe",
                                    "subscriptions": [{"id": new_id, "channelId": ch_id}],
                                }
                            )
                        )
                        del asked[sub_id]
                        asked[new_id] = (ch_id, time.monotonic())
                        self.resubscribed.append(subs[sub_id])
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg.get("op") == "advertise":
                        new = []
                        for ch in msg["channels"]:
                            self.channels[ch["id"]] = ch
                            if ch["topic"].endswith("/pose"):
                                sub_id = len(subs) + 1
                                subs[sub_id] = ch["topic"]
                                new.append({"id": sub_id, "channelId": ch["id"]})
                                asked[sub_id] = (ch["id"], time.monotonic())
                        if new:
                            ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                            self.subs_sent.append(new)
                elif frame[0] == 0x01:  # message data: op, subscription id, log time, payload
                    sub_id, _log_ns = struct.unpack_from("<IQ", frame, 1)
                    heard.add(sub_id)
                    self.poses.append((subs[sub_id], frame[13:]))


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("foxflight")
    fleet = "fox" + uuid.uuid4().hex[:8]
    port = free_tcp_port()
    path, raw_only = tmp / "flight.mcap", tmp / "raw.mcap"
    fox = fc.FoxgloveConfig(origin=ORIGIN)
    agents = ChildGroup(
        prefix=[sys.executable, "-m", "covey_cli", "agent"],
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        output="discard",
        stderr="discard",
        grace_s=10.0,
    )
    mesh_states: dict[tuple[int, int], tuple] = {}
    with Mesh(embedded_router(port, fleet=fleet)) as mesh:
        mesh.subscribe_states(
            lambda s, _t: mesh_states.__setitem__((s.vehicle_id, s.stamp_ns), s.pos_ned_m)
        )
        peer = embedded_peer(port, fleet=fleet)
        with (
            Recorder(RecordConfig(str(path), peer, foxglove=fox)),
            Recorder(RecordConfig(str(raw_only), peer, foxglove=None)),
            FoxgloveBridge(BridgeConfig(mesh=peer, port=0, foxglove=fox)) as bridge,
        ):
            ws = WsListener(bridge.port)
            ws.start()
            try:
                time.sleep(1.0)  # discovery
                connect_ep = f"tcp/127.0.0.1:{port}"
                for vid in VEHICLES:
                    n, e = STARTS[vid]
                    agents.start(
                        "--id",
                        str(vid),
                        "--fleet",
                        fleet,
                        "--connect",
                        connect_ep,
                        f"--start-ne-m={n},{e}",
                        "--no-gcs-failsafe",
                    )
                assert mesh.presence().wait_for(lambda v, _g: set(VEHICLES) <= v, 30.0)
                stamp = time.time_ns
                _command_all(
                    mesh,
                    lambda v: schema.Command.takeoff(
                        3.0, nonce=new_nonce(), stamp_ns=stamp(), targets=(v,)
                    ),
                )
                time.sleep(2.5)
                _command_all(
                    mesh,
                    lambda v: schema.Command.goto_local(
                        *GOALS[v], nonce=new_nonce(), stamp_ns=stamp(), targets=(v,)
                    ),
                )
                # a route each, kept not flown: vehicle 1 accepts, vehicle 2 refuses (150 m)
                for vid, route in MISSIONS.items():
                    up = mesh.send_command(_mission(vid, route, stamp()), timeout_s=5.0)
                    assert up.ok is (vid == 1), up.summary()
                time.sleep(2.5)
            finally:
                ws.stop.set()
                ws.join(5)
                agents.stop()
        yield {
            "path": path,
            "raw": raw_only,
            "tmp": tmp,
            "ws": ws,
            "mesh_states": dict(mesh_states),
            "fox": fox,
        }


@pytest.mark.e2e
def test_every_standard_channel_decodes_and_matches_the_raw_one(flight):
    std = read_standard(flight["path"])
    for vid in VEHICLES:
        for leaf in ("pose", "fix", "link"):
            assert std.get(f"/vehicles/{vid}/{leaf}"), f"no /vehicles/{vid}/{leaf}"
    for topic in ("/tf", "/scene", "/events", "/commands", "/acks"):
        assert std.get(topic), f"no {topic}"
    raw = {}
    for m in read_recording(flight["path"]).messages:  # covey's channels, as replay reads them
        if m.topic.endswith("/state"):
            s = schema.VehicleState.decode(m.data)
            raw[(s.vehicle_id, s.stamp_ns)] = s
    moved = 0
    for vid in VEHICLES:
        poses, fixes = std[f"/vehicles/{vid}/pose"], std[f"/vehicles/{vid}/fix"]
        assert len(poses) == len(fixes) == sum(k[0] == vid for k in raw)
        for pose, fix in zip(poses, fixes, strict=True):
            s = raw[(vid, _ns(pose.timestamp))]
            p = pose.pose.position
            assert (
                max(abs(a - b) for a, b in zip((p.x, p.y, p.z), s.pos_ned_m, strict=True)) <= 0.01
            )
            lat, lon, alt = ORIGIN.to_global(*s.pos_ned_m)
            assert abs(fix.latitude - lat) < 1e-9 and abs(fix.longitude - lon) < 1e-9
            assert abs(fix.altitude - alt) < 0.01
            moved += p.z < -1.0
    assert moved >= 20, "the recording holds the flight, not just the ground"


@pytest.mark.e2e
def test_acks_name_the_vehicles_commanded(flight):
    std = read_standard(flight["path"])
    commands = {c["nonce"]: c for c in std["/commands"]}
    accepted: dict[str, set[int]] = {}
    joined = 0
    for ack in std["/acks"]:
        cmd = commands[ack["nonce"]]
        assert ack["vehicle_id"] in cmd["targets"], (ack, cmd)
        # the join by nonce is filled in when the command reached the recorder first; an ack
        # may overtake its command (another Zenoh path), then the kind is left empty
        assert ack["command_kind"] in ("", cmd["kind"])
        joined += ack["command_kind"] == cmd["kind"]
        if ack["accepted"]:
            accepted.setdefault(cmd["kind"], set()).add(ack["vehicle_id"])
    assert accepted["TAKEOFF"] == accepted["GOTO_LOCAL"] == set(VEHICLES)
    assert joined >= len(std["/acks"]) // 2
    raw_events = [  # events and autopilot outcomes share the event key
        schema.decode_event_message(m.data)
        for m in read_recording(flight["path"]).messages
        if m.topic.endswith("/event")
    ]
    logs = std["/events"]
    assert len(logs) >= len(raw_events) > 0
    for ev in raw_events:
        assert any(
            _ns(lg.timestamp) == ev.stamp_ns
            and lg.name == f"vehicle/{ev.vehicle_id}"
            and lg.level == int(ev.severity) + 1
            for lg in logs
        )


@pytest.mark.e2e
def test_the_recording_draws_each_accepted_mission_as_a_route(flight):
    """Real agents answered the uploads: the recording's /scene holds vehicle 1's route (its
    three waypoints in order, in NED) and none for vehicle 2, which refused its mission."""
    std = read_standard(flight["path"])
    routes = {e.id: e for u in std["/scene"] for e in u.entities if e.id.startswith("route/")}
    assert set(routes) == {"route/1"}, set(routes)
    (line,) = routes["route/1"].lines
    got = [c for p in line.points for c in (p.x, p.y, p.z)]
    assert got == pytest.approx([c for n, e, a in MISSIONS[1] for c in (n, e, -a)], abs=1e-6)
    assert any(c["kind"] == "MISSION" for c in std["/commands"])


@pytest.mark.e2e
def test_live_bridge_serves_the_poses_the_mesh_carries(flight):
    ws = flight["ws"]
    assert ws.subprotocol in SUBPROTOCOLS
    topics = {ch["topic"]: ch for ch in ws.channels.values()}
    for vid in VEHICLES:
        assert f"/vehicles/{vid}/pose" in topics and f"/vehicles/{vid}/fix" in topics
    ch = topics["/vehicles/1/pose"]
    assert ch["encoding"] == "protobuf" and ch["schemaName"] == "foxglove.PoseInFrame"
    cls = proto_class(ch["schemaName"], base64.b64decode(ch["schema"]))
    got = {vid: 0 for vid in VEHICLES}
    for topic, payload in ws.poses:
        pose = cls.FromString(payload)
        vid = int(topic.split("/")[2])
        expected = flight["mesh_states"][(vid, _ns(pose.timestamp))]
        p = pose.pose.position
        assert max(abs(a - b) for a, b in zip((p.x, p.y, p.z), expected, strict=True)) <= 0.01
        got[vid] += 1
    if ws.resubscribed:
        print(f"the bridge delivered nothing on {ws.resubscribed} until they were subscribed again")
    assert all(n >= 20 for n in got.values()), (got, ws.subs_sent, ws.resubscribed, sorted(topics))


@pytest.mark.e2e
def test_foxglove_from_adds_the_channels_and_keeps_covey_bytes(flight, capsys):
    out = flight["tmp"] / "added.mcap"
    assert (
        record_cli(
            [
                "--foxglove-from",
                str(flight["raw"]),
                "-o",
                str(out),
                "--origin",
                "47.3977,8.5456,488",
            ]
        )
        == 0
    )
    assert not read_standard(flight["raw"])  # recorded with --no-foxglove: covey's only
    before, after = read_recording(flight["raw"]), read_recording(out)
    assert [(m.topic, m.log_time_ns, m.data) for m in before.messages] == [
        (m.topic, m.log_time_ns, m.data) for m in after.messages
    ]
    std = read_standard(out)
    n_states = sum(m.topic.endswith("/state") for m in before.messages)
    assert sum(len(std[f"/vehicles/{v}/pose"]) for v in VEHICLES) == n_states
    # the same conversion as recording live: identical standard messages per state
    direct = add_foxglove_channels(flight["raw"], flight["tmp"] / "again.mcap", flight["fox"])
    assert direct["foxglove"] > n_states


def test_foxglove_from_bad_input_is_one_line(tmp_path, capsys):
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello")
    assert record_cli(["--foxglove-from", str(not_mcap), "-o", str(tmp_path / "o.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert "is not an MCAP file" in err and "\n" not in err and "Traceback" not in err
    assert (
        record_cli(
            ["--foxglove-from", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "o.mcap")]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "no recording at" in err and "\n" not in err


def test_bridge_cli_refuses_bad_ports(capsys):
    from covey_cli import main

    with pytest.raises(SystemExit) as exc:
        main(["foxglove", "--port", "70000"])
    assert exc.value.code == 2 and "outside 0..65535" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["foxglove", "--origin", "1,2"])
    assert exc.value.code == 2 and "LAT,LON,ALT" in capsys.readouterr().err


@pytest.mark.e2e
def test_a_client_subscribed_before_the_first_command_gets_it():
    """The fleet's channels are advertised when the bridge starts (issue 39 #11): before, /commands,
    /acks and /events appeared only with their first message, so a client that subscribed
    earlier had nothing to subscribe to ("Unknown channel ID") and missed the first command."""
    fleet = "fox" + uuid.uuid4().hex[:8]
    port = free_tcp_port()
    with Mesh(embedded_router(port, fleet=fleet)) as mesh:
        peer = embedded_peer(port, fleet=fleet)
        with (
            FoxgloveBridge(BridgeConfig(mesh=peer, port=0)) as bridge,
            connect(f"ws://127.0.0.1:{bridge.port}", subprotocols=SUBPROTOCOLS) as ws,
        ):
            topics: dict[str, int] = {}
            end = time.monotonic() + 5.0
            while not {fc.COMMANDS_TOPIC, fc.ACKS_TOPIC, fc.EVENTS_TOPIC} <= set(topics):
                assert time.monotonic() < end, f"only {sorted(topics)} advertised before traffic"
                try:
                    msg = json.loads(ws.recv(timeout=0.5))
                except TimeoutError:
                    continue
                if msg.get("op") == "advertise":
                    topics.update({ch["topic"]: ch["id"] for ch in msg["channels"]})
            assert {t for t, _ in fc.FLEET_CHANNELS} <= set(topics)
            sub = {"id": 1, "channelId": topics[fc.COMMANDS_TOPIC]}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [sub]}))
            time.sleep(1.0)  # the bridge's Zenoh peer finds the router
            nonce = new_nonce()
            cmd = schema.Command.takeoff(4.0, nonce=nonce, stamp_ns=time.time_ns(), targets=(5,))
            got = None
            end = time.monotonic() + 15.0
            while got is None and time.monotonic() < end:
                mesh.send_command(cmd, timeout_s=0.5)  # nobody answers; the bridge records it
                try:
                    while got is None:
                        frame = ws.recv(timeout=0.5)
                        if isinstance(frame, bytes) and frame[0] == 0x01:
                            assert struct.unpack_from("<I", frame, 1)[0] == 1
                            got = json.loads(frame[13:])
                except TimeoutError:
                    continue
            assert got is not None, "the first command never reached the early subscriber"
            assert got["nonce"] == nonce and got["kind"] == "TAKEOFF" and got["targets"] == [5]
