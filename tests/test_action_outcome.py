"""The autopilot's outcome of a command as a message of its own (comms/schema.py ActionOutcome):
round trip, decoders that say why, fuzz, its signature, a receiver that outlives bad bytes on the
event key, a station that counts each ack and outcome once, and a real agent process whose
take-off reaches the station's command log once, as done."""

from __future__ import annotations

import dataclasses
import random
import re
import struct
import time

import pytest
from conftest import keyed_agent_argv, wait_until
from hypothesis import given, settings
from hypothesis import strategies as st

from comms import keys, schema
from comms.gate import Gate, Refusal
from comms.schema import (
    OUTCOME_DETAIL_BYTES,
    AckResult,
    ActionOutcome,
    Command,
    CommandAck,
    CommandKind,
    DecodeError,
    Event,
    EventKind,
    Mode,
    Role,
    decode,
    decode_event_message,
)
from groundstation.command_log import CommandLog, Status
from trust.auth import FleetAuth, load_auth
from trust.authority import Authority, throwaway_fleet
from trust.heartbeat import NO_STATION

S = 1_000_000_000


def outcome(**kw) -> ActionOutcome:
    fields = dict(vehicle_id=3, nonce=0x5FBFE957, ok=True, detail="takeoff to 5 m", stamp_ns=7)
    return ActionOutcome(**{**fields, **kw})


# -- the wire --------------------------------------------------------------------------------
@settings(max_examples=300, deadline=None)
@given(
    st.builds(
        ActionOutcome,
        vehicle_id=st.integers(1, schema.MAX_VEHICLE_ID),
        nonce=st.integers(0, 2**64 - 1),
        ok=st.booleans(),
        detail=st.text(
            st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"), max_size=24
        ),  # <= 96 bytes
        stamp_ns=st.integers(0, 2**64 - 1),
        sig=st.sampled_from([b""]) | st.binary(min_size=64, max_size=64),
    )
)
def test_an_outcome_round_trips_through_both_decoders(msg: ActionOutcome) -> None:
    data = msg.encode()
    assert data[:2] == bytes([schema.MsgType.ACTION_OUTCOME, ActionOutcome.VERSION])
    assert decode(data) == msg and decode_event_message(data) == msg
    assert decode(data).encode() == data


def test_a_long_detail_is_cut_on_a_character_boundary_and_its_kind_shows_as_action() -> None:
    long = outcome(detail="✈" * 100, ok=False)  # 300 bytes of UTF-8
    back = ActionOutcome.decode(long.encode())
    assert back.detail == "✈" * (OUTCOME_DETAIL_BYTES // 3)
    assert len(long.encode()) == 22 + OUTCOME_DETAIL_BYTES
    assert back.kind is EventKind.ACTION and back.severity is schema.Severity.ERROR
    assert outcome().severity is schema.Severity.INFO


def _with(data: bytes, offset: int, fmt: str, value: int) -> bytes:
    b = bytearray(data)
    struct.pack_into(fmt, b, offset, value)
    return bytes(b)


GOOD = outcome(detail="land").encode()  # 22 + 4 bytes


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b"", "too short for a header"),
        (_with(GOOD, 0, "B", schema.MsgType.EVENT), "expected message type 12, got 4"),
        (_with(GOOD, 1, "B", 2), "unsupported ACTION_OUTCOME version 2"),
        (GOOD[:10], "needs at least 22 bytes, got 10"),
        (GOOD[:-1], "with 4 detail bytes must be 26 bytes (+64 signed), got 25"),
        (GOOD + b"x", "must be 26 bytes (+64 signed), got 27"),
        (_with(GOOD, 20, "B", 2), "ok=2 must be 0 or 1"),
        (_with(GOOD, 21, "B", 97), "detail length 97 is over 96 bytes"),
        (GOOD[:22] + b"\xff\xfeab", "detail is not valid UTF-8"),
        (GOOD[:22] + b"la\0d", "detail holds a NUL byte"),
        (_with(GOOD, 2, "<H", 0), "vehicle_id=0 is outside [1, 65000]"),
    ],
)
def test_the_decoder_refuses_with_its_reason(data: bytes, why: str) -> None:
    with pytest.raises(DecodeError, match=re.escape(why)):
        ActionOutcome.decode(data)
    with pytest.raises(DecodeError):
        decode_event_message(data)


def test_the_event_key_carries_events_and_outcomes_and_nothing_else() -> None:
    ev = Event(3, 1, "battery low", kind=EventKind.FAILSAFE)
    assert decode_event_message(ev.encode()) == ev
    ack = CommandAck(3, 1, 1, AckResult.ACCEPTED, "", Mode.LANDED, bytes(64))
    with pytest.raises(
        DecodeError, match="expected an Event or an ActionOutcome, got message type 3"
    ):
        decode_event_message(ack.encode())
    with pytest.raises(DecodeError, match="none \\(empty\\)"):
        decode_event_message(b"")


def test_mutated_and_random_outcomes_only_raise_decode_error() -> None:
    rng = random.Random(38)
    seeds = [outcome(detail="✈ arming denied", ok=False).encode(), outcome(sig=bytes(64)).encode()]
    refused = 0
    for i in range(3000):
        data = bytearray(seeds[i % 2])
        for _ in range(rng.randint(1, 4)):
            op = rng.random()
            if op < 0.5 and data:
                data[rng.randrange(len(data))] = rng.randrange(256)
            elif op < 0.75:
                data = data[: rng.randrange(len(data) + 1)]
            else:
                data += bytes(rng.randrange(256) for _ in range(rng.randint(1, 70)))
        for decoder in (decode, decode_event_message):
            try:
                back = decoder(bytes(data))
            except DecodeError:
                refused += 1
            else:
                if isinstance(back, ActionOutcome):  # what decodes is valid and re-encodes
                    assert decode(back.encode()) == back
    for _ in range(1000):
        data = bytes([12, 1]) + bytes(rng.randrange(256) for _ in range(rng.randint(0, 200)))
        try:
            decode(data)
        except DecodeError:
            refused += 1
    assert refused > 2000  # the mutations do reach the checks


# -- its signature ---------------------------------------------------------------------------
@pytest.fixture
def fleet(tmp_path) -> Authority:
    return throwaway_fleet(tmp_path / "keys", "covey", vehicles=range(1, 4), stations=[1])


def member(fleet: Authority, role: Role, mid: int) -> FleetAuth:
    return load_auth(str(fleet.member_path(role, mid)))


def test_an_outcome_is_signed_by_its_vehicle_under_its_own_label(fleet) -> None:
    v3, v2 = member(fleet, Role.VEHICLE, 3), member(fleet, Role.VEHICLE, 2)
    gate = Gate(member(fleet, Role.STATION, 1), what="event")
    now = time.time_ns()
    msg = outcome(stamp_ns=now)
    signed = ActionOutcome.decode(v3.sign_outcome(msg).encode())  # the signature survives
    assert gate.admit_event(signed, now) is None
    assert gate.admit_event(msg, now) is Refusal.UNSIGNED
    assert gate.admit_event(v2.sign_outcome(msg), now) is Refusal.FORGED  # another vehicle
    flipped = dataclasses.replace(signed, ok=False, detail="takeoff to 5 m: arming denied")
    assert gate.admit_event(flipped, now) is Refusal.FORGED  # done turned into failed
    # A vehicle's event signature over the same bytes is no outcome signature (own label).
    as_event = dataclasses.replace(msg, sig=v3._sign("event", msg.signed_bytes()))
    assert gate.admit_event(as_event, now) is Refusal.FORGED
    assert gate.admit_event(v3.sign_outcome(msg), now + 3600 * S) is Refusal.STALE


# -- one receiver, bad bytes -----------------------------------------------------------------
@pytest.mark.e2e
def test_bad_bytes_on_the_event_key_never_stop_the_receiver() -> None:
    """Real Zenoh on loopback: garbage, a truncated outcome and an outcome of a future version
    are counted as malformed; the events and outcomes after them still arrive."""
    from comms.mesh import Mesh
    from comms.session import embedded_peer, embedded_router, free_tcp_port

    port = free_tcp_port()
    got: list[object] = []
    with Mesh(embedded_router(port)) as hub, Mesh(embedded_peer(port)) as vehicle:
        hub.subscribe_events(lambda e, _t: got.append(e), on_outcome=lambda o, _t: got.append(o))
        silent: list[object] = []
        hub.subscribe_events(lambda e, _t: silent.append(e))  # no on_outcome: outcomes unread
        time.sleep(0.5)  # the subscriptions reach the peer
        good = outcome(stamp_ns=vehicle.clock_ns())
        bad = [b"\x0c", good.encode()[:-2], _with(good.encode(), 1, "B", 9), b"\xff" * 40]
        for data in bad:
            vehicle.session.put(keys.event(vehicle.fleet, 3), data)
        vehicle.publish_outcome(good)
        vehicle.event(3, "after the garbage")
        assert wait_until(lambda: len(got) == 2, 10), got
        assert got[0] == good and isinstance(got[1], Event)
        assert wait_until(lambda: len(silent) == 1, 5) and isinstance(silent[0], Event)
        assert hub.stats.decode_errors >= len(bad)


# -- one ack, one outcome per (vehicle, nonce) -----------------------------------------------
def _ack(vid: int, nonce: int, result=AckResult.ACCEPTED, reason="") -> CommandAck:
    return CommandAck(vid, nonce, 2 * S, result, reason, Mode.TAKING_OFF, bytes(64))


def test_the_station_counts_each_ack_and_outcome_once() -> None:
    log = CommandLog()
    log.on_command(Command(CommandKind.TAKEOFF, nonce=9, stamp_ns=1, params=(5, 0, 0)), S)
    log.on_ack(_ack(3, 9), 2 * S)
    version = log.version
    log.on_ack(_ack(3, 9), 2 * S)  # the same answer again (two paths, two routers)
    # The vehicle's refusal of the same command sent again must not flip its first answer.
    log.on_ack(
        _ack(3, 9, AckResult.REJECTED, "replayed command: nonce 0x9 was already used"), 3 * S
    )
    assert log.version == version and log.duplicate_acks == 2
    (entry,) = log.entries()
    assert entry.answers[3].result is AckResult.ACCEPTED
    assert log.on_outcome(ActionOutcome(3, 9, True, "takeoff to 5 m", 3 * S))
    assert not log.on_outcome(ActionOutcome(3, 9, False, "takeoff: late copy", 3 * S))
    assert log.duplicate_outcomes == 1
    (entry,) = log.entries()
    assert entry.done[3].ok and entry.progress(3, 4 * S, 3.0, None).status is Status.ACCEPTED
    # An ack that overtook its command, twice: one answer once the command arrives.
    log.on_ack(_ack(4, 10), 5 * S)
    log.on_ack(_ack(4, 10), 5 * S)
    log.on_command(Command(CommandKind.LAND, nonce=10, stamp_ns=2, targets=(4,)), 5 * S)
    assert log.entries()[0].answers.keys() == {4} and log.duplicate_acks == 3


# -- a real agent process --------------------------------------------------------------------
@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.parametrize("keyed", [False, True], ids=["open", "keyed"])
def test_a_takeoffs_outcome_reaches_the_station_log_once_as_done(procs, tmp_path, keyed) -> None:
    """A `covey agent` process and a ground station on one Zenoh router: the station sends a
    take-off itself, so its ack reaches the station twice (the query's reply and the copy on
    msg/<id>/ack); its command log holds one answer, one outcome (done), and shows the
    take-off done once the vehicle holds at altitude. Keyed: the agent signs the outcome with
    its key file and the station's gate checks it."""
    from comms.commands import new_nonce
    from comms.mesh import Mesh
    from comms.session import embedded_peer, embedded_router, free_tcp_port
    from groundstation.station import GcsConfig, GroundStation

    vid = 3
    port = free_tcp_port()
    authority = throwaway_fleet(tmp_path / "keys", "covey", vehicles=[vid], stations=[1])
    argv = keyed_agent_argv(authority, vid) if keyed else ["-m", "covey_cli", "agent", "--id", "3"]
    key_file = str(authority.member_path(Role.STATION, 1)) if keyed else None
    with Mesh(embedded_router(port)) as hub:
        presence = hub.presence()
        procs.start(*argv, "--connect", f"tcp/127.0.0.1:{port}")
        assert presence.wait_for(lambda v, _g: vid in v, timeout_s=60), "the agent never came"
        with GroundStation(GcsConfig(mesh=embedded_peer(port), port=0, key_file=key_file)) as gcs:
            assert gcs.mesh is not None
            assert wait_until(lambda: vid in gcs.fleet.ids(), 30), "no state reached the station"
            # the agent refuses a take-off until it has heard this station's first heartbeat
            # (trust/heartbeat.py NO_STATION); on a busy machine that can come after its state
            deadline = time.monotonic() + 20.0
            while True:
                cmd = Command.takeoff(3.0, nonce=new_nonce(), stamp_ns=0, targets=(vid,))
                res = gcs.mesh.send_command(cmd, expect=(vid,), timeout_s=10)
                reply = res.outcomes[vid].ack
                if reply is None or NO_STATION not in reply.reason:
                    break
                assert time.monotonic() < deadline, reply.reason
                time.sleep(0.5)
            assert reply is not None and reply.result is AckResult.ACCEPTED  # the reply path

            def entry():
                return next(
                    (e for e in gcs.commands.entries() if e.command.nonce == cmd.nonce), None
                )

            assert wait_until(lambda: entry() is not None and vid in entry().done, 30), entry()
            assert wait_until(
                lambda: entry().progress(vid, gcs.mesh.clock_ns(), 3.0, None).status is Status.DONE,
                60,
            ), entry()
            done = entry()
            assert list(done.answers) == [vid] and done.answers[vid].result is AckResult.ACCEPTED
            assert done.done[vid].ok and "takeoff" in done.done[vid].detail
            assert done.done[vid].nonce == cmd.nonce
            assert gcs.commands.duplicate_acks == 0 and gcs.commands.duplicate_outcomes == 0
            assert (gcs.mesh.auth is not None) is keyed
            assert any(done.done[vid].sig) is keyed  # keyed: signed, and the gate let it in
            outcomes = [ev for _, ev in gcs.events.latest(EventKind.ACTION, n=50)]
            assert [o for o in outcomes if isinstance(o, ActionOutcome)] == [done.done[vid]]
