"""The shared command log and the per-kind event buffer: bounded, and one truth for every station."""

from __future__ import annotations

from comms.schema import AckResult, Command, CommandAck, CommandKind, Event, EventKind, Severity
from groundstation.command_log import CommandLog, CommandLogConfig
from groundstation.events import EventBuffer, EventsConfig


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
    assert e.describe() == "goto N 1 E 2 D -3 m → 1,2"


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
