"""Missions through real processes: a QGroundControl `.plan` file (6 items and a fence) uploaded
with the real `covey mission` CLI to a `covey fleet-sim` child of 3 simulated vehicles on a real
Zenoh mesh. Every waypoint is reached in order (the vehicles' own events and the progress in
their states), pause holds in place, resume continues the same item, abort holds; refused
missions say why and are not flown."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from conftest import wait_until

from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.plan_io import read_plan_file
from comms.plan_sync import publish_plan
from comms.schema import Event, EventKind, Mode, StateFlag, VehicleState
from comms.session import embedded_router, free_tcp_port
from groundstation.mission_cli import mission_cli

pytestmark = pytest.mark.e2e

FLEET = "ms"
IDS = (1, 2, 3)
ORIGIN = GeoOrigin()
HOME = [ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m]
SPREAD_M = 9.0
WAYPOINTS_NE_M = [(14.0, 0.0), (14.0, 12.0), (2.0, 12.0)]


def _qgc_item(command: int, n_m: float = 0.0, e_m: float = 0.0, alt_m: float = 0.0, p0=0.0):
    lat, lon, _ = ORIGIN.to_global(n_m, e_m, 0.0) if (n_m or e_m) else (0.0, 0.0, 0.0)
    return {
        "type": "SimpleItem",
        "command": command,
        "frame": 3,  # MAV_FRAME_GLOBAL_RELATIVE_ALT: above the planned home
        "params": [p0, 0, 0, None, lat, lon, alt_m],
        "autoContinue": True,
    }


def qgc_plan(fence_m: float = 60.0) -> dict:
    """Six items as QGroundControl writes them: take-off, waypoint, loiter 2 s, waypoint,
    waypoint, land; a square inclusion fence."""
    (a, b, c) = WAYPOINTS_NE_M
    zone = [ORIGIN.to_global(n, e, 0)[:2] for n, e in ((30, -40), (30, -30), (40, -30), (40, -40))]
    corners = [
        ORIGIN.to_global(n, e, 0)[:2]
        for n, e in (
            (-fence_m, -fence_m),
            (-fence_m, fence_m),
            (fence_m, fence_m),
            (fence_m, -fence_m),
        )
    ]
    return {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "QGroundControl",
        "mission": {
            "version": 2,
            "firmwareType": 12,
            "vehicleType": 2,
            "cruiseSpeed": 3,
            "plannedHomePosition": HOME,
            "items": [
                _qgc_item(22, alt_m=6.0),
                _qgc_item(16, *a, 6.0),
                _qgc_item(19, *b, 8.0, p0=2.0),
                _qgc_item(16, *c, 6.0),
                _qgc_item(16, 6.0, 6.0, 6.0),
                _qgc_item(21),
            ],
        },
        "geoFence": {
            "version": 2,
            "circles": [],
            "polygons": [
                {"inclusion": True, "polygon": [list(p) for p in corners], "version": 1},
                {"inclusion": False, "polygon": [list(p) for p in zone], "version": 1},
            ],
        },
        "rallyPoints": {"version": 2, "points": []},
    }


class Watch:
    """Every state and event of the fleet, as this test process hears them."""

    def __init__(self, mesh: Mesh) -> None:
        self.lock = threading.Lock()
        self.latest: dict[int, VehicleState] = {}
        self.items: dict[int, list[int]] = {v: [] for v in IDS}
        self.reached: dict[int, list[int]] = {v: [] for v in IDS}
        self.stepped_aside: set[int] = set()
        """Vehicles that published a state with FILTER_ACTIVE (the filter moved them for a
        neighbour) since `clear_stepped`."""
        mesh.subscribe_states(self.on_state)
        mesh.subscribe_events(self.on_event)

    def on_state(self, s: VehicleState, _t: int) -> None:
        with self.lock:
            self.latest[s.vehicle_id] = s
            seq = self.items.setdefault(s.vehicle_id, [])
            if not seq or seq[-1] != s.mission_item:
                seq.append(s.mission_item)
            if s.flags & StateFlag.FILTER_ACTIVE:
                self.stepped_aside.add(s.vehicle_id)

    def clear_stepped(self) -> None:
        with self.lock:
            self.stepped_aside.clear()

    def held(self, vid: int, since_m: np.ndarray, tol_m: float = 1.0) -> bool:
        """Whether vehicle `vid` stayed within tol_m of `since_m`, or else stepped aside for a
        neighbour (a holder keeps its place unless the filter moves it: the other vehicles fly
        their missions past it, 9 m apart on crossing legs)."""
        with self.lock:
            moved = float(np.linalg.norm(np.array(self.latest[vid].pos_ned_m) - since_m))
            return moved < tol_m or vid in self.stepped_aside

    def on_event(self, e: Event, _t: int) -> None:
        if e.kind is EventKind.STATUS and ": reached item " in e.text:
            k = int(e.text.rsplit(" ", 1)[1].split("/")[0])
            with self.lock:
                self.reached.setdefault(e.vehicle_id, []).append(k)

    def state(self, vid: int) -> VehicleState:
        with self.lock:
            return self.latest[vid]

    def until(self, pred, timeout_s: float, what: str) -> None:
        assert wait_until(lambda: self._holds(pred), timeout_s), (what, self.snapshot())

    def _holds(self, pred) -> bool:
        with self.lock:
            snap = dict(self.latest)
        try:
            return bool(pred(snap))
        except KeyError:
            return False

    def snapshot(self) -> dict:
        with self.lock:
            return {
                v: (s.mode.name, s.mission_item, s.mission_items, np.round(s.pos_ned_m, 1).tolist())
                for v, s in self.latest.items()
            }


def _cli(capsys, *argv: str) -> tuple[int, str]:
    try:
        rc = mission_cli(list(argv))
    except SystemExit as exc:
        rc = exc.code
    cap = capsys.readouterr()
    return rc, cap.out + cap.err


def test_a_qgc_plan_flies_on_three_vehicles_with_pause_resume_abort(procs, tmp_path, capsys):
    port = free_tcp_port()
    mesh_args = ["--fleet", FLEET, "--connect", f"tcp/127.0.0.1:{port}", "--timeout-s", "10"]
    plan = tmp_path / "survey.plan"
    plan.write_text(json.dumps(qgc_plan()))
    with Mesh(embedded_router(port, fleet=FLEET)) as mesh:
        watch = Watch(mesh)
        sim = procs.start(
            "-m", "covey_cli", "fleet-sim", "--vehicles", "3", "--first-id", "1",
            "--fleet", FLEET, "--connect", f"tcp/127.0.0.1:{port}",
            "--cruise-speed-m-s", "3", "--spacing-m", "9", "--geofence-radius-m", "100",
        )  # fmt: skip
        sim.wait_for("READY", timeout_s=90)
        watch.until(lambda s: set(s) >= set(IDS), 30, "a state from every vehicle")

        # The plan file's fence (60 m square) and keep-out zone, as the fleet plan (open mode:
        # unsigned), replace the vehicles' 100 m circle (comms/plan_sync.py).
        geometry = read_plan_file(plan, ORIGIN)
        assert geometry.fence is not None and len(geometry.keep_out) == 1
        publish_plan(mesh.session, geometry.plan(FLEET, 1))
        # Refused with the reason, and nothing kept: a waypoint outside the fence (inside the
        # circle), one in the keep-out zone, an altitude above the 120 m limit.
        # Waiting for the plan: a waypoint 150 m out is refused before it (the 100 m circle)
        # and after it (its fence), so the wait itself never loads a mission.
        beyond = tmp_path / "beyond.json"
        beyond.write_text(
            json.dumps({"items": [{"kind": "waypoint", "north_m": 150, "east_m": 0, "alt_m": 6}]})
        )

        def refused_outside_fence() -> bool:
            rc, out = _cli(capsys, "upload", str(beyond), "--to", "1", *mesh_args)
            assert rc == 1, out  # refused either way
            return "item 1 (waypoint): target outside the fence" in out

        assert wait_until(refused_outside_fence, 20), "the plan's fence never applied"
        far = tmp_path / "far.json"  # inside the 100 m circle, outside the plan's fence
        far.write_text(
            json.dumps({"items": [{"kind": "waypoint", "north_m": 80, "east_m": 0, "alt_m": 6}]})
        )
        rc, out = _cli(capsys, "upload", str(far), "--to", "1", *mesh_args)
        assert rc == 1 and "item 1 (waypoint): target outside the fence" in out, out
        zone = tmp_path / "zone.json"
        zone.write_text(json.dumps({"items": [
            {"kind": "waypoint", "north_m": 10, "east_m": -10, "alt_m": 6},
            {"kind": "waypoint", "north_m": 35, "east_m": -35, "alt_m": 6},
        ]}))  # fmt: skip
        rc, out = _cli(capsys, "upload", str(zone), "--to", "1-3", *mesh_args)
        assert rc == 1 and out.count("item 2 (waypoint): target inside keep-out zone") == 3, out
        high = tmp_path / "high.json"
        high.write_text(
            json.dumps({"items": [{"kind": "waypoint", "north_m": 5, "east_m": 0, "alt_m": 150}]})
        )
        rc, out = _cli(capsys, "upload", str(high), "--to", "1", *mesh_args)
        assert rc == 1 and "altitude 150.0 m is outside" in out, out
        rc, out = _cli(capsys, "show", "--to", "1", *mesh_args)
        assert rc == 0 and "no mission" in out, out

        # Upload: each vehicle its own copy, 9 m further east than the one before.
        rc, out = _cli(
            capsys, "upload", str(plan), "--to", "1-3", "--spread-m", str(SPREAD_M), *mesh_args
        )
        assert rc == 0 and out.count("accepted") == 3 and "6 items" in out, out
        watch.until(
            lambda s: all(s[v].mission_items == 6 and s[v].mission_item == 0 for v in IDS),
            10,
            "loaded",
        )
        rc, out = _cli(capsys, "start", "--to", "1-3", *mesh_args)
        assert rc == 1 and out.count("take off first") == 3, out  # landed: refused, said why

        from groundstation.ops import cmd_cli

        assert cmd_cli(["takeoff", "4", "--to", "1-3", *mesh_args]) == 0
        watch.until(lambda s: all(s[v].mode is Mode.HOLDING for v in IDS), 60, "airborne")
        capsys.readouterr()
        rc, out = _cli(capsys, "start", "--to", "all", *mesh_args)
        assert rc == 0 and out.count("accepted") == 3, out
        watch.until(lambda s: all(s[v].mode is Mode.MISSION for v in IDS), 10, "flying the mission")

        # Pause vehicle 1 on its way to item 3: it holds where it is, at the same item.
        watch.until(
            lambda s: s[1].mission_item == 3 and s[1].mode is Mode.MISSION,
            90,
            "vehicle 1 at item 3",
        )
        rc, out = _cli(capsys, "pause", "--to", "1", *mesh_args)
        assert rc == 0, out
        watch.until(lambda s: s[1].mode is Mode.HOLDING, 5, "vehicle 1 holding")
        time.sleep(1.0)  # let it brake
        p0 = np.array(watch.state(1).pos_ned_m)
        watch.clear_stepped()
        time.sleep(2.0)
        paused = watch.state(1)
        assert paused.mode is Mode.HOLDING and paused.mission_item == 3
        assert watch.held(1, p0), (p0, paused.pos_ned_m)
        rc, out = _cli(capsys, "show", "--to", "1", *mesh_args)
        assert "item 3/6 (waypoint), paused" in out, out
        rc, out = _cli(capsys, "resume", "--to", "1", *mesh_args)
        assert rc == 0, out
        watch.until(
            lambda s: s[1].mode is Mode.MISSION and s[1].mission_item == 3, 5, "resumed at item 3"
        )

        # Abort vehicle 2 at item 4: it holds, its progress dropped.
        watch.until(lambda s: s[2].mission_item >= 4, 90, "vehicle 2 at item 4")
        rc, out = _cli(capsys, "abort", "--to", "2", *mesh_args)
        assert rc == 0, out
        watch.until(
            lambda s: s[2].mode is Mode.HOLDING and s[2].mission_item == 0, 5, "vehicle 2 aborted"
        )
        time.sleep(1.0)
        q0 = np.array(watch.state(2).pos_ned_m)
        watch.clear_stepped()
        time.sleep(2.0)
        assert watch.held(2, q0), (q0, watch.state(2).pos_ned_m)

        # Vehicles 1 and 3 finish: every item reached in order, then the land item lands them.
        watch.until(lambda s: all(s[v].mode is Mode.LANDED for v in (1, 3)), 120, "1 and 3 landed")
        with watch.lock:
            for v in (1, 3):
                assert watch.reached[v] == [1, 2, 3, 4, 5], (v, watch.reached[v])
                seq = watch.items[v]
                assert seq == sorted(seq) and seq[-1] == 7, (v, seq)  # 7: done (6 items)
            assert watch.reached[2][:3] == [1, 2, 3]
        # Each flew its own copy: vehicle 3's waypoint 2 is 18 m east of vehicle 1's.
        assert watch.state(2).mode is Mode.HOLDING
