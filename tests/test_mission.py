"""Missions, piece by piece: the wire message (round trip, limits, a fuzzed decoder, its
signature), the pure executor (items, waits, pause, resume, abort with injected time), the flight
core's checks and failsafes on a simulated fleet (keep-out zone, ceiling, speed, battery, a lost
station), and the mission files (QGC and covey JSON; every bad file one line, exit 2)."""

from __future__ import annotations

import json
import math
import random

import numpy as np
import pytest

from agent.failsafe import FailsafeConfig
from agent.hosts import Fleet
from agent.mission import Ending, LocalItem, MissionRun, RunStatus
from agent.shell_config import FleetSimConfig
from comms.mesh import Mesh
from comms.plan import Fence, FleetPlan, Zone
from comms.schema import (
    MAX_MISSION_BYTES,
    MAX_MISSION_ITEMS,
    AckResult,
    Command,
    CommandKind,
    DecodeError,
    Mission,
    MissionFrame,
    MissionItem,
    MissionItemKind,
    Mode,
    Role,
    decode,
)
from comms.session import MeshConfig
from groundstation.mission_cli import NotInRoster, UploadConfig, mission_cli, upload_main
from groundstation.mission_io import MissionFileError, mission_from_text
from trust.auth import load_auth
from trust.authority import throwaway_fleet

K = MissionItemKind
ISOLATED = MeshConfig(mode="peer", connect=(), listen=("tcp/127.0.0.1:0",))


def _wp(n: float, e: float, alt: float, **kw) -> MissionItem:
    return MissionItem(K.WAYPOINT, x=n, y=e, alt_m=alt, **kw)


def _mission(*items: MissionItem, **kw) -> Mission:
    return Mission(kw.pop("nonce", 7), kw.pop("stamp_ns", 1), tuple(items), **kw)


# -- the wire ------------------------------------------------------------------------------------
def test_missions_round_trip() -> None:
    missions = [
        _mission(MissionItem(K.LAND)),
        _mission(
            MissionItem(K.TAKEOFF, alt_m=8.0),
            MissionItem(K.WAYPOINT, MissionFrame.GLOBAL, 48.7512345678, 9.1098765432, 471.5),
            _wp(10.0, -4.0, 8.0, speed_m_s=1.5, hold_s=2.0),
            MissionItem(K.HOLD, hold_s=3.0),
            MissionItem(K.RETURN),
            mission_id=2**32 - 1,
            mission_version=3,
            targets=(1, 65000),
            source_id=4,
        ),
        _mission(*[_wp(k, 0.0, 5.0) for k in range(MAX_MISSION_ITEMS)], targets=(1, 2, 3)),
    ]
    for m in missions:
        data = m.encode()
        assert len(data) == Mission.size(len(m.targets), len(m.items)) <= MAX_MISSION_BYTES
        back = decode(data)
        assert back == m and back.encode() == data
    # global positions keep float64 precision (a float32 latitude is off by metres)
    assert decode(missions[1].encode()).items[1].x == 48.7512345678


@pytest.mark.parametrize(
    ("mission", "why"),
    [
        (Mission(1, 1, ()), "0 mission items, must be 1..100"),
        (_mission(*[MissionItem(K.LAND)] * 101), "101 mission items"),
        (_mission(MissionItem(K.LAND), targets=tuple(range(1, 2001))), "at most 4096"),
        (_mission(MissionItem(K.LAND, x=3.0)), "item 1: a LAND has no position"),
        (_mission(MissionItem(K.RETURN, hold_s=2.0)), "a RETURN has no hold time"),
        (_mission(MissionItem(K.TAKEOFF, alt_m=0.1)), "takeoff alt_m=0.1"),
        (_mission(_wp(math.nan, 0, 5)), "mission item 1 must be finite"),
        (_mission(_wp(0, 0, 5), _wp(0, 0, 5, hold_s=-1.0)), "item 2 hold_s=-1.0"),
        (_mission(_wp(0, 0, 5, speed_m_s=500.0)), "speed_m_s=500.0"),
        (_mission(MissionItem(K.WAYPOINT, MissionFrame.GLOBAL, 95.0, 0.0, 400.0)), "lat_deg"),
        (_mission(MissionItem(K.LAND), targets=(3, 3)), "duplicates"),
    ],
)
def test_bad_missions_are_refused_with_the_reason(mission: Mission, why: str) -> None:
    with pytest.raises(DecodeError, match=why):
        mission.encode()


def test_the_mission_decoder_survives_mutations() -> None:
    """Every mutated mission decodes to one that re-encodes to the same bytes, or is refused
    with a reason: nothing else escapes (the tests/test_fuzz_decoders.py pattern)."""
    from test_fuzz_decoders import mutate

    rng = random.Random(36)
    seed = _mission(
        MissionItem(K.TAKEOFF, alt_m=8.0),
        MissionItem(K.WAYPOINT, MissionFrame.GLOBAL, 48.75, 9.1, 470.0),
        _wp(10.0, -4.0, 8.0, hold_s=2.0),
        MissionItem(K.LAND),
        targets=(1, 2),
    ).encode()
    decoded = 0
    for _ in range(6000):
        data = mutate(seed, rng)
        try:
            msg = decode(data)
        except DecodeError as exc:
            assert str(exc)
            continue
        decoded += 1
        assert msg.encode() == data
    assert decoded > 100  # the mutations reach the item checks, not only the header


def test_a_mission_is_signed_and_checked_like_a_command(tmp_path) -> None:
    authority = throwaway_fleet(tmp_path, "m", vehicles=[1], stations=[1])
    now = [10**18]
    station = load_auth(str(authority.member_path(Role.STATION, 1)), clock_ns=lambda: now[0])
    vehicle = load_auth(str(authority.member_path(Role.VEHICLE, 1)), clock_ns=lambda: now[0])
    signed = station.sign_mission(_mission(_wp(1, 2, 5), nonce=0))
    assert signed.nonce and signed.source_id == 1
    wire = decode(signed.encode())
    assert vehicle.check_mission(wire, 1) is None
    assert vehicle.check_mission(wire, 1).startswith("replayed")
    assert vehicle.check_mission(_mission(_wp(1, 2, 5)), 1).startswith("unsigned")
    tampered = Mission(wire.nonce + 1, wire.stamp_ns, wire.items, source_id=1, tag=wire.tag)
    assert vehicle.check_mission(tampered, 1).startswith("bad signature")
    # its signature is a mission's: the same bytes never pass as a command's
    assert vehicle.verify_command(wire).startswith("bad signature")
    now[0] += 60 * 10**9
    late = station.sign_mission(_mission(_wp(1, 2, 5)))
    now[0] -= 60 * 10**9
    assert vehicle.check_mission(late, 1).startswith("stale")
    with pytest.raises(Exception, match="only a station key"):
        vehicle.sign_mission(_mission(_wp(1, 2, 5)))


# -- the executor --------------------------------------------------------------------------------
def test_the_executor_flies_items_in_order_with_waits_pause_and_abort() -> None:
    items = (
        LocalItem(K.TAKEOFF, alt_m=6.0),
        LocalItem(K.WAYPOINT, (10.0, 0.0, -6.0), hold_s=2.0),
        LocalItem(K.HOLD, hold_s=1.0),
        LocalItem(K.LAND),
    )
    run = MissionRun(3, 1, items)
    here = np.array([1.0, 2.0, -4.0])
    assert run.progress() == (0, 4) and run.status is RunStatus.LOADED
    assert run.start(here).started == 1
    np.testing.assert_allclose(run.target, [1.0, 2.0, -6.0])  # climb where it is
    assert run.step(0.0, here, arrived=False).reached == 0
    tick = run.step(1.0, here, arrived=True)
    assert (tick.reached, tick.started) == (1, 2) and run.progress() == (2, 4)
    np.testing.assert_allclose(run.target, [10.0, 0.0, -6.0])
    assert run.step(5.0, run.target, arrived=True).reached == 2  # its 2 s wait begins
    run.pause(6.0)  # 1 s of the wait left
    assert run.step(100.0, run.target, arrived=True) == type(tick)()  # paused: nothing moves
    run.resume(200.0)
    assert run.step(200.5, run.target, arrived=True).started == 0
    tick = run.step(201.0, run.target, arrived=True)
    assert tick.started == 3 and run.items[2].kind is K.HOLD
    tick = run.step(201.1, run.target, arrived=True)
    assert tick.reached == 3 and not tick.started
    tick = run.step(202.2, run.target, arrived=True)
    assert tick.started == 4 and tick.ending is Ending.LAND and run.progress() == (5, 4)
    run.abort()
    assert run.progress() == (0, 4) and run.target is None


# -- the flight core on a simulated fleet --------------------------------------------------------
def _fleet(mesh: Mesh, clock: list[float], **failsafe) -> Fleet:
    fs = FailsafeConfig(require_gcs=False, geofence_radius_m=300.0, **failsafe)
    cfg = FleetSimConfig(vehicles=1, mesh=ISOLATED, see_others=False, failsafe=fs)
    return Fleet(cfg, mesh, clock_s=lambda: clock[0])


def _fly(fleet: Fleet, clock: list[float], seconds: float, every=None) -> None:
    for _ in range(int(seconds * 10)):
        clock[0] += 0.1
        fleet.tick(clock[0])
        if every is not None:
            every()


def _cmd(fleet: Fleet, kind: CommandKind, *params: float):
    p = (*params, 0.0, 0.0, 0.0)[:3]
    return fleet.handle_command(0, Command(kind, random.getrandbits(63) + 1, 0, params=p))


def _airborne(fleet: Fleet, clock: list[float]) -> None:
    assert _cmd(fleet, CommandKind.TAKEOFF, 5.0).result is AckResult.ACCEPTED
    _fly(fleet, clock, 12)
    assert fleet.modes[0] is Mode.HOLDING


def test_the_core_refuses_zones_ceilings_and_speeds_naming_the_item() -> None:
    clock = [100.0]
    with Mesh(ISOLATED) as mesh:
        fleet = _fleet(mesh, clock)
        plan = FleetPlan(
            "covey",
            1,
            0,
            fence=Fence(((-200, -200), (-200, 200), (200, 200), (200, -200)), ceiling_alt_m=40.0),
            keep_out=(Zone(((20, -5), (20, 5), (30, 5), (30, -5)), "school"),),
        )
        fleet.core.set_plan(plan)
        cases = [
            (_mission(_wp(5, 0, 5), _wp(25, 0, 5)), "item 2 (waypoint): target inside keep-out zone 'school'"),
            (_mission(_wp(5, 0, 50)), "item 1 (waypoint): target above the 40 m ceiling"),
            (_mission(_wp(250, 0, 10)), "item 1 (waypoint): target outside the fence"),
            (_mission(MissionItem(K.TAKEOFF, alt_m=45.0)), "item 1 (takeoff): altitude 45.0 m is above the 40 m ceiling"),
            (_mission(_wp(5, 0, 5, speed_m_s=9.0)), "item 1: speed 9 m/s is above the 1 m/s cruise"),
        ]  # fmt: skip
        for mission, why in cases:
            ack = fleet.handle_mission(0, mission)
            assert ack.result is AckResult.REJECTED and ack.reason.startswith(why), ack.reason
            assert fleet.core.missions[0] is None  # nothing kept
        assert fleet.handle_mission(0, _mission(_wp(5, 0, 5))).result is AckResult.ACCEPTED


def test_an_item_speed_is_flown_and_failsafes_override_a_mission() -> None:
    clock = [100.0]
    with Mesh(ISOLATED) as mesh:
        fleet = _fleet(mesh, clock)
        _airborne(fleet, clock)
        assert fleet.handle_mission(0, _mission(_wp(30, 0, 5, speed_m_s=0.5))).accepted
        assert _cmd(fleet, CommandKind.MISSION_START).result is AckResult.ACCEPTED
        speeds: list[float] = []
        _fly(fleet, clock, 8, lambda: speeds.append(float(np.hypot(*fleet.sim.vel_m_s[0, :2]))))
        assert fleet.modes[0] is Mode.MISSION
        assert 0.35 < max(speeds[-30:]) <= 0.55, max(speeds)  # cruise is 1 m/s
        # Battery low: the return failsafe takes over, as from a goto.
        fleet.sim.battery_pct[0] = 20.0
        _fly(fleet, clock, 0.5)
        assert fleet.modes[0] is Mode.RETURNING
        assert fleet.core.missions[0].status is RunStatus.PAUSED
        refused = _cmd(fleet, CommandKind.MISSION_RESUME)
        assert refused.result is AckResult.REJECTED and "while returning" in refused.reason
        refused = _cmd(fleet, CommandKind.MISSION_START)
        assert refused.result is AckResult.REJECTED and "battery 20 %" in refused.reason


def test_a_lost_station_holds_a_mission_and_its_return_resumes_it() -> None:
    clock = [100.0]
    alive = [True]
    with Mesh(ISOLATED) as mesh:
        fleet = _fleet(mesh, clock, gcs_lost_hold_s=2.0, gcs_lost_land_s=30.0)
        fleet.cfg = type(fleet.cfg)(**{**fleet.cfg.__dict__})  # frozen copy, same values
        object.__setattr__(fleet.cfg.failsafe, "require_gcs", True)
        fleet.stations.alive = lambda _now: alive[0]
        fleet.stations.takeoff_problem = lambda *_a: None
        _airborne(fleet, clock)
        assert fleet.handle_mission(0, _mission(_wp(40, 0, 5), _wp(40, 20, 5))).accepted
        assert _cmd(fleet, CommandKind.MISSION_START).result is AckResult.ACCEPTED
        _fly(fleet, clock, 3)
        alive[0] = False
        _fly(fleet, clock, 3)
        assert fleet.modes[0] is Mode.HOLDING and fleet.core.missions[0].by_failsafe
        alive[0] = True
        _fly(fleet, clock, 0.5)
        assert fleet.modes[0] is Mode.MISSION and fleet.core.mission_progress()[0][0] == 1


def test_pause_resume_and_abort_answer_with_reasons() -> None:
    clock = [100.0]
    with Mesh(ISOLATED) as mesh:
        fleet = _fleet(mesh, clock)
        assert "no mission" in _cmd(fleet, CommandKind.MISSION_STATUS).reason
        _airborne(fleet, clock)
        assert _cmd(fleet, CommandKind.MISSION_START).reason == "no mission uploaded"
        assert fleet.handle_mission(0, _mission(_wp(20, 0, 5), mission_id=9)).accepted
        assert "no paused mission" in _cmd(fleet, CommandKind.MISSION_RESUME).reason
        assert "not flying a mission" in _cmd(fleet, CommandKind.MISSION_PAUSE).reason
        assert _cmd(fleet, CommandKind.MISSION_START).result is AckResult.ACCEPTED
        busy = fleet.handle_mission(0, _mission(_wp(1, 0, 5)))
        assert busy.result is AckResult.REJECTED and "pause or abort it first" in busy.reason
        _fly(fleet, clock, 2)
        assert _cmd(fleet, CommandKind.MISSION_ABORT).mode is Mode.HOLDING
        assert _cmd(fleet, CommandKind.MISSION_ABORT).reason == "no mission flying"
        assert "mission 9 v1: not started" in _cmd(fleet, CommandKind.MISSION_STATUS).reason


# -- files ---------------------------------------------------------------------------------------
HOME = [48.749, 9.105, 450.0]


def _qgc(*items: dict, home=HOME) -> str:
    return json.dumps(
        {"fileType": "Plan", "mission": {"items": list(items), "plannedHomePosition": home}}
    )


def _simple(command: int, frame: int = 3, params=(0, 0, 0, 0, 48.7491, 9.1051, 10)) -> dict:
    return {"type": "SimpleItem", "command": command, "frame": frame, "params": list(params)}


def test_a_qgc_plan_reads_as_covey_items() -> None:
    got = mission_from_text(
        _qgc(
            _simple(22, params=(0, 0, 0, 0, 0, 0, 12)),
            _simple(16, params=(3, 0, 0, 0, 48.7491, 9.1051, 10)),
            _simple(19, frame=0, params=(5, 0, 0, 0, 48.7492, 9.1052, 470)),
            _simple(21, params=(0, 0, 0, 0, 48.7493, 9.1053, 0)),
            _simple(20, params=(0,) * 7),
        )
    ).items
    assert [i.kind for i in got] == [
        K.TAKEOFF,
        K.WAYPOINT,
        K.WAYPOINT,
        K.WAYPOINT,
        K.LAND,
        K.RETURN,
    ]
    assert got[0].alt_m == 12.0
    assert (got[1].frame, got[1].alt_m, got[1].hold_s) == (MissionFrame.GLOBAL, 460.0, 3.0)
    assert (got[2].alt_m, got[2].hold_s) == (470.0, 5.0)
    assert (got[3].x, got[3].alt_m) == (48.7493, 470.0)  # a land at a position: fly there first


@pytest.mark.parametrize(
    ("text", "why"),
    [
        (_qgc(_simple(178)), "item 1: MAV_CMD 178 is not flown by covey"),
        (_qgc({"type": "ComplexItem"}), "'ComplexItem' items (surveys, corridors) are not flown"),
        (_qgc(_simple(16), home=None), "needs mission.plannedHomePosition"),
        (_qgc(_simple(16, frame=10)), "frame 10 is not supported"),
        (_qgc(_simple(16, params=(0, 0, 0, 0, 48.7, 9.1, -5))), "below home"),
        (_qgc(*[_simple(16)] * 101), "101 items"),
        (
            '{"items": [{"kind": "waypoint", "north_m": 1, "east_m": 2, "alt_m": -3}]}',
            "below the origin",
        ),
        ('{"items": [{"kind": "waypoint", "north_m": 1, "lat_deg": 2, "alt_m": 3}]}', "not a mix"),
        ('{"items": [{"kind": "jump"}]}', "needs a 'kind' of takeoff"),
        ('{"items": [{"kind": "land", "north_m": 3}]}', "unknown fields north_m"),
        ('{"items": [{"kind": "hold", "hold_s": 1e9}]}', "hold_s=1000000000.0"),
        ("[1, 2]", "expected a JSON object"),
        ("{}", "neither a covey mission"),
    ],
)
def test_bad_files_say_why(text: str, why: str) -> None:
    with pytest.raises(MissionFileError, match=None) as exc:
        mission_from_text(text, "mission file m")
    assert why in str(exc.value), str(exc.value)


@pytest.mark.parametrize(
    ("content", "why"),
    [
        (b"{not json", "is not JSON"),
        (b"[" * 100 + b"]" * 100, "nests deeper than 32 levels"),
        (b" " * 1_000_001, "over the 1000000 limit"),
        (b"\xff\xfe", "UTF-8"),
    ],
)
def test_a_malformed_or_oversize_file_is_one_line_and_exit_2(
    tmp_path, capsys, content, why
) -> None:
    path = tmp_path / "m.plan"
    path.write_bytes(content)
    with pytest.raises(SystemExit) as exc:
        mission_cli(["upload", str(path), "--to", "1"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and why in err, err


def test_a_vehicle_outside_the_roster_is_refused_before_anything_is_sent(tmp_path, capsys) -> None:
    authority = throwaway_fleet(tmp_path / "keys", "covey", vehicles=[1, 2], stations=[1])
    key = str(authority.member_path(Role.STATION, 1))
    cfg = UploadConfig(mesh=ISOLATED, items=(_wp(1, 2, 5),), targets=(2, 7), key_file=key)
    with pytest.raises(
        NotInRoster, match=r"vehicle 7 is not in fleet roster v\d+: no mission sent"
    ):
        upload_main(cfg)  # raised before a mesh session opens: nothing sent
    path = tmp_path / "m.json"
    path.write_text('{"items": [{"kind": "land"}]}')
    with pytest.raises(SystemExit) as exc:
        mission_cli(
            ["upload", str(path), "--to", "7", "--key-file", key, "--connect", "tcp/127.0.0.1:9"]
        )
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "vehicle 7 is not in fleet roster" in err, err


def test_the_command_log_says_when_mission_commands_are_done() -> None:
    import dataclasses

    from comms.schema import VehicleState
    from groundstation.command_log import outcome_text

    def cmd(kind: CommandKind) -> Command:
        return Command(kind, 1, 0)

    assert outcome_text(cmd(CommandKind.MISSION_PAUSE), Mode.HOLDING, None) == "holding"
    assert outcome_text(cmd(CommandKind.MISSION_STATUS), Mode.LANDED, None) == "answered"
    done = VehicleState(
        1,
        1,
        1,
        (0.0, 0.0, -5.0),
        (0.0, 0.0, 0.0),
        0.0,
        Mode.HOLDING,
        mission_item=4,
        mission_items=3,
    )
    assert outcome_text(cmd(CommandKind.MISSION_START), Mode.HOLDING, done) == "mission done"
    flying = dataclasses.replace(done, mode=Mode.MISSION, mission_item=2)
    assert outcome_text(cmd(CommandKind.MISSION_START), Mode.MISSION, flying) is None


def test_uploads_split_long_target_lists_and_spread_copies() -> None:
    from comms.geo import GeoOrigin
    from groundstation.mission_cli import missions_for

    items = (
        MissionItem(K.TAKEOFF, alt_m=5.0),
        MissionItem(K.WAYPOINT, MissionFrame.GLOBAL, 48.75, 9.1, 460.0),
        _wp(10.0, 2.0, 5.0),
    )
    many = UploadConfig(mesh=ISOLATED, items=items, targets=tuple(range(1, 3001)))
    missions = missions_for(many, set(), 1)
    assert len(missions) == 2 and sum(len(m.targets) for m in missions) == 3000
    assert all(len(m.encode()) <= MAX_MISSION_BYTES for m in missions)
    spread = UploadConfig(mesh=ISOLATED, items=items, targets=(), spread_m=8.0)
    copies = missions_for(spread, {4, 2, 9}, 1)
    assert [m.targets for m in copies] == [(2,), (4,), (9,)]
    origin = GeoOrigin(48.75, 9.1, 0.0)
    for k, m in enumerate(copies):
        n, e, _ = origin.to_local(m.items[1].x, m.items[1].y, 0.0)
        assert abs(n) < 1e-3 and abs(e - 8.0 * k) < 1e-3
        assert (m.items[2].x, m.items[2].y) == (10.0, 2.0 + 8.0 * k)
        assert m.items[0] == items[0]


def test_covey_status_shows_the_mission_progress() -> None:
    from comms.schema import VehicleState
    from groundstation.fleet import FleetModel
    from groundstation.ops import format_status

    fleet = FleetModel()
    for vid, (k, n) in {1: (3, 6), 2: (7, 6), 3: (0, 0)}.items():
        state = VehicleState(
            vid, 1, 1_000, (0.0, 0.0, -5.0), (0.0, 0.0, 0.0), 0.0, Mode.MISSION, True, 90.0,
            mission_item=k, mission_items=n,
        )  # fmt: skip
        fleet.on_state(state, 1_000)
    lines = format_status(fleet.snapshot(2_000)).splitlines()
    assert lines[0].split()[-1] == "mission"
    assert [line.split()[-1] for line in lines[1:4]] == ["3/6", "done", "-"]
