"""The shared command log and the per-kind event buffer: bounded, and one truth for every station."""

from __future__ import annotations

import pytest

from comms.schema import (
    AckResult,
    ActionOutcome,
    Command,
    CommandAck,
    CommandKind,
    Event,
    EventKind,
    Mode,
    Severity,
    StateFlag,
    VehicleState,
)
from groundstation.command_log import CommandLog, CommandLogConfig, Progress, Status
from groundstation.events import EventBuffer, EventsConfig
from groundstation.tables import command_log_html, event_text

S = 1_000_000_000


def cmd(nonce: int, targets=(1,), source_id: int = 2, kind=CommandKind.GOTO_LOCAL) -> Command:
    return Command(
        kind=kind,
        nonce=nonce,
        stamp_ns=nonce,
        params=(1.0, 2.0, -3.0),
        targets=targets,
        source_id=source_id,
    )


def ack(vid: int, nonce: int, result=AckResult.ACCEPTED) -> CommandAck:
    return CommandAck(vid, nonce, nonce, result, "" if result is AckResult.ACCEPTED else "no")


def test_answers_are_kept_per_command_and_stray_acks_are_refused():
    log = CommandLog()
    log.on_command(cmd(10, targets=(1, 2)), 1)
    log.on_ack(ack(1, 10), 2)
    log.on_ack(ack(2, 10, AckResult.REJECTED), 3)
    log.on_ack(ack(1, 99), 4)  # answers nothing we saw (yet)
    log.on_ack(ack(1, 10), 5, check=lambda a, c, d: "bad tag")  # fails the signature check
    (e,) = log.entries()
    assert {v: a.result for v, a in e.answers.items()} == {
        1: AckResult.ACCEPTED,
        2: AckResult.REJECTED,
    }
    assert log.refused_acks == 1
    # An ack that overtook its command is applied when the command arrives.
    log.on_command(cmd(99), 6)
    assert log.entries()[0].answers[1].result is AckResult.ACCEPTED
    assert e.describe() == "goto N 1.0 E 2.0 alt 3.0 m above origin → 1,2"


def test_a_later_accepted_command_supersedes_the_earlier_on_that_vehicle_only():
    seen = []
    log = CommandLog(
        on_superseded=lambda before, vid, later: seen.append((before.seq, vid, later.seq))
    )
    log.on_command(cmd(1, targets=(1, 2), source_id=2), 1)
    log.on_ack(ack(1, 1), 2)
    log.on_ack(ack(2, 1), 2)
    log.on_command(cmd(2, targets=(1,), source_id=3), 3)
    log.on_ack(ack(1, 2, AckResult.REJECTED), 4)  # a refused command replaces nothing
    assert seen == []
    log.on_command(cmd(3, targets=(1,), source_id=3), 5)
    log.on_ack(ack(1, 3), 6)
    assert seen == [(1, 1, 3)]
    first = log.entries()[-1]
    assert first.superseded == {1: 3} and 2 not in first.superseded
    # An ack that arrives after a later command was accepted is marked superseded at once.
    log.on_command(cmd(4, targets=(2,)), 7)
    log.on_command(cmd(5, targets=(2,)), 8)
    log.on_ack(ack(2, 5), 9)
    log.on_ack(ack(2, 4), 10)
    by_nonce = {e.command.nonce: e for e in log.entries()}
    assert by_nonce[4].superseded == {2: by_nonce[5].seq}


def test_the_log_is_bounded_in_commands_and_answers():
    log = CommandLog(CommandLogConfig(max_commands=5, max_answers=3))
    for n in range(1, 101):
        log.on_command(cmd(n, targets=()), n)
        for vid in range(1, 11):
            log.on_ack(ack(vid, n), n)
    entries = log.entries()
    assert len(entries) == 5 and [e.command.nonce for e in entries] == [100, 99, 98, 97, 96]
    assert all(len(e.answers) == 3 and e.dropped_answers == 7 for e in entries)
    assert len(log._last_accepted) <= 5 * 3
    for n in range(1000, 1100):  # acks for commands never seen stay bounded
        log.on_ack(ack(1, n), n)
    assert len(log._early) <= 5 and log.refused_acks >= 95


def test_a_flood_of_one_event_kind_never_hides_another():
    buf = EventBuffer(EventsConfig(per_kind=50, shown=12), clock_text=lambda: "t")
    buf.add(Event(vehicle_id=1, stamp_ns=0, text="mode GOTO", kind=EventKind.MODE_CHANGE))
    for k in range(10_000):
        buf.add(
            Event(
                vehicle_id=2,
                stamp_ns=k,
                text="refused",
                kind=EventKind.SECURITY,
                severity=Severity.WARNING,
            )
        )
    assert [e.text for _, e in buf.latest(EventKind.MODE_CHANGE)] == ["mode GOTO"]
    shown = buf.latest()  # all kinds: the flood fills at most a third of the lines
    assert [e.kind for _, e in shown] == [EventKind.MODE_CHANGE] + [EventKind.SECURITY] * 4
    assert len(buf.latest(EventKind.SECURITY)) == 12
    assert buf.latest(min_severity=Severity.ERROR) == []
    assert sum(len(q) for q in buf._by_kind.values()) == 51


def state(vid: int, stamp_ns: int, mode: Mode, pos=(0.0, 0.0, -5.0), goal=None) -> VehicleState:
    return VehicleState(
        vehicle_id=vid,
        seq=stamp_ns,
        stamp_ns=stamp_ns,
        pos_ned_m=pos,
        vel_ned_m_s=(0.0, 0.0, 0.0),
        heading_rad=0.0,
        mode=mode,
        armed=mode is not Mode.LANDED,
        battery_pct=90.0,
        flags=StateFlag.HAS_GOAL if goal is not None else StateFlag.NONE,
        goal_ned_m=goal or (0.0, 0.0, 0.0),
    )


def accepted(vid: int, nonce: int, stamp_ns: int, mode: Mode) -> CommandAck:
    return CommandAck(vid, nonce, stamp_ns, AckResult.ACCEPTED, "", mode)


def status(log: CommandLog, nonce: int, vid: int, now_ns: int = 0, present=None):
    e = next(e for e in log.entries() if e.command.nonce == nonce)
    return e.progress(vid, now_ns, 3.0, present)


def refuse_unsigned(c: Command) -> str | None:
    """Stands in for FleetAuth.verify_command (tests/test_trust_* run the real one)."""
    return None if c.tag != bytes(len(c.tag)) else "unsigned command: no station signature"


def test_forged_commands_are_counted_by_cause_and_never_displace_real_ones():
    log = CommandLog(CommandLogConfig(max_commands=5))
    signed = [
        Command(CommandKind.LAND, nonce=n, stamp_ns=n, source_id=1, tag=b"\x01" * 64)
        for n in (1, 2)
    ]
    for c in signed:
        assert log.on_command(c, 10 * S, check=refuse_unsigned)
    for n in range(100, 3240):  # 3,140 forged queries claiming this station, over 30 s
        kill = Command(CommandKind.KILL, nonce=n, stamp_ns=n, source_id=1)
        assert not log.on_command(kill, 10 * S + n * 10_000_000, check=refuse_unsigned)
    assert [e.command.nonce for e in log.entries()] == [2, 1]
    assert all(e.signed for e in log.entries())
    counts = log.refused_last_minute(45 * S)
    assert counts == {"unsigned command": 3140}
    html = command_log_html(log.entries(), 45 * S, refused=counts)
    assert "3,140 refused command attempts in the last minute" in html
    assert html.count("data-command=") == 2 and "kill" not in html
    assert log.refused_last_minute(200 * S) == {}  # a minute later the line is gone
    assert log.refused_commands == 3140


def test_a_mission_upload_is_listed_with_each_vehicles_ack():
    """An upload reads "mission 3 (6 items) → 1,2,3", is done ("loaded") where accepted,
    rejected with the vehicle's reason where not, and supersedes no command (it flies
    nothing); a forged one is only counted, like a forged command."""
    from comms.schema import Mission, MissionItem, MissionItemKind

    log = CommandLog()
    log.on_command(cmd(5, targets=(1,)), 1 * S)
    log.on_ack(ack(1, 5), 1 * S)  # vehicle 1 flies a goto
    items = tuple(
        MissionItem(MissionItemKind.WAYPOINT, x=float(k), y=0.0, alt_m=6.0) for k in range(6)
    )
    up = Mission(7, 7, items, mission_id=3, targets=(1, 2, 3), source_id=2, tag=b"\x01" * 64)
    assert log.on_command(up, 2 * S, check=refuse_unsigned)
    log.on_ack(ack(1, 7), 2 * S)
    log.on_ack(ack(2, 7), 2 * S)
    log.on_ack(CommandAck(3, 7, 7, AckResult.REJECTED, "item 2: outside the fence"), 2 * S)
    entry, goto = log.entries()
    assert entry.describe() == "mission 3 (6 items) → 1,2,3" and entry.sender() == "station 2"
    assert {v: entry.progress(v, 3 * S, 5.0, None) for v in (1, 2, 3)} == {
        1: Progress(Status.DONE, "loaded"),
        2: Progress(Status.DONE, "loaded"),
        3: Progress(Status.REJECTED, "item 2: outside the fence"),
    }
    assert goto.progress(1, 3 * S, 5.0, None) == Progress(Status.ACCEPTED, "under way")
    forged = Mission(8, 8, items[:1], mission_id=9, targets=(1,), source_id=1)
    assert not log.on_command(forged, 3 * S, check=refuse_unsigned)
    assert len(log) == 2 and log.refused_last_minute(4 * S) == {"unsigned command": 1}
    html = command_log_html(log.entries(), 3 * S, refused=log.refused_last_minute(4 * S))
    assert "mission 3 (6 items) → 1,2,3" in html and "mission 9" not in html
    assert "1 refused command attempt in the last minute" in html


def test_senders_are_labelled_honestly():
    log = CommandLog()
    log.mark_own(1)
    log.on_command(Command(CommandKind.HOLD, nonce=1, stamp_ns=1, source_id=1), 1)
    log.on_command(Command(CommandKind.HOLD, nonce=2, stamp_ns=2, source_id=1), 2)
    signed = Command(CommandKind.HOLD, nonce=3, stamp_ns=3, source_id=2, tag=b"\x01" * 64)
    log.on_command(signed, 3, check=refuse_unsigned)
    who = {e.command.nonce: e.sender() for e in log.entries()}
    assert who == {
        1: "this station (unsigned: open mode)",
        2: "unsigned, claims station 1",  # a CLI or anyone else, in open mode
        3: "station 2",
    }


def test_each_vehicle_reads_done_failed_superseded_timed_out_or_unreachable():
    log = CommandLog()
    takeoff = Command(CommandKind.TAKEOFF, nonce=1, stamp_ns=1, params=(5.0, 0, 0), targets=())
    log.on_command(takeoff, 1 * S)
    for vid in (1, 2, 3):
        log.on_ack(accepted(vid, 1, 2 * S, Mode.TAKING_OFF), 2 * S)
    assert status(log, 1, 1).status is Status.ACCEPTED
    log.on_state(state(1, 1 * S, Mode.HOLDING))  # from before the ack: proves nothing
    assert status(log, 1, 1).status is Status.ACCEPTED
    log.on_state(state(1, 3 * S, Mode.HOLDING, pos=(0.0, 0.0, -4.96)))
    log.on_state(state(2, 3 * S, Mode.HOLDING))
    assert status(log, 1, 1) == Progress(Status.DONE, "reached 5.0 m")
    # Vehicle 3 fails in the autopilot; vehicles 1 and 2 then get a goto: the take-off stays
    # done (it had finished), it is not "superseded".
    log.on_outcome(ActionOutcome(3, 1, False, "takeoff to 5 m: arming denied"))
    goto = Command(CommandKind.GOTO_LOCAL, nonce=2, stamp_ns=2, params=(10.0, 1.46958e-15, -5.0))
    log.on_command(goto, 4 * S)
    for vid in (1, 2):
        log.on_ack(accepted(vid, 2, 5 * S, Mode.GOTO), 5 * S)
    assert [status(log, 1, v).status for v in (1, 2, 3)] == [
        Status.DONE,
        Status.DONE,
        Status.FAILED,
    ]
    assert "arming denied" in status(log, 1, 3).detail
    # Vehicle 1 reaches its goal; vehicle 2 is sent elsewhere before it does: superseded.
    log.on_state(state(1, 6 * S, Mode.HOLDING, goal=(10.0, 0.0, -5.0)))
    assert status(log, 2, 1) == Progress(Status.DONE, "reached goal")
    land = Command(CommandKind.LAND, nonce=3, stamp_ns=3, targets=(2, 9))
    log.on_command(land, 7 * S)
    log.on_ack(accepted(2, 3, 8 * S, Mode.LANDING), 8 * S)
    assert status(log, 2, 2).status is Status.SUPERSEDED
    log.on_state(state(2, 9 * S, Mode.LANDED, pos=(0.0, 0.0, 0.0)))
    assert status(log, 3, 2).detail == "landed"
    # Vehicle 9 never answers: waiting, then timed out (present) or not reachable (absent).
    assert status(log, 3, 9, now_ns=8 * S).status is Status.WAITING
    assert status(log, 3, 9, now_ns=20 * S, present={2, 9}).status is Status.TIMED_OUT
    assert status(log, 3, 9, now_ns=20 * S, present={2}).status is Status.UNREACHABLE
    html = command_log_html(log.entries(), 20 * S, present={1, 2, 3}, answer_timeout_s=3.0)
    assert "goto N 10.0 E 0.0 alt 5.0 m above origin" in html and "e-15" not in html
    assert 'data-vehicle="1" data-answer="done"' in html
    assert 'data-vehicle="9" data-answer="not reachable"' in html
    assert 'data-vehicle="2" data-answer="superseded"' in html


@pytest.mark.parametrize(
    ("kind", "ack_mode", "later", "text"),
    [
        (CommandKind.HOLD, Mode.HOLDING, None, "holding"),
        (CommandKind.KILL, Mode.KILLED, None, "killed"),
        (CommandKind.RETURN, Mode.RETURNING, Mode.LANDED, "returned and landed"),
        (CommandKind.LAND, Mode.LANDING, Mode.LANDED, "landed"),
    ],
)
def test_a_command_is_done_in_the_mode_it_ends_in(kind, ack_mode, later, text):
    log = CommandLog()
    log.on_command(Command(kind, nonce=7, stamp_ns=7, targets=(4,)), S)
    log.on_ack(accepted(4, 7, 2 * S, ack_mode), 2 * S)
    if later is not None:
        assert status(log, 7, 4).status is Status.ACCEPTED
        log.on_state(state(4, 3 * S, later))
    assert status(log, 7, 4) == Progress(Status.DONE, text)


def test_autopilot_events_name_their_command_not_the_nonce():
    log = CommandLog()
    log.on_command(Command(CommandKind.TAKEOFF, nonce=0x5FBFE957, stamp_ns=1, params=(5, 0, 0)), 1)
    ok = ActionOutcome(1, 0x5FBFE957, True, "takeoff to 5 m", stamp_ns=2)
    assert event_text(ok, log.name_of) == "autopilot done: takeoff to 5.0 m above origin → all"
    bad = ActionOutcome(1, 0x1234, False, "land: link lost", stamp_ns=2)
    assert event_text(bad, log.name_of) == "autopilot FAILED: land: link lost"
    assert "5fbfe957" not in event_text(ok, log.name_of)


@pytest.mark.e2e
def test_a_keyless_command_query_is_only_counted_by_a_keyed_station(tmp_path):
    """Real Zenoh, a keyed station (station 1) and a keyless process that queries the fleet's
    command keys with kills that claim source_id=1, as issue 34 found: none enters the log, the
    one summary line counts them, and a command signed by station 2 is logged as station 2's."""
    import time

    from conftest import wait_until

    from comms import keys
    from comms.mesh import Mesh
    from comms.schema import Role
    from comms.session import embedded_peer, embedded_router, free_tcp_port, open_session
    from groundstation.station import GcsConfig, GroundStation
    from trust.auth import load_auth
    from trust.authority import throwaway_fleet

    authority = throwaway_fleet(tmp_path / "keys", "covey", vehicles=[1], stations=[1, 2])
    key = {sid: str(authority.member_path(Role.STATION, sid)) for sid in (1, 2)}
    port = free_tcp_port()
    with (
        Mesh(embedded_router(port)),
        GroundStation(GcsConfig(mesh=embedded_peer(port), port=0, key_file=key[1])) as gcs,
        open_session(embedded_peer(port)) as attacker,
    ):
        tries = [0]

        def forge() -> None:
            tries[0] += 1
            kill = Command(CommandKind.KILL, nonce=tries[0], stamp_ns=time.time_ns(), source_id=1)
            for _ in attacker.get(keys.all_cmds("covey"), payload=kill.encode(), timeout=0.2):
                pass

        # until the station's queryable has reached the attacker's session (a loaded machine
        # takes its time), a query finds nobody: probe until the station counts one
        assert wait_until(lambda: forge() or gcs.commands.refused_commands >= 1, 20, 0.1)
        base = gcs.commands.refused_commands
        forged = 60
        for _ in range(forged):
            forge()
        assert wait_until(lambda: gcs.commands.refused_commands >= base + forged, 10)
        forged = gcs.commands.refused_commands
        assert forged <= tries[0]  # counted once each, never more
        assert gcs.commands.entries() == []
        with Mesh(embedded_peer(port), auth=load_auth(key[2])) as other:
            nonces = []
            for _ in range(10):  # a new session's first query may find no route yet
                hold = Command(CommandKind.HOLD, nonce=0, stamp_ns=0, targets=(1,))
                nonces.append(other.send_command(hold, timeout_s=0.5).command.nonce)
                if wait_until(lambda: len(gcs.commands) >= 1, 2):
                    break
        assert wait_until(lambda: len(gcs.commands) >= 1, 10)
        entries = gcs.commands.entries()
        assert all(e.command.nonce in nonces and e.sender() == "station 2" for e in entries)
        assert wait_until(
            lambda: f"data-refused-commands='{forged}'" in gcs.command_log_html.content, 10
        )
        html = gcs.command_log_html.content
        assert f"{forged} unsigned command" in html and "this station" not in html
