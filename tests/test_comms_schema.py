"""Wire schema: every message type round-trips, and decoders only ever raise DecodeError."""

from __future__ import annotations

import math
import random
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from comms import schema
from comms.schema import (
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    DecodeError,
    Event,
    EventKind,
    FeedBatch,
    FeedEntry,
    GuidanceTrace,
    Mode,
    Severity,
    StateFlag,
    VehicleState,
    decode,
)

f32 = st.floats(-1e5, 1e5, allow_nan=False, width=32)
vid = st.integers(1, schema.MAX_VEHICLE_ID)
u64 = st.integers(0, 2**64 - 1)


@st.composite
def states(draw) -> VehicleState:
    return VehicleState(
        vehicle_id=draw(vid),
        seq=draw(st.integers(0, 2**32 - 1)),
        stamp_ns=draw(u64),
        pos_ned_m=tuple(draw(f32) for _ in range(3)),
        vel_ned_m_s=tuple(draw(st.floats(-100, 100, width=32)) for _ in range(3)),
        heading_rad=draw(st.floats(-3.0, 3.0, width=32)),
        mode=draw(st.sampled_from(Mode)),
        armed=draw(st.booleans()),
        battery_pct=draw(st.floats(0.0, 100.0, width=32)),
        flags=StateFlag(draw(st.integers(0, 255))),
        goal_ned_m=tuple(draw(f32) for _ in range(3)),
        sig=draw(st.sampled_from([b"", bytes(64)]) | st.binary(min_size=64, max_size=64)),
    )


@st.composite
def commands(draw) -> Command:
    kind = draw(st.sampled_from(CommandKind))
    if kind is CommandKind.TAKEOFF:
        params = (draw(st.floats(0.5, 500)), 0.0, 0.0)
    elif kind is CommandKind.GOTO_LOCAL:
        params = (
            draw(st.floats(-1e5, 1e5)),
            draw(st.floats(-1e5, 1e5)),
            draw(st.floats(-1e4, 100)),
        )
    elif kind is CommandKind.GOTO_GLOBAL:
        params = (draw(st.floats(-90, 90)), draw(st.floats(-180, 180)), draw(st.floats(-500, 1e4)))
    else:
        params = (0.0, 0.0, 0.0)
    targets = tuple(draw(st.lists(vid, max_size=20, unique=True)))
    return Command(
        kind=kind,
        nonce=draw(u64),
        stamp_ns=draw(u64),
        params=params,
        targets=targets,
        source_id=draw(st.integers(0, schema.MAX_VEHICLE_ID)),
        seq=draw(st.integers(0, 2**32 - 1)),
        tag=draw(st.binary(min_size=64, max_size=64)),
    )


acks = st.builds(
    CommandAck,
    vehicle_id=vid,
    nonce=u64,
    stamp_ns=u64,
    result=st.sampled_from(AckResult),
    reason=st.text(
        st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"), max_size=30
    ),
    mode=st.sampled_from(Mode),
    tag=st.binary(min_size=64, max_size=64),
)
events = st.builds(
    Event,
    vehicle_id=st.integers(0, schema.MAX_VEHICLE_ID),
    stamp_ns=u64,
    text=st.text(
        st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"), max_size=40
    ),
    severity=st.sampled_from(Severity),
    kind=st.sampled_from(EventKind),
    sig=st.sampled_from([b""]) | st.binary(min_size=64, max_size=64),
)


@st.composite
def rosters(draw) -> schema.Roster:
    ids = draw(st.lists(st.tuples(st.sampled_from(schema.Role), vid), max_size=12, unique=True))
    keys = draw(
        st.lists(
            st.binary(min_size=32, max_size=32), min_size=len(ids), max_size=len(ids), unique=True
        )
    )
    members = sorted(
        (schema.Member(r, i, k) for (r, i), k in zip(ids, keys, strict=True)),
        key=lambda m: (int(m.role), m.member_id),
    )
    return schema.Roster(
        fleet=draw(st.from_regex(r"[A-Za-z0-9_-]{1,32}", fullmatch=True)),
        version=draw(st.integers(1, 2**32 - 1)),
        stamp_ns=draw(u64),
        members=tuple(members),
        sig=draw(st.binary(min_size=64, max_size=64)),
    )


@st.composite
def traces(draw) -> GuidanceTrace:
    own = draw(vid)
    ids = draw(st.lists(vid.filter(lambda i: i != own), max_size=30, unique=True))
    return GuidanceTrace(
        vehicle_id=own,
        state_seq=draw(st.integers(0, 2**32 - 1)),
        stamp_ns=draw(u64),
        heading_rad=draw(st.floats(-2 * math.pi, 2 * math.pi)),
        cmd_vel_ned_m_s=tuple(draw(st.floats(-1000, 1000)) for _ in range(3)),
        neighbours=tuple(
            (i, draw(st.integers(0, 2**32 - 1)), draw(st.floats(0.0, schema.MAX_TRACE_AGE_S)))
            for i in ids
        ),
        complete=draw(st.booleans()),
        decided=draw(st.booleans()),
        sig=draw(st.sampled_from([b""]) | st.binary(min_size=64, max_size=64)),
    )


@st.composite
def feed_batches(draw) -> FeedBatch:
    return FeedBatch(
        feed_seq=draw(st.integers(0, 2**32 - 1)),
        entries=tuple(
            FeedEntry(draw(st.integers(0, 2**32 - 1)), s.encode())
            for s in draw(st.lists(states(), min_size=1, max_size=30))  # 30 x 133 + 8 <= 4096
        ),
    )


outcomes = st.builds(
    schema.ActionOutcome,
    vehicle_id=vid,
    nonce=u64,
    ok=st.booleans(),
    detail=st.text(
        st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"), max_size=24
    ),
    stamp_ns=u64,
    sig=st.sampled_from([b""]) | st.binary(min_size=64, max_size=64),
)


@settings(max_examples=300, deadline=None)
@given(st.one_of(states(), commands(), acks, events, rosters(), traces(), feed_batches(), outcomes))
def test_every_message_round_trips(msg) -> None:
    data = msg.encode()
    assert data[0] == msg.TYPE and data[1] == getattr(msg, "VERSION", schema.SCHEMA_VERSION)
    back = decode(data)
    assert type(back) is type(msg)
    assert back == msg
    assert back.encode() == data


def _trace(**kw) -> GuidanceTrace:
    fields = dict(
        vehicle_id=3,
        state_seq=41,
        stamp_ns=10**18,
        heading_rad=0.25,
        cmd_vel_ned_m_s=(0.5, -0.25, 0.0),
        neighbours=((1, 7, 0.1), (2, 9, 0.0)),
    )
    return GuidanceTrace(**{**fields, **kw})


def test_trace_keeps_float64_exactly_and_cuts_long_neighbour_lists() -> None:
    tr = _trace(heading_rad=0.1 + 0.2, cmd_vel_ned_m_s=(1 / 3, -2 / 3, 1e-17), decided=False)
    back = GuidanceTrace.decode(tr.encode())
    assert back == tr and back.heading_rad == 0.1 + 0.2 and not back.decided and back.complete
    n = schema.MAX_TRACE_NEIGHBOURS + 5
    ids = np.arange(2, n + 2)
    built = GuidanceTrace.build(1, 2, 3, np.float64(0.5), np.zeros(3), ids, ids * 10, ids * 1e-3)
    assert not built.complete and len(built.neighbours) == schema.MAX_TRACE_NEIGHBOURS
    assert type(built.neighbours[0][0]) is int and type(built.heading_rad) is float
    data = built.encode()
    assert len(data) + schema.TAG_BYTES <= 4096  # under the ACL routers' message size limit
    assert GuidanceTrace.decode(data) == built


@pytest.mark.parametrize(
    ("trace", "why"),
    [
        (lambda: _trace(vehicle_id=0), "vehicle_id=0"),
        (lambda: _trace(heading_rad=math.nan), "heading_rad must be finite"),
        (lambda: _trace(heading_rad=7.0), "heading_rad=7.0 is outside"),
        (lambda: _trace(cmd_vel_ned_m_s=(0.0, math.inf, 0.0)), "must be finite"),
        (lambda: _trace(cmd_vel_ned_m_s=(0.0, 0.0)), "2 axes"),
        (lambda: _trace(cmd_vel_ned_m_s=(1e4, 0.0, 0.0)), "outside"),
        (lambda: _trace(neighbours=((3, 1, 0.1),)), "lists itself"),
        (lambda: _trace(neighbours=((1, 1, 0.1), (1, 2, 0.2))), "listed twice"),
        (lambda: _trace(neighbours=((1, 1, -0.5),)), "age_s=-0.5 is outside"),
        (lambda: _trace(neighbours=((1, 1, math.nan),)), "age_s must be finite"),
        (lambda: _trace(neighbours=((1, 2**32, 0.0),)), "does not fit 32 bits"),
        (lambda: _trace(state_seq=-1), "does not fit 32 bits"),
        (lambda: _trace(sig=b"x"), "signature must be empty or 64"),
        (
            lambda: _trace(neighbours=tuple((i, 0, 0.0) for i in range(4, 300))),
            "at most 256",
        ),
    ],
)
def test_trace_refuses_bad_fields(trace, why) -> None:
    with pytest.raises(DecodeError, match=why):
        trace().encode()


@pytest.mark.parametrize(
    ("mutate", "why"),
    [
        (lambda b: b[:-1], "must be 79 bytes"),
        (lambda b: b + bytes(64) + b"x", "must be 79 bytes"),
        (lambda b: b[:10], "too short"),
        (lambda b: b[:1] + bytes([2]) + b[2:], "unsupported GUIDANCE_TRACE version 2"),
        (lambda b: b[:49] + struct.pack("<H", 3) + b[51:], "3 neighbours must be 93 bytes"),
        (lambda b: b[:49] + struct.pack("<H", 65535) + b[51:], "65535 neighbours, at most 256"),
        (lambda b: b[:48] + bytes([4]) + b[49:], "unknown bits"),
        (lambda b: b[:16] + struct.pack("<d", math.nan) + b[24:], "heading_rad must be finite"),
        (lambda b: b[:57] + struct.pack("<d", math.inf) + b[65:], "age_s must be finite"),
        (lambda b: b[:51] + struct.pack("<H", 3) + b[53:], "lists itself"),
    ],
)
def test_trace_decoder_says_why(mutate, why) -> None:
    good = _trace(neighbours=((1, 7, 0.1), (2, 9, 0.0))).encode()
    assert len(good) == 51 + 2 * 14
    with pytest.raises(DecodeError, match=why):
        decode(mutate(good))


def _feed(n: int, signed: bool = False, size: int | None = None) -> FeedBatch:
    one = VehicleState(3, 1, 5, (1, 2, 3), (0, 0, 0), 0.5, sig=bytes(64) if signed else b"")
    data = one.encode() if size is None else bytes(size)
    return FeedBatch(7, tuple(FeedEntry(k + 1, data) for k in range(n)))


@pytest.mark.parametrize(
    ("batch", "why"),
    [
        (_feed(0), "0 feed entries, must be 1..54"),
        (_feed(55), "55 feed entries, must be 1..54"),
        (_feed(30, signed=True), "FeedBatch of 4178 bytes, at most 4096"),
        (_feed(2, size=63), "entry 0: a state is 70 or 134 bytes, not 63"),
        (FeedBatch(2**32, _feed(1).entries), "feed_seq=4294967296 does not fit"),
        (FeedBatch(1, (FeedEntry(-1, _feed(1).entries[0].state),)), "entry_seq=-1 does not fit"),
    ],
)
def test_feed_batch_refuses_what_it_cannot_carry(batch, why) -> None:
    with pytest.raises(DecodeError, match=why):
        batch.encode()


def test_feed_batch_holds_54_unsigned_or_29_signed_states() -> None:
    assert FeedBatch.MAX_ENTRIES == 54
    for batch in (_feed(54), _feed(29, signed=True)):
        data = batch.encode()
        assert len(data) <= schema.MAX_FEED_BYTES and decode(data) == batch
    # The entries are carried as bytes, not checked: the receiver decodes each on its own.
    junk = FeedBatch(1, (FeedEntry(1, bytes(70)),))
    assert decode(junk.encode()) == junk
    with pytest.raises(DecodeError):
        VehicleState.decode(junk.entries[0].state)


def test_reason_text_is_cut_on_a_character_boundary() -> None:
    ack = CommandAck(1, 2, 3, AckResult.REJECTED, "é" * 200)
    back = decode(ack.encode())
    assert back.reason == "é" * (schema.REASON_BYTES // 2)


@pytest.mark.parametrize(
    ("mutate", "why"),
    [
        (lambda b: b[:-1], "must be 70 bytes"),
        (lambda b: bytes([99]) + b[1:], "unknown message type 99"),
        (lambda b: b[:1] + bytes([7]) + b[2:], "unsupported VEHICLE_STATE version 7"),
        (lambda b: b[:16] + struct.pack("<f", math.nan) + b[20:], "must be finite"),
        (lambda b: b[:16] + struct.pack("<f", math.inf) + b[20:], "must be finite"),
        (lambda b: b[:56] + bytes([99]) + b[57:], "not a valid Mode"),
        (lambda b: b[:2] + struct.pack("<H", 0) + b[4:], "vehicle_id=0"),
    ],
)
def test_state_decoder_says_why(mutate, why) -> None:
    good = VehicleState(3, 1, 5, (1, 2, 3), (0, 0, 0), 0.5).encode()
    with pytest.raises(DecodeError, match=why):
        decode(mutate(good))


@pytest.mark.parametrize(
    ("params", "kind", "why"),
    [
        ((math.nan, 0, 0), CommandKind.TAKEOFF, "must be finite"),
        ((1000.0, 0, 0), CommandKind.TAKEOFF, "outside"),
        ((0, 0, 0), CommandKind.TAKEOFF, "outside"),
        ((91.0, 0, 0), CommandKind.GOTO_GLOBAL, "lat_deg"),
        ((1.0, 0, 0), CommandKind.LAND, "unused ones must be 0"),
    ],
)
def test_command_validation_rejects_bad_fields(params, kind, why) -> None:
    with pytest.raises(DecodeError, match=why):
        Command(kind=kind, nonce=1, stamp_ns=1, params=params).encode()


def test_command_with_wrong_target_count_is_refused() -> None:
    data = bytearray(Command(CommandKind.LAND, 1, 1, targets=(1, 2)).encode())
    struct.pack_into("<H", data, 49, 3)  # claims 3 targets, carries 2
    with pytest.raises(DecodeError, match="3 targets must be"):
        decode(bytes(data))


def test_random_bytes_only_raise_decode_error() -> None:
    """10,000 random byte strings plus 10,000 mutations of valid messages."""
    rng = random.Random(1234)
    valid = [
        VehicleState(3, 1, 5, (1, 2, 3), (0, 0, 0), 0.5).encode(),
        Command.goto_local(1, 2, -3, nonce=7, stamp_ns=9, targets=(1, 2)).encode(),
        CommandAck(1, 7, 9, AckResult.REJECTED, "no").encode(),
        Event(1, 5, "hi").encode(),
    ]
    decoded = rejected = 0
    for i in range(20_000):
        if i < 10_000:
            data = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 200)))
            if data and rng.random() < 0.5:  # half of them get a plausible header
                data = bytes([rng.randrange(1, 5), 1]) + data[2:]
        else:
            data = bytearray(rng.choice(valid))
            for _ in range(rng.randrange(1, 4)):
                data[rng.randrange(len(data))] = rng.getrandbits(8)
            data = bytes(data)
        try:
            decode(data)
            decoded += 1
        except DecodeError:
            rejected += 1
    assert decoded + rejected == 20_000
    assert rejected > 10_000  # nearly all random strings are invalid
    print(f"fuzz: {decoded} decoded, {rejected} rejected with DecodeError")


def test_float32_positions_keep_centimetres_at_10_km() -> None:
    s = VehicleState(1, 1, 1, (9999.987, -9999.993, -120.004), (0, 0, 0), 0.0)
    back = decode(s.encode())
    assert np.allclose(back.pos_ned_m, s.pos_ned_m, atol=0.005)


def test_nul_in_text_is_sent_as_replacement_character():
    """NUL pads text fields on the wire; a NUL in the text must not vanish or cut the text."""
    ack = CommandAck(1, 0, 0, AckResult.REJECTED, "bad\0", Mode.LANDED)
    assert CommandAck.decode(ack.encode()).reason == "bad\ufffd"
    ev = Event(1, 0, "a\0b")
    assert Event.decode(ev.encode()).text == "a\ufffdb"
    raw = bytearray(Event(1, 0, "ab").encode())
    raw[-1] = 0x41  # a byte after the padding: not a text this codec writes
    with pytest.raises(DecodeError, match="after its NUL padding"):
        Event.decode(bytes(raw))


_EDGES = (
    0.0,
    -0.0,
    1.5,
    math.nan,
    math.inf,
    -math.inf,
    schema.POSITION_LIMIT_M,
    -schema.POSITION_LIMIT_M,
    math.nextafter(schema.POSITION_LIMIT_M, math.inf),
    schema.SPEED_LIMIT_M_S,
    math.nextafter(schema.SPEED_LIMIT_M_S, math.inf),
    -math.nextafter(schema.SPEED_LIMIT_M_S, math.inf),
    2 * math.pi,
    math.nextafter(2 * math.pi, math.inf),
    100.0,
    100.5,
    -1e-9,
)


@settings(max_examples=3000, deadline=None)
@given(
    vid=st.sampled_from((0, 1, 7, schema.MAX_VEHICLE_ID, schema.MAX_VEHICLE_ID + 1)),
    seq=st.sampled_from((0, 5, 2**32 - 1, 2**32, -1)),
    stamp=st.sampled_from((0, 10**18, 2**64 - 1, 2**64, -1)),
    floats=st.lists(st.sampled_from(_EDGES), min_size=11, max_size=11),
    mode=st.sampled_from((*Mode, 0, 99)),
    flags=st.sampled_from((0, 1, 0xFF, 0x100)),
    sig=st.sampled_from((b"", bytes(schema.TAG_BYTES), b"x")),
)
def test_state_validate_fast_path_accepts_exactly_what_the_reference_accepts(
    vid, seq, stamp, floats, mode, flags, sig
) -> None:
    """VehicleState.validate's one-comparison fast path against its reasoned checks."""
    s = VehicleState(
        vid,
        seq,
        stamp,
        tuple(floats[0:3]),
        tuple(floats[3:6]),
        floats[6],
        mode,
        False,
        floats[7],
        flags,
        tuple(floats[8:11]),
        sig,
    )

    def verdict(check) -> str | None:
        try:
            check()
        except DecodeError as exc:
            return str(exc)
        return None

    fast, reference = verdict(s.validate), verdict(s._validate_reasoned)
    assert fast == reference  # same refusal, with the reference's reason
