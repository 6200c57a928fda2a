"""A polled agent's receive path (comms/mesh.py `CellSubscription.drain`) against its reference,
on random inputs: the heads of a relay batch read in one loop (comms/heard.py `hear_all`) against
`Heard.of` one by one; `VehicleState.decode`'s fast test against the reasoned checks of every
field; `RelayBatch.decode` against its plain loop; the batch handler (each vehicle's states
grouped once, its least lag looked up once, the usual order without a sort) against the
handler that estimated every state and sorted every vehicle's; the keyed admitter (the signed
bytes the state was decoded from, not packed again) against the gate's head, decode and rest
called as before; and a subscription's relay block, worked out once per `set_cells`."""

from __future__ import annotations

import dataclasses
import math
import random
import struct
import time
import types
from collections.abc import Callable

import pytest

import comms.mesh as mesh_mod
from comms import keys
from comms.arrival import ArrivalEstimate
from comms.gate import Gate, GateConfig, Refusal, Summaries
from comms.heard import Heard, hear_all
from comms.mesh import PLAUSIBLE_LAG_SLACK_NS, Mesh, MeshStats
from comms.relay import MisplacedState, decode_placed
from comms.schema import (
    LINK_ENTRY_BYTES,
    MAX_LINK_TAGS,
    MAX_STATE_BYTES,
    MAX_VEHICLE_ID,
    POSITION_LIMIT_M,
    TAG_BYTES,
    DecodeError,
    Mode,
    MsgType,
    RelayBatch,
    Role,
    StateFlag,
    VehicleState,
)
from comms.session import MeshConfig, embedded_router, free_tcp_port
from tests.test_heard import random_state
from trust.auth import load_auth
from trust.authority import throwaway_fleet

MS = 1_000_000
FMT = VehicleState._FMT
_CHARS = "BBHIQ" + "f" * 10 + "BBHfBBf"
"""VehicleState._FMT's fields, one character each (22: the `f` of VehicleState.decode)."""
_AT = [struct.calcsize("<" + _CHARS[:i]) for i in range(len(_CHARS))]


# -- heads -------------------------------------------------------------------------------------
def test_hear_all_equals_heard_of_one_by_one() -> None:
    rng = random.Random(11)
    for _ in range(300):
        payloads = []
        for _ in range(rng.randint(0, 25)):
            data = random_state(rng).encode()
            r = rng.random()
            if r < 0.1:
                data = data[: rng.randrange(len(data))]  # too short (or not)
            elif r < 0.15:
                data = bytes([rng.choice([rng.randrange(256), MsgType.VEHICLE_STATE])]) + data[1:]
            elif r < 0.2:
                data = data[:1] + bytes([rng.randrange(256)]) + data[2:]
            elif r < 0.25:
                data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 200)))
            payloads.append(data)
        block = (rng.randint(1, 2), (rng.randint(-3, 3), rng.randint(-3, 3)))
        for b in (block, None):
            got, bad = hear_all("k", payloads, b)
            want = [Heard.of("k", p, b, i) for i, p in enumerate(payloads)]
            assert got == [h for h in want if h is not None]
            assert bad == [i for i, h in enumerate(want) if h is None]
            assert all(type(h) is Heard and type(h.signed) is bool for h in got)


# -- VehicleState.decode -----------------------------------------------------------------------
class _Refused(Exception):
    """The reference refused a state before its field checks (its reason is not compared)."""


def _reference_decode(data: bytes) -> VehicleState:
    """VehicleState.decode with every state built by the dataclass's own __init__ and checked by
    the reasoned checks, one reason each (`_validate_reasoned`)."""
    if len(data) < 2 or data[0] != MsgType.VEHICLE_STATE or data[1] != VehicleState.VERSION:
        raise _Refused
    signed_end = FMT.size + TAG_BYTES
    links = b""
    if len(data) > signed_end:
        count = data[signed_end]
        if not 1 <= count <= MAX_LINK_TAGS or len(data) != signed_end + 1 + count * 10:
            raise _Refused
        links = bytes(data[signed_end + 1 :])
    elif len(data) not in (FMT.size, signed_end):
        raise _Refused
    f = FMT.unpack_from(data)
    if f[16] not in (0, 1) or f[17] > 0xFF or f[15] not in {int(m) for m in Mode}:
        raise _Refused
    state = VehicleState(
        vehicle_id=f[2],
        seq=f[3],
        stamp_ns=f[4],
        pos_ned_m=f[5:8],
        vel_ned_m_s=f[8:11],
        heading_rad=f[11],
        goal_ned_m=f[12:15],
        mode=Mode(f[15]),
        armed=f[16] == 1,
        flags=StateFlag(f[17]),
        battery_pct=f[18],
        mission_item=f[19],
        mission_items=f[20],
        pos_sigma_m=f[21],
        sig=data[FMT.size : signed_end],
        links=links,
    )
    state._validate_reasoned()
    return state


_EDGE_F = [
    math.nan,
    math.inf,
    -math.inf,
    -0.0,
    POSITION_LIMIT_M,
    -POSITION_LIMIT_M,
    1.0000001e6,
    -1.0000001e6,
    1000.0,
    -1000.0,
    1000.0001,
    -1000.0001,
    6.283185,
    6.2831855,
    -6.2831855,
    100.0,
    100.00001,
    -1e-30,
    0.0,
    3.0,
]


def _mutate(rng: random.Random, data: bytes) -> bytes:
    """`data` with a field or a byte or two set to an edge value."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 2)):
        r = rng.random()
        if r < 0.7:
            i = rng.randrange(2, len(_CHARS))
            c = _CHARS[i]
            if c == "f":
                v: float | int = rng.choice(_EDGE_F)
            elif c == "H" and i == 2:
                v = rng.choice([0, 1, MAX_VEHICLE_ID, MAX_VEHICLE_ID + 1, 65535])
            elif c == "H":
                v = rng.choice([0, 255, 256, rng.randrange(65536)])
            elif c == "B":
                v = rng.choice([0, 1, 2, 100, 101, 102, 255, rng.randrange(256)])
            else:
                v = rng.randrange(2 ** (8 * struct.calcsize(c)))
            struct.pack_into("<" + c, b, _AT[i], v)
        elif r < 0.85 and len(b) > FMT.size + TAG_BYTES + 1:  # a link entry's receiver id
            k = FMT.size + TAG_BYTES + 1 + LINK_ENTRY_BYTES * rng.randrange(b[FMT.size + 64])
            struct.pack_into("<H", b, k, rng.choice([0, 1, MAX_VEHICLE_ID, MAX_VEHICLE_ID + 1]))
        else:
            b[rng.randrange(len(b))] = rng.randrange(256)
    return bytes(b)


def test_decode_equals_the_reasoned_checks_on_random_bytes() -> None:
    rng = random.Random(12)
    took = refused = 0
    why: set[str] = set()
    for _ in range(6000):
        data = random_state(rng).encode()
        if rng.random() < 0.9:
            data = _mutate(rng, data)
        try:
            want: VehicleState | str | None = _reference_decode(data)
        except _Refused:
            want = None
        except DecodeError as exc:
            want = str(exc)
        try:
            got: VehicleState | str = VehicleState.decode(data)
        except DecodeError as exc:
            got = str(exc)
        if isinstance(want, VehicleState):
            assert isinstance(got, VehicleState) and got == want and repr(got) == repr(want)
            # what a receiver checks the signature and link tags of (mesh.py `_SIGNED_BYTES`)
            assert got.signed_bytes() == data[: FMT.size]
            took += 1
        elif want is None:
            assert isinstance(got, str), data.hex()
        else:
            assert got == want, data.hex()
            refused += 1
            why.add(got.split("=")[0].split("[")[0].split(" ")[0])
    assert took > 500 and refused > 1000  # both ways, many times, for every field's reason
    assert {
        "vehicle_id",
        "position",
        "vel_ned_m_s",
        "heading_rad",
        "battery_pct",
        "pos_sigma_m",
        "mission_items",
        "mission_item",
        "link",
    } <= why, why


# -- RelayBatch.decode -------------------------------------------------------------------------
def _reference_batch(data: bytes) -> RelayBatch:
    """RelayBatch.decode's loop, each size read from the class."""
    _, _, relay_seq, n = RelayBatch._HEAD.unpack_from(data)
    states, at = [], RelayBatch._HEAD.size
    for i in range(n):
        if at + RelayBatch._LEN.size > len(data):
            raise DecodeError(f"RelayBatch of {len(data)} bytes ends inside state {i} of {n}")
        (length,) = RelayBatch._LEN.unpack_from(data, at)
        at += RelayBatch._LEN.size
        if not 2 <= length <= MAX_STATE_BYTES or at + length > len(data):
            raise DecodeError(
                f"RelayBatch state {i} of {n}: {length} bytes, must be 2..{MAX_STATE_BYTES} "
                f"and within the batch's {len(data)}"
            )
        states.append(data[at : at + length])
        at += length
    if at != len(data):
        raise DecodeError(f"RelayBatch has {len(data) - at} bytes after its {n} states")
    return RelayBatch(relay_seq, tuple(states))


def test_relay_batch_decode_equals_its_plain_loop() -> None:
    rng = random.Random(13)
    kinds: set[type] = set()
    for _ in range(1500):
        states = tuple(random_state(rng).encode() for _ in range(rng.randint(0, 12)))
        data = bytearray(RelayBatch(rng.randrange(2**32), states).encode())
        for _ in range(rng.choice([0, 0, 1, 2])):
            if rng.random() < 0.5 and len(data) > 8:
                data[rng.randrange(6, len(data))] = rng.randrange(256)
            else:
                data = data[: rng.randrange(8, len(data) + 1)] + bytes(rng.randrange(3))
        data = bytes(data)
        try:
            want: RelayBatch | str = _reference_batch(data)
        except DecodeError as exc:
            want = str(exc)
        try:
            got: RelayBatch | str = RelayBatch.decode(data)
        except DecodeError as exc:
            got = str(exc)
        assert got == want
        kinds.add(type(got))
    assert kinds == {RelayBatch, str}


# -- the batch handler -------------------------------------------------------------------------
def _reference_handler(
    admit: Callable[[Heard, int], bool],
    every_state: bool,
    budget_s: float,
    stats: MeshStats,
    perf_counter: Callable[[], float],
) -> Callable[[list[Heard], int, int], None]:
    """Mesh._state_batch_handler as it was: every state's receive time estimated as drained,
    every vehicle's states sorted."""
    arrival = ArrivalEstimate()

    def on_states(states: list[Heard], taken_ns: int, since_ns: int) -> None:
        got = [
            (s, arrival.estimate_ns(s.vehicle_id, s.stamp_ns, taken_ns, since_ns)) for s in states
        ]
        if every_state:
            for state, recv_ns in got:
                if admit(state, recv_ns):
                    arrival.note(state.vehicle_id, taken_ns - state.stamp_ns, taken_ns)
            return
        by_vehicle: dict[int, list[tuple[Heard, int]]] = {}
        for state, recv_ns in got:
            by_vehicle.setdefault(state.vehicle_id, []).append((state, recv_ns))
        for vid, candidates in by_vehicle.items():
            least_ns = arrival.least_ns(vid)
            floor_ns = None if least_ns is None else least_ns - PLAUSIBLE_LAG_SLACK_NS
            candidates.sort(
                key=lambda c: (
                    floor_ns is not None and taken_ns - c[0].stamp_ns < floor_ns,
                    -c[0].stamp_ns,
                )
            )
        t0_s = perf_counter()
        superseded = unchecked = 0
        rounds, k = list(by_vehicle.values()), 0
        while rounds:
            left = []
            for candidates in rounds:
                if k and perf_counter() - t0_s > budget_s:
                    unchecked += len(candidates) - k
                    continue
                state, recv_ns = candidates[k]
                if admit(state, recv_ns):
                    arrival.note(state.vehicle_id, taken_ns - state.stamp_ns, taken_ns)
                    superseded += len(candidates) - k - 1
                elif k + 1 < len(candidates):
                    left.append(candidates)
            rounds, k = left, k + 1
        if superseded:
            stats.bump("states_superseded", superseded)
        if unchecked:
            stats.bump("states_unchecked", unchecked)

    return on_states


def _ticks(rng: random.Random) -> list[tuple[list[Heard], int, int]]:
    """A random run of drains: vehicles with lags and clocks of their own, several states each
    a drain, mostly in order, now and then reordered, replayed, stamped ahead or far back."""
    vids = rng.sample(range(1, 40), rng.randint(1, 8))
    lag = {v: rng.randint(-200, 200) * MS for v in vids}
    taken_ns, out, place = 10_000 * MS, [], 0
    for _ in range(rng.randint(5, 40)):
        since_ns, taken_ns = taken_ns, taken_ns + rng.randint(30, 1200) * MS
        states = []
        for v in vids:
            n = rng.choice([0, 1, 1, 2, 2, 3, 6, 10])
            stamps = sorted(
                rng.randint(since_ns, taken_ns) - lag[v] - rng.randint(0, 40) * MS for _ in range(n)
            )
            r = rng.random()
            if r < 0.15:
                rng.shuffle(stamps)
            elif r < 0.25 and stamps:
                stamps.insert(rng.randrange(len(stamps) + 1), rng.choice(stamps))  # a replay
            elif r < 0.35:
                stamps.append(taken_ns + rng.randint(0, 3000) * MS)  # ahead: implausible
            elif r < 0.4:
                stamps.insert(0, rng.randint(0, since_ns))
            for s in stamps:
                place += 1
                states.append(Heard(v, place, max(s, 0), True, b"", "k", None, place))
        if rng.random() < 0.5:
            rng.shuffle(states)  # the vehicles interleaved (each one's order kept or not)
        else:
            states.sort(key=lambda h: h.place)
        out.append((states, taken_ns, since_ns))
    return out


def test_the_batch_handler_equals_its_reference(monkeypatch) -> None:
    """Same states tried, in the same order, at the same estimated receive times, and the same
    counts superseded and unchecked: random drains, verdicts and check budgets."""
    rng = random.Random(14)
    seen = [0, 0]  # superseded, unchecked
    for trial in range(300):
        every_state = rng.random() < 0.15
        budget_s = rng.choice([1e9, 0.0, 0.0025, 0.0055])
        p_pass = rng.choice([0.1, 0.5, 0.9, 1.0])
        logs: list[list[tuple[int, int]]] = [[], []]

        def admitter(
            log: list[tuple[int, int]], trial: int = trial, p_pass: float = p_pass
        ) -> Callable[[Heard, int], bool]:
            def admit(heard: Heard, recv_ns: int) -> bool:
                log.append((heard.place, recv_ns))
                return random.Random(heard.place * 7919 + trial).random() < p_pass

            return admit

        def perf_counter() -> Callable[[], float]:
            t = [0.0]

            def tick() -> float:  # each look at the clock a millisecond later
                t[0] += 0.001
                return t[0]

            return tick

        ref_stats = MeshStats()
        ref = _reference_handler(
            admitter(logs[0]), every_state, budget_s, ref_stats, perf_counter()
        )
        fake = types.SimpleNamespace(stats=MeshStats(), _unchecked=Summaries(None))
        monkeypatch.setattr(mesh_mod, "time", types.SimpleNamespace(perf_counter=perf_counter()))
        new = Mesh._state_batch_handler(fake, admitter(logs[1]), every_state, budget_s)
        for states, taken_ns, since_ns in _ticks(rng):
            ref(list(states), taken_ns, since_ns)
            new(list(states), taken_ns, since_ns)
            assert logs[1] == logs[0], trial
        assert fake.stats.states_superseded == ref_stats.states_superseded, trial
        assert fake.stats.states_unchecked == ref_stats.states_unchecked, trial
        seen[0] += ref_stats.states_superseded
        seen[1] += ref_stats.states_unchecked
    assert min(seen) > 100


# -- the keyed admitter ------------------------------------------------------------------------
def test_the_keyed_admitter_equals_the_gate_called_as_before(tmp_path) -> None:
    """Random signed, tagged, forged, stripped, unsigned, stale, replayed, misplaced, malformed
    and out-of-reach states through a mesh's keyed admitter of heard states, and through a gate
    of its own, called as the admitter did before (`admit_head`, `decode_placed`,
    `admit_decoded` packing the signed bytes again): the same states go on at the same times,
    the same are refused for the same causes, and every counter agrees."""
    rng = random.Random(15)
    me, others = 1, [2, 3, 4, 5]
    fleet = throwaway_fleet(tmp_path, "rxfast", vehicles=[me, *others], stations=[1])
    member = {v: str(fleet.member_path(Role.VEHICLE, v)) for v in [me, *others]}
    signers = {v: load_auth(member[v]) for v in others}
    rx, ref_auth = load_auth(member[me]), load_auth(member[me])
    cfg = GateConfig(min_interval_s=0.15, max_skew_s=2.0)
    block = (1, (0, 0))

    def reach(s: VehicleState) -> bool:
        return abs(s.pos_ned_m[1]) < 30.0

    with Mesh(embedded_router(free_tcp_port(), fleet="rxfast"), auth=rx) as mesh:
        got: list[tuple[VehicleState, int]] = []
        refused: list[tuple[int, str, int]] = []
        admit = mesh._admitters(
            lambda s, t: got.append((s, t)),
            None,
            lambda v, why, t: refused.append((v, why, t)),
            cfg,
            me,
            reach,
        )[1]
        gate = mesh.gates[-1]
        ref_gate = Gate(ref_auth, cfg, worth_checking=reach)
        ref_got: list[tuple[VehicleState, int]] = []
        ref_refused: list[tuple[int, str, int]] = []
        ref_errors = [0, 0]  # decode errors, of which misplaced

        def ref_admit(heard: Heard, recv_ns: int) -> bool:
            if heard.vehicle_id == me:
                return False
            verdict = ref_gate.admit_head(
                heard.vehicle_id, heard.seq, heard.stamp_ns, heard.signed, recv_ns
            )
            if verdict is None:
                try:
                    state = decode_placed(heard.where, heard.payload, heard.block)
                except DecodeError as exc:
                    ref_errors[0] += 1
                    ref_errors[1] += isinstance(exc, MisplacedState)
                    return False
                verdict = ref_gate.admit_decoded(state, recv_ns)
                if verdict is None:
                    ref_got.append((state, recv_ns))
                    return True
            if isinstance(verdict, Refusal):
                ref_refused.append((heard.vehicle_id, verdict.value, recv_ns))
            return False

        now_ns, sent, seq = 1_000_000 * MS, [], 0
        for place in range(400):
            now_ns += rng.randint(0, 120) * MS
            r = rng.random()
            if r < 0.08 and sent:
                payload = rng.choice(sent)  # a replay
            else:
                seq += 1
                vid = rng.choice([*others, me, 9] if rng.random() < 0.1 else others)
                signer = signers[rng.choice(others) if vid not in others else vid]
                e_m = rng.choice([5.0, -20.0, 25.0, 45.0, 70.0])  # 45, 70: out of reach or block
                stamp = now_ns + rng.choice([0, -50, -2500, 2500, rng.randint(-300, 50)]) * MS
                st = VehicleState(vid, seq, stamp, (3.0, e_m, -6.0), (1.0, 0.0, 0.0), 0.0)
                receivers = rng.choice([[me], [me, 3], [3], [], [4, me]])
                if rng.random() < 0.1:
                    payload = st.encode()  # unsigned
                else:
                    signed = signer.sign_state(st, receivers)
                    data = bytearray(signed.encode())
                    c = rng.random()
                    if c < 0.1 and signed.links:  # a wrong tag (the signature still right)
                        data[-1] ^= 0x40
                    elif c < 0.2:  # a wrong signature (a right tag still passes)
                        data[FMT.size + 5] ^= 0x01
                    elif c < 0.3:  # the body changed after signing
                        data[_AT[5]] ^= 0x01
                    elif c < 0.33:  # a good head on a body no decode takes
                        data[_AT[16]] = 2
                    payload = bytes(data)
                sent.append(payload)
            heard = Heard.of("relay", payload, block, place)
            if heard is None:
                continue
            assert admit(heard, now_ns) == ref_admit(heard, now_ns), place
        assert [(s, t) for s, t in got] == ref_got and refused == ref_refused
        assert len(got) > 50 and len(refused) > 20
        causes = {why for _, why, _ in refused}
        assert {"forged", "stale", "unsigned", "unknown signer"} <= causes
        assert (gate.accepted, gate.skipped, gate.out_of_reach, gate.refused) == (
            ref_gate.accepted,
            ref_gate.skipped,
            ref_gate.out_of_reach,
            ref_gate.refused,
        )
        assert gate.skipped > gate.out_of_reach > 0
        stats = mesh.stats
        assert stats.states_received == len(ref_got)
        assert stats.states_refused == len(ref_refused)
        assert stats.states_beyond_reach == ref_gate.out_of_reach
        assert (stats.decode_errors, stats.states_misplaced) == tuple(ref_errors)
        assert ref_errors[1] > 0 and ref_errors[0] > ref_errors[1]
        rx_links, ref_links = rx.links, ref_auth.links
        assert rx_links is not None and ref_links is not None
        assert (rx_links.tags_good, rx_links.tags_bad) == (ref_links.tags_good, ref_links.tags_bad)
        assert rx_links.tags_good > 20 and rx_links.tags_bad > 5


# -- the relay block ---------------------------------------------------------------------------
def test_the_relay_block_follows_the_cells() -> None:
    """A polled subscription's relay block is worked out once per `set_cells`, and again on
    every change."""
    port = free_tcp_port()
    client = MeshConfig(fleet="rxblock", mode="client", connect=(f"tcp/127.0.0.1:{port}",))
    client = dataclasses.replace(client, listen=())
    with Mesh(embedded_router(port, fleet="rxblock")), Mesh(client) as me:
        sub = me.subscribe_cells(lambda s, t: None, (), polled=True, relay_for=7)
        assert sub._relay_id is not None
        for anchor, k in [((0, 0), 1), ((5, -3), 1), ((5, -3), 2), ((0, 0), 1)]:
            sub.set_cells(keys.block_cells(k, anchor))
            assert sub._block == (k, anchor)
            sub.drain(time.time_ns())
            assert sub._block == (k, anchor)
        sub.set_cells([(0, 0), (0, 1)])  # no block
        assert sub._block is None
        sub.set_cells(keys.block_cells(1, (2, 2)))
        assert sub._block == (1, (2, 2))


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q"])
