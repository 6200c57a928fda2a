"""Several ground stations on one real fleet (`covey demo` with 2 agents, real Zenoh): one command
log for all, "superseded" when another station replaces a command, and a station that cannot
serve its web app never joins the mesh."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest
from conftest import views_by_id, wait_until

from comms.schema import AckResult, CommandKind, Mode
from comms.session import MeshConfig
from groundstation.demo_proc import DemoProcess
from groundstation.inputs import CommandRequest
from groundstation.station import GcsConfig, GroundStation

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def demo():
    # Open mode: two stations need two station keys; signing is covered by test_trust_keyed.py.
    with DemoProcess(["--vehicles", "2", "--port", "0", "--open-mode"]) as proc:
        yield proc


def station(demo, gcs_id: int) -> GroundStation:
    return GroundStation(
        GcsConfig(
            mesh=MeshConfig(mode="peer", connect=(demo.mesh_endpoint,)), port=0, gcs_id=gcs_id
        )
    )


def send(gcs: GroundStation, req: CommandRequest, targets: tuple[int, ...]):
    done, got = threading.Event(), []
    gcs.dispatch("test", [(req, targets)], lambda d: (got.append(d), done.set()), None)
    assert done.wait(10.0), "the station's worker never finished the command"
    (result,) = got[0].results
    assert result.ok, result.summary()
    return result.command


def entry(gcs: GroundStation, nonce: int):
    return next((e for e in gcs.commands.entries() if e.command.nonce == nonce), None)


def test_every_station_logs_every_command_and_shows_superseded(demo):
    with station(demo, 2) as a, station(demo, 3) as b:
        assert wait_until(
            lambda: a.presence.vehicles >= {1, 2} and b.presence.vehicles >= {1, 2}, 20
        )
        send(a, CommandRequest(CommandKind.TAKEOFF, (4.0, 0.0, 0.0)), (1, 2))
        assert wait_until(lambda: views_by_id(a.fleet.snapshot(time.time_ns()))[1].alt_m > 2.0, 30)
        goto_a = send(a, CommandRequest(CommandKind.GOTO_LOCAL, (6.0, 0.0, -4.0)), (1,))
        # Station B sees A's goto, sent by station 2, with vehicle 1's answer.
        assert wait_until(lambda: (e := entry(b, goto_a.nonce)) is not None and 1 in e.answers, 10)
        seen = entry(b, goto_a.nonce)
        assert seen.source_id == 2 and seen.answers[1].result is AckResult.ACCEPTED
        assert wait_until(lambda: 'data-station="2"' in b.command_log_html.content, 5)
        # B overrides it: A's log marks its goto superseded on vehicle 1 (and only there).
        goto_b = send(b, CommandRequest(CommandKind.GOTO_LOCAL, (-6.0, 0.0, -4.0)), (1,))
        assert wait_until(lambda: 1 in entry(a, goto_a.nonce).superseded, 10)
        assert entry(a, goto_a.nonce).superseded == {1: entry(a, goto_b.nonce).seq}
        assert wait_until(lambda: 'data-answer="superseded"' in a.command_log_html.content, 5)
        send(a, CommandRequest(CommandKind.LAND), (1, 2))
        assert wait_until(
            lambda: all(v.mode is Mode.LANDED for v in a.fleet.snapshot(time.time_ns()).vehicles),
            60,
        )


def test_a_station_that_cannot_serve_exits_2_in_one_line_and_never_joins(demo):
    with station(demo, 4) as watcher:
        assert wait_until(lambda: 4 in watcher.presence.ground_stations, 10)
        before = set(watcher.presence.ground_stations)
        bad = subprocess.run(
            [
                sys.executable,
                "-m",
                "covey_cli",
                "gcs",
                "--host",
                "999.1.1.1",
                "--gcs-id",
                "9",
                "--connect",
                demo.mesh_endpoint,
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert bad.returncode == 2
        assert len(bad.stderr.strip().splitlines()) == 1 and "999.1.1.1" in bad.stderr
        time.sleep(1.0)
        assert 9 not in watcher.presence.ground_stations
        assert set(watcher.presence.ground_stations) == before


def test_a_station_hears_the_feed_and_every_state_only_when_asked(demo):
    peer = MeshConfig(mode="peer", connect=(demo.mesh_endpoint,))
    with (
        GroundStation(GcsConfig(mesh=peer, port=0, gcs_id=4)) as fed,
        GroundStation(GcsConfig(mesh=peer, port=0, gcs_id=5, every_state=True)) as every,
    ):
        for gcs in (fed, every):
            assert wait_until(lambda g=gcs: set(g.fleet.positions()) >= {1, 2}, 20)
        window_s, n0 = 3.0, fed.mesh.stats.feed_batches_received
        time.sleep(window_s)
        batches_s = (fed.mesh.stats.feed_batches_received - n0) / window_s
        # Two one-vehicle agents, each at most feed_hz / 0.9 batches a second (comms/feed.py),
        # counted where they arrive (a batch up to 1 s late on a loaded machine may add).
        assert 0 < batches_s <= 2 * peer.feed_hz / 0.9 * (window_s + 1.0) / window_s, batches_s
        assert every.mesh.stats.feed_batches_received == 0 and every.mesh.stats.states_received
        for gcs in (fed, every):

            def fresh(g=gcs) -> bool:
                views = views_by_id(g.fleet.snapshot(time.time_ns(), trails=False))
                return not views[1].stale and not views[2].stale

            assert wait_until(fresh, 10)
            assert views_by_id(gcs.fleet.snapshot(time.time_ns()))[1].loss_pct == 0.0
