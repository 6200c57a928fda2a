"""Fuzz every wire decoder with random and mutated inputs (seeded, so a failure reproduces).

Each input must either decode into a message that re-encodes to the same bytes, or raise
DecodeError with a non-empty reason; nothing else may escape, and no input may take long.
Decoded commands, acks, states, events and rosters also go through the keyed-mode checks
(FleetAuth: signature, roster, freshness), which must answer a reason string or accept only the
exact signed original: mutated signatures and rosters are refused, never a crash.
"""

from __future__ import annotations

import random
import struct
import time

import pytest

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
    Mission,
    MissionFrame,
    MissionItem,
    MissionItemKind,
    Mode,
    Role,
    Roster,
    Severity,
    StateFlag,
    VehicleState,
    decode,
)
from trust.auth import FleetAuth, command_digest, load_auth
from trust.authority import throwaway_fleet

SEED = 20261122
N_MUTATED = 60_000
N_RANDOM = 20_000
SLOWEST_INPUT_S = 2.0
"""A hang guard, not a benchmark: the machine is shared, so only a stuck decoder trips it.
The slowest input is printed."""


def valid_messages(rng: random.Random, keys: dict | None = None) -> list[bytes]:
    out = [
        VehicleState(
            3,
            42,
            10**18,
            (1.0, -2.0, -10.0),
            (0.5, 0.0, 0.0),
            0.3,
            Mode.GOTO,
            True,
            88.0,
            StateFlag.HAS_GOAL | StateFlag.OPEN_MODE,
            (5.0, 5.0, -10.0),
        ).encode(),
        Command.takeoff(10.0, nonce=9, stamp_ns=1, targets=(1, 2, 3)).encode(),
        Command.goto_local(10.0, -5.0, -8.0, nonce=10, stamp_ns=2).encode(),
        Command.goto_global(47.4, 8.5, 500.0, nonce=11, stamp_ns=3, targets=(7,)).encode(),
        Command(CommandKind.KILL, 12, 4, targets=tuple(range(1, 200))).encode(),
        CommandAck(5, 9, 1, AckResult.REJECTED, "too high — über", Mode.HOLDING).encode(),
        Event(2, 1, "battery low ✈", Severity.WARNING, EventKind.FAILSAFE).encode(),
        Mission(
            13,
            5,
            (
                MissionItem(MissionItemKind.TAKEOFF, alt_m=8.0),
                MissionItem(MissionItemKind.WAYPOINT, MissionFrame.GLOBAL, 48.75, 9.1, 470.0),
                MissionItem(MissionItemKind.WAYPOINT, x=10.0, y=-4.0, alt_m=8.0, hold_s=2.0),
                MissionItem(MissionItemKind.LAND),
            ),
            targets=(1, 2),
        ).encode(),
    ]
    if keys is not None:
        station, vehicle = keys["station"], keys["vehicle"]
        cmd = station.sign_command(Command(CommandKind.HOLD, 0, 0, targets=(4,)))
        out.append(cmd.encode())
        ack = CommandAck(1, cmd.nonce, 5, AckResult.ACCEPTED, "", Mode.HOLDING)
        out.append(vehicle.sign_ack(ack, command_digest(cmd.encode())).encode())
        out.append(
            vehicle.sign_state(
                VehicleState(1, 7, 10**18, (1.0, 2.0, -3.0), (0.0, 0.0, 0.0), 0.1)
            ).encode()
        )
        out.append(
            vehicle.sign_event(
                Event(1, 10**18, "signed", Severity.WARNING, EventKind.SECURITY)
            ).encode()
        )
        out.append(keys["newer_roster"].encode())
        keys["cmd"] = cmd
    return out


INTERESTING = [
    b"\x00",
    b"\xff",
    b"\x7f",
    b"\x80",
    struct.pack("<f", float("nan")),
    struct.pack("<d", float("inf")),
    struct.pack("<H", 65535),
    struct.pack("<I", 2**32 - 1),
    b"\xff\xff",
    b"\x00\x00",
]


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One to four of: flip bits, set interesting bytes, insert, delete, truncate, extend, splice."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(8)
        if op == 0 and b:
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and b:
            v = rng.choice(INTERESTING)
            i = rng.randrange(len(b))
            b[i : i + len(v)] = v
        elif op == 2:
            i = rng.randrange(len(b) + 1)
            b[i:i] = rng.randbytes(rng.randint(1, 8))
        elif op == 3 and b:
            i = rng.randrange(len(b))
            del b[i : i + rng.randint(1, 8)]
        elif op == 4:
            b = b[: rng.randrange(len(b) + 1)]
        elif op == 5:
            b += rng.randbytes(rng.randint(1, 64))
        elif op == 6 and len(b) > 2:
            b[rng.randrange(2, len(b))] = rng.randrange(256)  # payload byte, header intact
        elif op == 7 and len(b) > 60:
            # Command target count: a lie about how many targets follow.
            b[49:51] = struct.pack("<H", rng.choice([0, 1, 2, 1023, 1024, 1025, 65535]))
    return bytes(b)


def check_one(data: bytes, keys: dict, stats: dict[str, int]) -> None:
    vehicle: FleetAuth = keys["vehicle"]
    t0 = time.perf_counter()
    try:
        msg = decode(data)
    except DecodeError as exc:
        assert str(exc), f"empty DecodeError for {data.hex()}"
        stats["rejected"] += 1
    else:
        assert msg.encode() == data, f"decoded but does not round-trip: {data.hex()}"
        stats["decoded"] += 1
        if isinstance(msg, Mission):
            reason = vehicle.check_mission(msg, 1)  # unsigned seeds: never accepted
            assert isinstance(reason, str) and reason, "a mutated mission verified"
        elif isinstance(msg, Command):
            reason = vehicle.check_command(msg, 1)
            assert reason is None or isinstance(reason, str)
        elif isinstance(msg, CommandAck):
            cmd = keys["cmd"]
            reason = keys["station"].check_ack(msg, cmd, command_digest(cmd.encode()))
            assert reason is None or (isinstance(reason, str) and reason.startswith("forged ack"))
            assert reason is not None or data == keys["valid"]["ack"], "a mutated ack verified"
        elif isinstance(msg, VehicleState | Event):
            check = vehicle.check_state if isinstance(msg, VehicleState) else vehicle.check_event
            reason = check(msg)
            assert reason is None or isinstance(reason, str)
            assert reason is not None or data in keys["valid"].values(), (
                "a mutated state/event verified"
            )
        elif isinstance(msg, GuidanceTrace):
            reason = vehicle.check_trace(msg)
            assert reason is None or isinstance(reason, str)
            assert reason is not None or data == keys.get("valid_trace"), "a mutated trace verified"
        elif isinstance(msg, FeedBatch):
            for entry in msg.entries:  # as the station does: each entry on its own
                try:
                    state = VehicleState.decode(entry.state)
                except DecodeError as exc:
                    assert str(exc)
                    continue
                reason = vehicle.check_state(state)
                assert reason is None or isinstance(reason, str)
                assert reason is not None or entry.state == keys["valid"]["state"], (
                    "a mutated feed entry verified"
                )
        elif isinstance(msg, Roster):
            reason = vehicle.apply_roster(msg)  # never newer AND genuine unless unmutated
            assert reason is not None or data == keys["valid"]["roster"], "a mutated roster applied"
            if reason is None:
                keys["reset"]()
    # Also through the typed decoders: they must refuse foreign types with DecodeError too.
    for cls in (
        VehicleState,
        Command,
        CommandAck,
        Event,
        Roster,
        GuidanceTrace,
        FeedBatch,
        Mission,
    ):
        try:
            cls.decode(data)
        except DecodeError:
            pass
    elapsed_s = time.perf_counter() - t0
    stats["slowest_us"] = max(stats["slowest_us"], int(elapsed_s * 1e6))
    assert elapsed_s < SLOWEST_INPUT_S, f"{elapsed_s * 1e3:.1f} ms for {data[:32].hex()}..."


@pytest.fixture
def auth(tmp_path):
    """A throwaway fleet: station 1's and vehicle 1's FleetAuth, and a newer genuine roster."""
    import dataclasses
    import logging

    logger = logging.getLogger("trust.auth")
    level = logger.level
    logger.setLevel(logging.CRITICAL)  # thousands of refusals
    authority = throwaway_fleet(tmp_path / "keys", "fuzz", vehicles=[1, 4], stations=[1])
    first = authority.roster
    authority.add(Role.VEHICLE, 9)
    clock = lambda: 10**18  # noqa: E731 - every stamp in the seeds is "now"
    keys = {
        "station": load_auth(str(authority.member_path(Role.STATION, 1)), clock_ns=clock),
        "vehicle": load_auth(str(authority.member_path(Role.VEHICLE, 1)), clock_ns=clock),
        "newer_roster": authority.roster,
    }

    base = keys["vehicle"].key

    def reset() -> None:  # back to the first roster, so that the genuine newer one applies again
        keys["vehicle"] = FleetAuth(dataclasses.replace(base, roster=first), clock_ns=clock)

    keys["reset"] = reset
    reset()
    seeds = valid_messages(random.Random(0), keys)
    keys["valid"] = {
        "cmd": seeds[-5],
        "ack": seeds[-4],
        "state": seeds[-3],
        "event": seeds[-2],
        "roster": seeds[-1],
    }
    yield keys
    logger.setLevel(level)  # other tests read this logger's warnings


def test_mutated_valid_messages_only_raise_decode_error(auth) -> None:
    rng = random.Random(SEED)
    seeds = valid_messages(rng) + list(auth["valid"].values())  # the signed ones last
    stats = {"decoded": 0, "rejected": 0, "slowest_us": 0}
    for i in range(N_MUTATED):
        check_one(mutate(seeds[i % len(seeds)], rng), auth, stats)
    for data in seeds[-5:]:  # control: the unmutated signed originals do pass
        check_one(data, auth, stats)
    print(f"fuzz mutated: {N_MUTATED} inputs, {stats}")
    assert stats["decoded"] > 100 and stats["rejected"] > 1000  # the mutator reaches both sides


def test_random_bytes_only_raise_decode_error(auth) -> None:
    rng = random.Random(SEED + 1)
    stats = {"decoded": 0, "rejected": 0, "slowest_us": 0}
    for _ in range(N_RANDOM):
        n = rng.choice([0, 1, 2, 3, 64, 83, 150, 134, rng.randrange(4096)])
        head = bytes(
            [rng.randint(0, 5), rng.choice([1, 1, 1, 0, 2, 255])]
        )  # mostly plausible headers
        check_one((head + rng.randbytes(n))[:n] if n >= 2 else rng.randbytes(n), auth, stats)
    check_one(b"\x02\x01" + bytes(10**6), auth, stats)  # a 1 MB command
    print(f"fuzz random: {N_RANDOM + 1} inputs, {stats}")


def test_decode_accepts_every_bytes_like_type() -> None:
    data = Event(2, 1, "x").encode()
    assert decode(bytearray(data)) == decode(memoryview(data)) == decode(data)


def test_mutated_and_random_traces_only_raise_decode_error(auth) -> None:
    """Guidance traces: mutated (unsigned, signed, a full neighbour list) and random bodies."""
    rng = random.Random(SEED + 2)
    many = tuple((i, i * 7, i * 1e-3) for i in range(2, 258))
    unsigned = [
        GuidanceTrace(3, 41, 10**18, 0.3, (0.5, -0.25, 0.0), ((1, 7, 0.1), (2, 9, 0.0))),
        GuidanceTrace(3, 0, 0, -3.0, (0.0, 0.0, 0.0), (), complete=False, decided=False),
        GuidanceTrace(1, 5, 10**18, 1.0, (1.0, 1.0, 0.0), many, complete=False),
    ]
    signed = auth["vehicle"].sign_trace(
        GuidanceTrace(1, 8, 10**18, 0.1, (0.2, 0.0, 0.0), ((4, 2, 0.25),))
    )
    auth["valid_trace"] = signed.encode()
    seeds = [t.encode() for t in unsigned] + [auth["valid_trace"]]
    stats = {"decoded": 0, "rejected": 0, "slowest_us": 0}
    for i in range(20_000):
        check_one(mutate(seeds[i % len(seeds)], rng), auth, stats)
    for _ in range(5_000):
        n = rng.choice([51, 65, 79, 143, rng.randrange(4096)])
        check_one((bytes([6, 1]) + rng.randbytes(n))[:n], auth, stats)
    check_one(auth["valid_trace"], auth, stats)  # control: the signed original verifies
    print(f"fuzz traces: 25001 inputs, {stats}")
    assert stats["decoded"] > 100 and stats["rejected"] > 1000


def test_mutated_and_random_feed_batches_only_raise_decode_error(auth) -> None:
    """Feed batches: mutated (unsigned, signed, mixed, full) and random bodies; the entries of
    those that decode are decoded and verified one by one, as the station does."""
    rng = random.Random(SEED + 3)
    unsigned = VehicleState(3, 42, 10**18, (1.0, -2.0, -10.0), (0.5, 0.0, 0.0), 0.3).encode()
    signed = auth["valid"]["state"]
    seeds = [
        FeedBatch(1, (FeedEntry(1, unsigned),)).encode(),
        FeedBatch(2, (FeedEntry(5, signed), FeedEntry(6, unsigned))).encode(),
        FeedBatch(3, tuple(FeedEntry(k, unsigned) for k in range(FeedBatch.MAX_ENTRIES))).encode(),
        FeedBatch(
            4, tuple(FeedEntry(k, signed) for k in range(4088 // (5 + len(signed))))
        ).encode(),
    ]
    stats = {"decoded": 0, "rejected": 0, "slowest_us": 0}
    for i in range(20_000):
        check_one(mutate(seeds[i % len(seeds)], rng), auth, stats)
    for _ in range(5_000):
        n = rng.choice([8, 13, 77, 141, rng.randrange(5000)])
        check_one((bytes([7, 1]) + rng.randbytes(n))[:n], auth, stats)
    for data in seeds:
        check_one(data, auth, stats)
    print(f"fuzz feed batches: 25004 inputs, {stats}")
    assert stats["decoded"] > 100 and stats["rejected"] > 1000
