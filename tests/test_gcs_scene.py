"""The scene layer against a real viser server (no browser): paths, frames, alerts, lost vehicles."""

from __future__ import annotations

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


def color_of(scene: FleetScene, layer: str, vid: int) -> tuple[int, ...]:
    return tuple(int(c) for c in scene.nodes[layer].batched_colors[scene.ids.index(vid)])


def node_names(server) -> set[str]:
    return set(server.scene._handle_from_node_name)  # every node the server holds


def test_vehicles_are_drawn_in_batched_nodes_in_the_scene_frame(server):
    model = FleetModel()
    put(
        model,
        3,
        1,
        (10.0, -4.0, -6.0),
        0.0,
        mode=Mode.GOTO,
        flags=StateFlag.HAS_GOAL,
        goal_ned_m=(20.0, 0.0, -6.0),
        vel=(1.0, 0.0, 0.0),
    )
    scene = FleetScene(server, SceneConfig())
    with server.atomic():
        scene.update(model.snapshot(0), send_trails=True)
    for layer in ("bodies", "rings", "goals", "velocity", "stalks", "trails"):
        assert server.scene.get_handle_by_name(f"/fleet/{layer}") is not None, layer
    assert server.scene.get_handle_by_name("/labels/3") is not None
    assert scene.ids == (3,)
    bodies = scene.nodes["bodies"]
    assert bodies.batched_positions[0] == pytest.approx((-4.0, 10.0, 6.0))  # ENU: east, north, up
    assert color_of(scene, "bodies", 3) == mode_rgb(Mode.GOTO)
    goals = scene.nodes["goals"]
    assert (
        goals.batched_positions[0] == pytest.approx((0.0, 20.0, 6.0))
        and goals.batched_scales[0] == 1.0
    )
    assert scene.labels[3].text == "3 GOTO 6.0m 100%"
    start, tip = scene.nodes["velocity"].points[0]
    assert tip - start == pytest.approx((0.0, 1.0, 0.0))  # north = scene +y
    assert scene.nodes["stalks"].points[0][1] == pytest.approx(
        (-4.0, 10.0, 0.0)
    )  # down to the ground


def test_rings_turn_red_when_closer_than_separation_and_lost_vehicles_grey(server):
    model = FleetModel()
    put(model, 1, 1, (0.0, 0.0, -5.0), 0.0, mode=Mode.HOLDING)
    put(model, 2, 1, (0.0, 2.5, -5.0), 0.0, mode=Mode.HOLDING)
    put(
        model,
        3,
        1,
        (0.0, 9.0, -5.0),
        0.0,
        mode=Mode.HOLDING,
        flags=StateFlag.HAS_GOAL,
        goal_ned_m=(5.0, 9.0, -5.0),
    )
    scene = FleetScene(server, SceneConfig(separation_m=3.0))
    scene.update(model.snapshot(0))
    assert [color_of(scene, "rings", v) for v in (1, 2, 3)] == [ALERT_RGB, ALERT_RGB, RING_OK_RGB]
    assert color_of(scene, "bodies", 3) == mode_rgb(Mode.HOLDING)
    assert list(scene.nodes["goals"].batched_scales) == [
        0.0,
        0.0,
        1.0,
    ]  # goal shown only with a goal
    put(model, 2, 2, (0.0, 4.0, -5.0), 0.1, mode=Mode.HOLDING)
    model.on_presence(3, False, 0)
    scene.update(model.snapshot(int(0.1 * NS_PER_S)))
    assert [color_of(scene, "rings", v) for v in (1, 2, 3)] == [RING_OK_RGB] * 3
    assert color_of(scene, "bodies", 3) == LOST_RGB
    assert scene.nodes["goals"].batched_scales[2] == 0.0  # a lost vehicle's goal is not shown
    assert scene.labels[3].text.startswith("3 LOST")


class Recorder:
    """Stands in for a scene node: records which properties are assigned, then assigns them."""

    def __init__(self, node, log: list[str]) -> None:
        object.__setattr__(self, "_node", node)
        object.__setattr__(self, "_log", log)

    def __setattr__(self, name: str, value) -> None:
        self._log.append(name)
        setattr(self._node, name, value)

    def __getattr__(self, name: str):
        return getattr(self._node, name)


def test_a_hovering_vehicle_sends_nothing_new(server):
    model = FleetModel()
    put(model, 1, 1, (1.0, 1.0, -5.0), 0.0, mode=Mode.HOLDING)
    scene = FleetScene(server, SceneConfig())
    scene.update(model.snapshot(0))
    assigned: list[str] = []
    scene.nodes = {layer: Recorder(node, assigned) for layer, node in scene.nodes.items()}
    put(model, 1, 2, (1.001, 1.001, -5.001), 0.1, mode=Mode.HOLDING)  # sub-centimetre jitter
    scene.update(model.snapshot(int(0.1 * NS_PER_S), trails=False))
    assert assigned == []
    put(model, 1, 3, (1.5, 1.0, -5.0), 0.2, mode=Mode.HOLDING)  # a visible move is sent
    scene.update(model.snapshot(int(0.2 * NS_PER_S), trails=False))
    assert "batched_positions" in assigned and "batched_colors" not in assigned


def test_trails_are_read_round_robin_and_drawn_once_all_are_fresh(server):
    model = FleetModel()
    for vid in range(1, 26):
        put(model, vid, 1, (float(vid) * 5, 0.0, -5.0), 0.0, mode=Mode.GOTO)
        put(model, vid, 2, (float(vid) * 5 + 1.0, 0.0, -5.0), 1.0, mode=Mode.GOTO)
    scene = FleetScene(server, SceneConfig(trail_spread_updates=10, trail_max_points=60))
    slices = [scene.trail_ids(model.ids()) for _ in range(10)]
    assert set().union(*slices) == set(range(1, 26))  # every vehicle once per 10 updates
    assert max(len(s) for s in slices) == 3 and sum(len(s) for s in slices) == 25
    snap = model.snapshot(NS_PER_S, trails=slices[0])
    assert {v.vehicle_id for v in snap.vehicles if len(v.trail_ned_m)} == slices[0]
    scene.update(snap)  # the first update draws what it has
    first = scene.sent["trails.points"]
    for ids in slices[1:-1]:
        scene.update(model.snapshot(NS_PER_S, trails=ids))
        assert scene.sent["trails.points"] == first  # not re-sent until every trail is fresh
    scene.update(model.snapshot(NS_PER_S, trails=slices[-1]))
    assert scene.sent["trails.points"] != first
    dots = scene.nodes["trails"].points.reshape(25, 60, 3)
    # Vehicle 1 flew 1 m north (scene +y): its trail is that leg, padded with its latest point.
    assert dots[0, :3].ravel() == pytest.approx([0, 5, 5, 0, 6, 5, 0, 6, 5])
    colors = scene.nodes["trails"].colors.reshape(25, 60, 3)
    assert tuple(colors[0, 0]) == mode_rgb(Mode.GOTO)


def test_vehicles_that_disappear_are_removed(server):
    model = FleetModel()
    for vid in (1, 2, 3):
        put(model, vid, 1, (float(vid) * 5, 0.0, -5.0), 0.0, mode=Mode.HOLDING)
    scene = FleetScene(server, SceneConfig())
    scene.update(model.snapshot(0))
    model2 = FleetModel()
    for vid in (1, 3):
        put(model2, vid, 1, (float(vid) * 5, 0.0, -5.0), 0.0, mode=Mode.HOLDING)
    scene.update(model2.snapshot(0))
    assert scene.ids == (1, 3) and len(scene.nodes["bodies"].batched_positions) == 2
    assert "/labels/2" not in node_names(server) and set(scene.labels) == {1, 3}


def test_the_number_of_scene_nodes_does_not_grow_with_the_fleet():
    counts = []
    for n in (5, 50):
        model = FleetModel()
        for vid in range(1, n + 1):
            put(
                model,
                vid,
                1,
                (float(vid) * 5, 0.0, -5.0),
                0.0,
                mode=Mode.HOLDING,
                flags=StateFlag.HAS_GOAL,
                goal_ned_m=(0.0, 0.0, -5.0),
            )
        srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        try:
            scene = FleetScene(srv, SceneConfig(labels_all_max_vehicles=0))
            scene.update(model.snapshot(0))
            assert len(scene.ids) == n
            counts.append(len(node_names(srv)))
        finally:
            srv.stop()
    assert counts[0] == counts[1]


def test_labels_are_limited_to_vehicles_that_need_attention_in_a_large_fleet(server):
    model = FleetModel()
    for vid in range(1, 31):
        put(model, vid, 1, (float(vid) * 5, 0.0, -5.0), 0.0, mode=Mode.HOLDING)
    put(model, 31, 1, (151.0, 0.0, -5.0), 0.0, mode=Mode.HOLDING)  # 1 m from vehicle 30
    model.on_presence(7, False, 0)
    scene = FleetScene(server, SceneConfig(labels_all_max_vehicles=20))
    scene.update(model.snapshot(0))
    assert set(scene.labels) == {7, 30, 31}
