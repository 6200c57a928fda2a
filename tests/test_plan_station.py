"""The fleet plan in the browser station, server side: the scene draws the fence, the keep-out
zones (concave ones filled inside their outline only) and the rally points with their names; a
keyed station draws the plan a member pushes, and an uploaded file is checked, signed with the
station's key and reaches a vehicle's follower over Zenoh."""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely
import viser

from comms.mesh import Mesh
from comms.plan_sync import PlanSync
from comms.schema import Role
from comms.session import MeshConfig, free_tcp_port
from groundstation.scene import FleetScene, SceneConfig
from groundstation.station import GcsConfig, GroundStation
from tests.conftest import wait_until
from tests.test_plan_files import ORIGIN, geojson
from tests.test_plan_wire import HANGAR, sample_plan
from trust.auth import load_auth
from trust.authority import throwaway_fleet

FLEET = "planstation"


@pytest.fixture
def server():
    srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    srv.stop()


def names(server) -> set[str]:
    return set(server.scene._handle_from_node_name)


def test_the_scene_draws_fence_zones_and_rally_points(server) -> None:
    scene = FleetScene(server, SceneConfig(geofence_radius_m=50.0))
    circle = server.scene.get_handle_by_name("/geofence")
    assert circle.visible
    scene.update_plan(sample_plan())
    drawn = names(server)
    for name in ("/plan/fence", "/plan/fence/label", "/plan/zones/0/fill", "/plan/zones/1/edge",
                 "/plan/zones/1/label", "/plan/rally/0", "/plan/rally/1/label"):  # fmt: skip
        assert name in drawn, name
    assert server.scene.get_handle_by_name("/plan/zones/0/label").text == "keep out: school"
    assert server.scene.get_handle_by_name("/plan/zones/1/label").text == (
        "keep out: hangar (to 30 m)"
    )
    assert server.scene.get_handle_by_name("/plan/rally/1/label").text == "north field"
    assert not circle.visible  # the plan's fence replaces the circle
    # The U-shaped hangar is filled inside its outline only (scene x = east, y = north).
    fill = server.scene.get_handle_by_name("/plan/zones/1/fill")
    tris = np.asarray(fill.vertices)[np.asarray(fill.faces)]
    hangar = shapely.Polygon(HANGAR)
    for tri in tris:
        c = tri.mean(axis=0)
        assert hangar.contains(shapely.Point(c[1], c[0])), c
    area = sum(shapely.Polygon(t[:, [1, 0]]).area for t in tris)
    assert area == pytest.approx(hangar.area, rel=1e-4)
    # The zone's name sits inside the U, not in its notch.
    label = server.scene.get_handle_by_name("/plan/zones/1/label").position
    assert hangar.contains(shapely.Point(label[1], label[0]))
    scene.update_plan(None)
    assert not any(n.startswith("/plan") for n in names(server)) and circle.visible


def test_a_keyed_station_draws_a_pushed_plan_and_pushes_an_upload(tmp_path) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1])
    vehicle = load_auth(str(authority.member_path(Role.VEHICLE, 1)))
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    gcs_cfg = GcsConfig(
        mesh=MeshConfig(fleet=FLEET, mode="peer", connect=(), listen=(ep,)),
        port=0,
        key_file=str(authority.member_path(Role.STATION, 1)),
        origin=ORIGIN,
    )
    with (
        GroundStation(gcs_cfg) as gcs,
        Mesh(MeshConfig(fleet=FLEET, mode="peer", connect=(ep,)), auth=vehicle) as v,
        PlanSync(v.session, FLEET, vehicle) as follower,
    ):
        view = gcs.plan_view
        assert "no fleet plan" in view.html.content
        station_auth = gcs.mesh.auth
        assert wait_until(lambda: follower.counts().get("pulls", 0) >= 1, 5)
        follower.push(station_auth.sign_plan(sample_plan(2, fleet=FLEET)))
        assert wait_until(lambda: view.drawn is not None, 10)
        assert "keep out: school" in view.html.content and "/plan/zones/0/fill" in names(gcs.server)
        # An upload: checked, signed by station 1, applied here and at the vehicle.
        line = view.load(json.dumps(geojson()).encode(), "field.geojson", "alice")
        assert line.startswith("plan v") and "pushed by alice" in line, line
        assert wait_until(lambda: follower.plan.version > 2, 5)
        assert follower.plan.signer_id == 1 and follower.plan.fence.ceiling_alt_m == 120
        assert wait_until(lambda: view.drawn.version == follower.plan.version, 10)
        bad = view.load(b"{not json", "oops.geojson")
        assert bad.startswith("refused: uploaded 'oops.geojson' is not JSON")


def test_foxglove_shows_the_plan_as_one_scene_entity() -> None:
    from comms.schema import PlanMessage
    from recording import foxglove_channels as fc
    from tests.test_foxglove import proto_class

    (out,) = fc.Converter().convert(
        f"covey/{FLEET}/plan", PlanMessage(sample_plan(3, fleet=FLEET)).encode(), 5
    )
    scene = proto_class("foxglove.SceneUpdate", fc.SCENE_UPDATE.data).FromString(out.data)
    (entity,) = scene.entities
    assert entity.id == "plan" and entity.frame_id == fc.NED_FRAME
    assert [len(line.points) for line in entity.lines] == [4, 4, 8]  # fence, school, hangar
    assert [t.text for t in entity.texts] == ["keep out: school", "keep out: hangar"]
