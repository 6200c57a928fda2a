"""The autopilot backstop: the fleet plan's fence and keep-out zones go to PX4 as its own
geofence (MAVSDK's geofence plugin, mission_type FENCE). The emulator's side of the protocol on
its own (upload, download, clear, refusals, reposition targets it then denies), and real MAVSDK
uploading a plan to the emulator in its own process and downloading it back."""

from __future__ import annotations

import random

import pytest
from pymavlink.dialects.v20 import common as mavlink

from agent.backends.mavsdk_backend import MavsdkBackend, MavsdkConfig
from agent.hosts import Agent
from agent.shell_config import AgentConfig
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.plan import FleetPlan
from comms.session import MeshConfig
from firmware.sitl.fence import FENCE, FenceStore
from firmware.sitl.process import SitlProcess, free_udp_port
from tests.conftest import wait_until
from tests.test_plan_wire import SCHOOL, sample_plan

ISOLATED = MeshConfig(mode="peer", connect=(), listen=("tcp/127.0.0.1:0",))

HOME = GeoOrigin(48.7490, 9.1050, 450.0)
GCS = (255, 190)


def item(seq: int, command: int, lat: float, lon: float, p1: float) -> object:
    return mavlink.MAVLink_mission_item_int_message(
        1, 1, seq, mavlink.MAV_FRAME_GLOBAL, command, 0, 1, p1, 0, 0, 0,
        int(round(lat * 1e7)), int(round(lon * 1e7)), 0.0, FENCE,
    )  # fmt: skip


def upload(store: FenceStore, items: list) -> list:
    """Run an upload through the store as MAVSDK would; the replies, in order."""
    out = store.handle(mavlink.MAVLink_mission_count_message(1, 1, len(items), FENCE), 0.0, GCS)
    for it in items:
        out += store.handle(it, 0.1, GCS)
    return out


def square(lat0: float, lon0: float, d: float, command: int, seq0: int = 0) -> list:
    corners = [(lat0, lon0), (lat0, lon0 + d), (lat0 + d, lon0 + d), (lat0 + d, lon0)]
    return [item(seq0 + k, command, lat, lon, 4) for k, (lat, lon) in enumerate(corners)]


INCL = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
EXCL = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION


def test_the_emulator_stores_a_fence_and_denies_targets_it_rules_out() -> None:
    store = FenceStore(1)
    items = square(48.0, 9.0, 0.01, INCL) + square(48.004, 9.004, 0.002, EXCL, 4)
    items.append(item(8, mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, 48.008, 9.002, 50.0))
    replies = upload(store, items)
    assert [r.get_type() for r in replies] == ["MISSION_REQUEST_INT"] * 9 + ["MISSION_ACK"]
    assert replies[-1].type == mavlink.MAV_MISSION_ACCEPTED and len(store.shapes) == 3
    assert store.refusal(48.002, 9.002, 48.0) is None
    assert store.refusal(48.02, 9.002, 48.0) == "outside the geofence"
    assert store.refusal(48.005, 9.005, 48.0) == "inside a geofence exclusion zone"
    assert store.refusal(48.0082, 9.002, 48.0) == "inside a geofence exclusion zone"  # 22 m
    # Download gives back exactly what was stored; clear empties it.
    (count,) = store.handle(mavlink.MAVLink_mission_request_list_message(1, 1, FENCE), 1.0, GCS)
    assert count.count == 9
    got = store.handle(mavlink.MAVLink_mission_request_int_message(1, 1, 5, FENCE), 1.0, GCS)
    assert (got[0].x, got[0].y, got[0].command) == (items[5].x, items[5].y, EXCL)
    (ack,) = store.handle(mavlink.MAVLink_mission_clear_all_message(1, 1, FENCE), 2.0, GCS)
    assert ack.type == mavlink.MAV_MISSION_ACCEPTED and store.refusal(60.0, 9.0, 48.0) is None


def test_bad_fence_uploads_are_refused_never_raised() -> None:
    store = FenceStore(1)
    bad_count = square(48.0, 9.0, 0.01, INCL)[:3]  # says 4 vertices, sends 3
    assert upload(store, bad_count)[-1].type == mavlink.MAV_MISSION_INVALID_PARAM1
    mixed = square(48.0, 9.0, 0.01, INCL)
    mixed[2] = item(2, EXCL, 48.01, 9.01, 4)
    assert upload(store, mixed)[-1].type == mavlink.MAV_MISSION_INVALID_PARAM1
    waypoint = [item(0, mavlink.MAV_CMD_NAV_WAYPOINT, 48.0, 9.0, 0)]
    assert upload(store, waypoint)[-1].type == mavlink.MAV_MISSION_UNSUPPORTED
    assert store.shapes == () and store.uploads == 0
    # A mission or rally transfer: unsupported, said at once (MAVSDK does not wait it out).
    (ack,) = store.handle(mavlink.MAVLink_mission_count_message(1, 1, 3, 0), 0.0, GCS)
    assert ack.type == mavlink.MAV_MISSION_UNSUPPORTED
    # Random items, out of order, repeated, with garbage fields: answered, never raised.
    rng = random.Random(3)
    for _ in range(300):
        n = rng.randint(0, 12)
        store.handle(mavlink.MAVLink_mission_count_message(1, 1, n, FENCE), 0.0, GCS)
        for _ in range(rng.randint(0, 14)):
            it = item(rng.randint(0, 13), rng.choice([INCL, EXCL, 5003, 5004, 5000, 16]),
                      rng.uniform(-90, 90), rng.uniform(-180, 180), rng.choice([0, 3, 4, -1, 1e9]))  # fmt: skip
            store.handle(it, 0.1, GCS)


def test_the_emulator_denies_a_reposition_into_an_exclusion_zone() -> None:
    from firmware.sitl.config import SitlConfig
    from firmware.sitl.emulator import Emulator

    port = free_udp_port()
    with Emulator(SitlConfig(home=HOME, links=(f"udpout:127.0.0.1:{port}",))) as emu:
        ap = emu.autopilot
        lat0, lon0, _ = HOME.to_global(-100.0, -100.0, 0.0)
        lat1, lon1, _ = HOME.to_global(100.0, 100.0, 0.0)
        d_lat, d_lon = lat1 - lat0, lon1 - lon0
        ring = [
            (lat0, lon0),
            (lat0, lon0 + d_lon),
            (lat0 + d_lat, lon0 + d_lon),
            (lat0 + d_lat, lon0),
        ]
        items = [item(k, EXCL, lat, lon, 4) for k, (lat, lon) in enumerate(ring)]
        assert upload(ap.fence, items)[-1].type == mavlink.MAV_MISSION_ACCEPTED
        lat, lon, alt = HOME.to_global(10.0, 10.0, -5.0)
        cmd = mavlink.MAVLink_command_int_message(
            1, 1, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_DO_REPOSITION, 0, 0,
            -1, 0, 0, 0, int(lat * 1e7), int(lon * 1e7), alt,
        )  # fmt: skip
        (ack,) = [r for r in ap.handle(cmd, 1.0) if r.get_type() == "COMMAND_ACK"]
        assert ack.result == mavlink.MAV_RESULT_DENIED
        assert any("inside a geofence exclusion zone" in e for e in emu.vehicle.events)


@pytest.mark.e2e
def test_mavsdk_uploads_the_plan_to_the_emulator_and_reads_it_back() -> None:
    port = free_udp_port()
    home = f"{HOME.lat_deg},{HOME.lon_deg},{HOME.alt_m}"
    cfg = MavsdkConfig(connection=f"udpin://127.0.0.1:{port}", action_timeout_s=10.0)
    plan = sample_plan(7, fleet=ISOLATED.fleet)
    with (
        SitlProcess(["--id", "1", "--connect", f"udpout:127.0.0.1:{port}", "--home", home]),
        MavsdkBackend(cfg, HOME) as vb,
    ):
        assert vb.wait_connected()
        # A real agent around the backend uploads the plan it is given (off the Zenoh thread).
        events = []
        with Mesh(ISOLATED) as mesh:
            cfg_a = AgentConfig(vehicle_id=1, mesh=ISOLATED, origin=HOME)
            with Agent(cfg_a, vb, mesh) as agent:
                publish = agent._event
                agent._event = lambda text, *a, **k: (events.append(text), publish(text, *a, **k))
                agent.plan.push(plan)
                assert wait_until(lambda: any("autopilot geofence" in e for e in events), 20)
        assert "autopilot geofence set from fleet plan v7" in events, events
        geofence = vb._plugin("geofence")
        data = vb._call("download geofence", geofence.download_geofence)
        assert [p.fence_type.name for p in data.polygons] == ["INCLUSION", "EXCLUSION", "EXCLUSION"]
        school = data.polygons[1].points
        for pt, (n, e) in zip(school, SCHOOL, strict=True):
            lat, lon, _ = HOME.to_global(n, e, 0.0)
            assert pt.latitude_deg == pytest.approx(lat, abs=2e-7)
            assert pt.longitude_deg == pytest.approx(lon, abs=2e-7)
        # A plan with no fence and no zones clears the autopilot's.
        vb.upload_fence(FleetPlan(plan.fleet, 8, 0))
        assert vb._call("download geofence", geofence.download_geofence).polygons == []
