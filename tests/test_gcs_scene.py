"""The scene layer against a real viser server (no browser): paths, frames, alerts, lost vehicles."""

from __future__ import annotations

import numpy as np
import pytest
import viser

from comms.schema import Mode, StateFlag, VehicleState
from groundstation.fleet import NS_PER_S, FleetModel
from groundstation.palette import ALERT_RGB, LOST_RGB, RING_OK_RGB, mode_rgb
from groundstation.scene import FleetScene, SceneConfig


@pytest.fixture
def server():
    srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    srv.stop()


def put(model: FleetModel, vid: int, seq: int, pos, t_s: float, **kw) -> None:
    model.on_presence(vid, True, 0)
    model.on_state(
        VehicleState(vid, seq, seq, pos, kw.pop("vel", (0.0, 0.0, 0.0)), 0.0, **kw),
        int(t_s * NS_PER_S),
    )


def test_vehicles_are_drawn_under_their_paths_in_the_scene_frame(server):
    model = FleetModel()
    put(model, 3, 1, (10.0, -4.0, -6.0), 0.0, mode=Mode.GOTO, flags=StateFlag.HAS_GOAL, goal_ned_m=(20.0, 0.0, -6.0),
        vel=(1.0, 0.0, 0.0))  # fmt: skip
    scene = FleetScene(server, SceneConfig())
    with server.atomic():
        scene.update(model.snapshot(0), send_trails=True)
    for path in (
        "/vehicles/3",
        "/vehicles/3/body",
        "/vehicles/3/label",
        "/vehicles/3/ring",
        "/goals/3",
        "/trails/3",
    ):
        assert server.scene.get_handle_by_name(path) is not None, path
    h = scene._vehicles[3]
    assert h.frame.position == pytest.approx((-4.0, 10.0, 6.0))  # ENU: east, north, up
    assert h.goal.position == pytest.approx((0.0, 20.0, 6.0)) and h.goal.visible
    assert tuple(h.body.color) == mode_rgb(Mode.GOTO)
    assert h.label.text == "3 GOTO 6.0m 100%"
    assert np.asarray(h.velocity.points)[0, 1] == pytest.approx((0.0, 1.0, 0.0))  # north = scene +y


def test_rings_turn_red_when_closer_than_separation_and_lost_vehicles_grey(server):
    model = FleetModel()
    put(model, 1, 1, (0.0, 0.0, -5.0), 0.0, mode=Mode.HOLDING)
    put(model, 2, 1, (0.0, 2.5, -5.0), 0.0, mode=Mode.HOLDING)
    put(model, 3, 1, (0.0, 9.0, -5.0), 0.0, mode=Mode.HOLDING)
    scene = FleetScene(server, SceneConfig(separation_m=3.0))
    scene.update(model.snapshot(0))
    assert [scene._vehicles[v].cache["ring"] for v in (1, 2, 3)] == [
        ALERT_RGB,
        ALERT_RGB,
        RING_OK_RGB,
    ]
    put(model, 2, 2, (0.0, 4.0, -5.0), 0.1, mode=Mode.HOLDING)
    model.on_presence(3, False, 0)
    scene.update(model.snapshot(int(0.1 * NS_PER_S)))
    assert [scene._vehicles[v].cache["ring"] for v in (1, 2, 3)] == [RING_OK_RGB] * 3
    assert tuple(scene._vehicles[3].body.color) == LOST_RGB
    assert scene._vehicles[3].label.text.startswith("3 LOST")


def test_a_hovering_vehicle_sends_nothing_new(server):
    model = FleetModel()
    put(model, 1, 1, (1.0, 1.0, -5.0), 0.0, mode=Mode.HOLDING)
    scene = FleetScene(server, SceneConfig())
    scene.update(model.snapshot(0))
    cache = dict(scene._vehicles[1].cache)
    put(model, 1, 2, (1.001, 1.001, -5.001), 0.1, mode=Mode.HOLDING)  # sub-centimetre jitter
    scene.update(model.snapshot(int(0.1 * NS_PER_S)))
    assert scene._vehicles[1].cache == cache


def test_trails_are_re_sent_round_robin_a_slice_per_update(server):
    model = FleetModel()
    for vid in range(1, 26):
        put(model, vid, 1, (float(vid) * 5, 0.0, -5.0), 0.0, mode=Mode.GOTO)
    scene = FleetScene(server, SceneConfig(trail_spread_updates=10))
    slices = [scene.trail_ids(model.ids()) for _ in range(10)]
    assert set().union(*slices) == set(range(1, 26))  # every vehicle once per 10 updates
    assert max(len(s) for s in slices) == 3 and sum(len(s) for s in slices) == 25
    snap = model.snapshot(0, trails=slices[0])
    assert {v.vehicle_id for v in snap.vehicles if len(v.trail_ned_m)} == slices[0]
