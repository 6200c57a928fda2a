"""`covey record` as a terminal runs it: Ctrl-C reaches the whole process group (the recorder and
its Foxglove worker), and the recorder, a client of its router by default, waits for a router
that is not up yet, says so, and gives up on Ctrl-C."""

from __future__ import annotations

import signal
import threading
import time

import pytest
from mcap.reader import make_reader

from comms.mesh import Mesh
from comms.schema import VehicleState
from comms.session import MeshConfig, MeshConfigError, embedded_router, free_tcp_port, open_session
from recording.record import read_recording

pytestmark = pytest.mark.e2e


def test_ctrl_c_to_the_process_group_ends_a_recording_whole(procs, tmp_path) -> None:
    port = free_tcp_port()
    path = tmp_path / "flight.mcap"
    with Mesh(embedded_router(port)) as hub:
        rec = procs.start(
            "-m", "covey_cli", "record", "-o", path, "--connect", f"tcp/127.0.0.1:{port}"
        )
        rec.wait_for("recording fleet", timeout_s=30)
        for seq in range(1, 200):  # until the recorder has the states (it joins after the line)
            s = VehicleState(4, seq, time.time_ns(), (0.0, 0.0, -2.0), (0.0, 0.0, 0.0), 0.0)
            hub.publish_state(s)
            time.sleep(0.05)
            if seq > 40 and path.stat().st_size > 2000:
                break
        rec.signal(signal.SIGINT)  # the terminal's Ctrl-C: to the foreground group
        assert rec.wait(30) == 0, rec.lines()[-5:]
    out = "\n".join(rec.lines())
    assert "wrote " in out and "stopped early" not in out, out[-800:]
    topics = {m.topic for m in read_recording(path).messages}
    assert any(t.endswith("/4/state") for t in topics), sorted(topics)
    with open(path, "rb") as f:  # the worker's standard channels are there: it was not killed
        standard = {ch.topic for _s, ch, _m in make_reader(f).iter_messages()}
    assert "/vehicles/4/pose" in standard, sorted(standard)


def test_a_client_waits_for_its_router_says_so_and_gives_up_when_stopped(caplog) -> None:
    port = free_tcp_port()  # nothing listens there
    client = MeshConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
    stop = threading.Event()
    threading.Timer(1.0, stop.set).start()
    with caplog.at_level("WARNING", logger="comms.session"):
        t0 = time.monotonic()
        with pytest.raises(MeshConfigError, match="no router answered at tcp/"):
            open_session(client, stop, note_every_s=0.3)
    assert time.monotonic() - t0 < 10.0
    assert f"waiting for a router at tcp/127.0.0.1:{port}" in caplog.text


def test_a_client_opens_once_its_router_comes_up() -> None:
    port = free_tcp_port()
    client = MeshConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
    out: list = []
    opener = threading.Thread(target=lambda: out.append(open_session(client)), daemon=True)
    opener.start()
    time.sleep(1.0)
    assert opener.is_alive() and not out  # no router yet
    with Mesh(embedded_router(port)):
        opener.join(30)
        assert out, "the client never opened"
        out[0].close()
