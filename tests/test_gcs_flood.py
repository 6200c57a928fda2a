"""A ground station under a phantom flood (real agents, real rogue processes, real Zenoh): its
fleet table stays bounded and empties of phantoms within the documented expiry, a real mode
change during the flood reaches the events panel, and the real agents keep their 10 Hz. The
phantoms come both on state keys (the agents' and the hub's path) and in feed batches (the
station's path, comms/feed.py)."""

from __future__ import annotations

import time

import pytest

from bench.flood_jitter import FEED_FLOOD_ENTRIES, Samples, start_agents, start_flooder
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import Command, EventKind
from comms.session import MeshConfig, embedded_router, free_tcp_port
from groundstation.station import GcsConfig, GroundStation

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

FLOOD_S = 8.0


def test_a_phantom_flood_leaves_only_real_vehicles_and_events_get_through() -> None:
    port = free_tcp_port()
    agents = []
    try:
        with Mesh(embedded_router(port)) as hub:
            samples = Samples()
            hub.subscribe_states(samples.on_state)
            presence = hub.presence()
            agents = start_agents(port)
            assert presence.wait_for(lambda v, _g: v >= {1, 2}, timeout_s=60)
            cfg = GcsConfig(
                mesh=MeshConfig(mode="peer", connect=(f"tcp/127.0.0.1:{port}",)), port=0
            )
            with GroundStation(cfg) as gcs:
                rogue = start_flooder(port, 3000, FLOOD_S, mix="phantom")
                feeder = start_flooder(port, 3000 / FEED_FLOOD_ENTRIES, FLOOD_S, mix="feed")
                deadline = time.monotonic() + 30
                while len(gcs.fleet.ids()) < 100 and time.monotonic() < deadline:
                    time.sleep(0.1)
                assert len(gcs.fleet.ids()) >= 100, "the flood never reached the station"
                samples.clear()
                t0 = time.monotonic()
                # A real mode change during the flood.
                res = hub.send_command(
                    Command.takeoff(3.0, nonce=new_nonce(), stamp_ns=0), expect=(1,)
                )
                assert res.ok, res.summary()
                while time.monotonic() - t0 < 3.0:
                    time.sleep(0.1)
                shown = [ev for _, ev in gcs.events.latest()]  # what an "all kinds" panel shows
                assert any(
                    ev.kind is EventKind.MODE_CHANGE and ev.vehicle_id == 1 for ev in shown
                ), shown
                with samples.lock:
                    rows = {v: sorted(r) for v, r in samples.by_vehicle.items()}
                for v in (1, 2):  # the agent's own publishing rate, and how much of it arrived
                    (s0, t0_ns, _), (s1, t1_ns, _) = rows[v][0], rows[v][-1]
                    rate_hz = (s1 - s0) / ((t1_ns - t0_ns) / 1e9)
                    arrived = len(rows[v]) / (s1 - s0 + 1)
                    print(f"vehicle {v} during the flood: {rate_hz:.2f} Hz, {arrived:.1%} arrived")
                    assert rate_hz >= 9.5 and arrived >= 0.95, (v, rate_hz, arrived)
                assert len(gcs.fleet.ids()) <= gcs.fleet.cfg.max_vehicles
                rogue.wait_output(timeout_s=60)
                feeder.wait_output(timeout_s=60)
                # Within the expiry time after the flood only the real vehicles are listed.
                expire_s = gcs.fleet.cfg.unconfirmed_expire_s
                end = time.monotonic() + expire_s + 5.0
                while set(gcs.fleet.ids()) != {1, 2} and time.monotonic() < end:
                    time.sleep(0.2)
                assert set(gcs.fleet.ids()) == {1, 2}, f"{len(gcs.fleet.ids())} vehicles listed"
                assert gcs.fleet.expired >= 100
    finally:
        for a in agents:
            a.kill()
            a.wait(timeout=10)
