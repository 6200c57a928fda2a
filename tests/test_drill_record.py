"""Nothing is lost: a recording made during a drill (an agent killed with -9 and restarted,
commands sent) holds every message that reached the recorder's mesh.

An independent observer session counts what the mesh delivered; the recording must hold every
state the observer saw while the recorder was open, every command sent, and both presence edges
of the killed agent. Sent vs recorded per agent comes from the agents' own sequence numbers.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from comms import keys
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import Command, CommandKind, VehicleState, decode
from comms.session import MeshConfig, embedded_peer, embedded_router, free_tcp_port
from recording.record import RecordConfig, Recorder, read_recording

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def agent(procs, port: int, vid: int):
    return procs.start(
        "-m",
        "covey_cli",
        "agent",
        "--id",
        str(vid),
        "--connect",
        f"tcp/127.0.0.1:{port}",
        f"--start-ne-m=0,{4 * vid}",
        "--no-gcs-failsafe",
    )


def test_a_drill_recording_holds_every_message_that_reached_the_recorder(procs, tmp_path) -> None:
    port = free_tcp_port()
    path = tmp_path / "drill.mcap"
    seen: set[tuple[int, int, int]] = set()  # (vehicle, seq, stamp) the observer received
    lock = threading.Lock()

    def on_state(s: VehicleState, _t: int) -> None:
        with lock:
            seen.add((s.vehicle_id, s.seq, s.stamp_ns))

    with Mesh(embedded_router(port)) as hub, Mesh(embedded_peer(port)) as observer:
        presence = hub.presence()
        agents = {vid: agent(procs, port, vid) for vid in (1, 2)}
        assert presence.wait_for(lambda v, _g: v >= {1, 2}, timeout_s=60)
        # As `covey record` joins by default: a client of the router (a peer would hear the
        # restarted agent only once their gossip link is up, and could miss its first state).
        client = MeshConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
        with Recorder(RecordConfig(path=str(path), mesh=client, flush_interval_s=0.1)):
            time.sleep(1.0)  # let the recorder's subscriptions reach every publisher
            observer.subscribe_states(on_state)
            time.sleep(1.0)
            sent_cmds = []
            for kind in (CommandKind.HOLD, CommandKind.LAND):
                cmd = Command(kind, new_nonce(), time.time_ns())
                hub.send_command(cmd, expect=(1, 2), timeout_s=5)
                sent_cmds.append(cmd.encode())
            os.kill(agents[2].pid, signal.SIGKILL)
            assert presence.wait_for(lambda v, _g: 2 not in v, timeout_s=5)
            agents[2] = agent(procs, port, 2)
            assert presence.wait_for(lambda v, _g: 2 in v, timeout_s=60)
            time.sleep(1.5)
            with lock:
                observed = set(seen)
            observer.close()
            time.sleep(0.5)  # the recorder flushes what it already has
        rec = read_recording(path)
    assert not rec.truncated, rec.truncated
    recorded_states: set[tuple[int, int, int]] = set()
    recorded_cmds: list[bytes] = []
    alive_edges: list[tuple[str, bytes]] = []
    for m in rec.messages:
        parsed = keys.parse_vehicle_key(m.topic)
        leaf = parsed[2] if parsed else m.topic.rsplit("/", 1)[-1]
        if leaf == "state":
            s = decode(m.data)
            recorded_states.add((s.vehicle_id, s.seq, s.stamp_ns))
        elif leaf == "cmd":
            recorded_cmds.append(m.data)
        elif leaf == "alive":
            alive_edges.append((m.topic, m.data))
    missing = observed - recorded_states
    for vid in (1, 2):
        mine = sorted(s for v, s, _ in recorded_states if v == vid)
        print(
            f"vehicle {vid}: recorded {len(mine)} states; observer saw {len([o for o in observed if o[0] == vid])}"
        )
    v1 = sorted(s for v, s, _ in recorded_states if v == 1)
    sent_v1 = v1[-1] - v1[0] + 1
    print(
        f"vehicle 1 sent {sent_v1} states while recorded (by seq), recording holds {len(v1)}; "
        f"{len(recorded_cmds)}/{len(sent_cmds)} commands; presence edges {[d for _, d in alive_edges if '/v/2/' in _]}"
    )
    assert not missing, (
        f"{len(missing)} states reached the mesh but not the recording, e.g. {sorted(missing)[:5]}"
    )
    assert len(v1) == sent_v1, "vehicle 1's recorded sequence has holes"
    assert sorted(recorded_cmds) == sorted(sent_cmds)
    v2_edges = [d for t, d in alive_edges if t == keys.alive("covey", 2)]
    assert b"\x00" in v2_edges and v2_edges[-1] == b"\x01", v2_edges  # it went away and came back
