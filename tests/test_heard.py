"""A polled receiver decodes only the states it tries (comms/heard.py): the head a state's bytes
say (`VehicleState.peek`) against the decoded state, the gate's checks of the head plus the rest
against its whole check (`Gate.admit_head` + `admit_decoded` against `admit_state`), and on a
real Zenoh mesh: a malformed newest state (a good head, a bad body) neither hides the real one
nor goes unreported. That superseded states are not decoded: tests/test_polled_states.py."""

from __future__ import annotations

import random
import struct
import time

import pytest

from comms.gate import Gate, GateConfig
from comms.heard import Heard
from comms.mesh import Mesh
from comms.schema import DecodeError, MsgType, Role, StateFlag, VehicleState
from comms.scope import ScopeConfig
from tests.conftest import wait_until
from tests.test_polled_states import Got, keyed_peers, state, warm_up
from trust.links import LINK_ENTRY_BYTES

FLEET = "heard"
MS = 1_000_000
ARMED_AT = struct.calcsize("<BBHIQ3f3ff3fB")
"""Where a VehicleState's armed byte is (comms/schema.py `VehicleState._FMT`)."""


def _armed_2(data: bytes) -> bytes:
    """`data` with its armed byte 2: a good head on a body that no decode takes."""
    return data[:ARMED_AT] + b"\x02" + data[ARMED_AT + 1 :]


def random_state(rng: random.Random) -> VehicleState:
    sig = bytes(rng.randrange(256) for _ in range(64)) if rng.random() < 0.7 else b""
    links = b""
    if sig and rng.random() < 0.5:
        n = rng.randint(1, 5)
        links = b"".join(
            rng.randint(1, 500).to_bytes(2, "little") + bytes(LINK_ENTRY_BYTES - 2)
            for _ in range(n)
        )
    return VehicleState(
        vehicle_id=rng.randint(1, 60_000),
        seq=rng.randrange(2**32),
        stamp_ns=rng.randrange(2**63),
        pos_ned_m=(rng.uniform(-900, 900), rng.uniform(-900, 900), rng.uniform(-100, 0)),
        vel_ned_m_s=(rng.uniform(-5, 5), rng.uniform(-5, 5), 0.0),
        heading_rad=rng.uniform(-3, 3),
        flags=StateFlag.HAS_GOAL if rng.random() < 0.5 else StateFlag.NONE,
        sig=sig,
        links=links,
        pos_sigma_m=rng.uniform(0, 2),
    )


def test_peek_reads_what_decode_reads() -> None:
    rng = random.Random(7)
    for _ in range(300):
        s = random_state(rng)
        data = s.encode()
        assert VehicleState.peek(data) == (s.vehicle_id, s.seq, s.stamp_ns, bool(s.sig))
        d = VehicleState.decode(data)
        assert (d.vehicle_id, d.seq, d.stamp_ns, bool(d.sig)) == VehicleState.peek(data)


def test_a_head_peek_refuses_is_one_decode_refuses() -> None:
    data = state(4, 1, 10 * MS).encode()
    for bad in (
        data[:-1],  # too short for a state
        b"",
        bytes([MsgType.COMMAND]) + data[1:],  # another message's type
        data[:1] + bytes([data[1] + 1]) + data[2:],  # another version
    ):
        assert VehicleState.peek(bad) is None
        with pytest.raises(DecodeError):
            VehicleState.decode(bad)
    # a good head on a bad body (armed = 2): peeked, and its decode, when tried, says why not
    bad_body = _armed_2(data)
    assert VehicleState.peek(bad_body) == (4, 1, 10 * MS, False)
    with pytest.raises(DecodeError, match="armed"):
        VehicleState.decode(bad_body)
    heard = Heard.of("k", data, (1, (0, 0)), 3)
    assert heard is not None and heard.where == "k state 3" and Heard.of("k", b"\x00") is None


class _Keys:
    """A SignatureChecker whose verdict is set per state (the gate's order is what is tested)."""

    def __init__(self, forged: set[int]) -> None:
        self.forged = forged

    @property
    def roster(self):
        class _R:
            members = {(Role.VEHICLE, v): None for v in range(1, 10)}

        return _R()

    def is_member(self, role, member_id) -> bool:
        return True

    def check_state(self, s: VehicleState) -> str | None:
        return "bad signature" if s.seq in self.forged else None

    def check_event(self, e):  # pragma: no cover - not asked here
        return None

    def check_outcome(self, o):  # pragma: no cover - not asked here
        return None


def test_the_head_and_the_rest_are_the_whole_gate() -> None:
    """Random streams of states (replays, reordering, thinning, unsigned, stale, forged, out
    of reach) through two gates: one checks each whole, the other its head then the rest; the
    verdicts and the counters agree."""
    rng = random.Random(3)
    for trial in range(20):
        forged = {q for q in range(400) if rng.random() < 0.1}
        cfg = GateConfig(min_interval_s=0.15, max_skew_s=2.0)

        def reach(s: VehicleState) -> bool:
            return abs(s.pos_ned_m[0]) < 600

        whole = Gate(_Keys(forged), cfg, worth_checking=reach)
        split = Gate(_Keys(forged), cfg, worth_checking=reach)
        now_ns = 10_000 * MS
        for q in range(400):
            now_ns += rng.randint(0, 120) * MS
            vid = rng.randint(1, 4)
            stamp = now_ns + rng.randint(-3_000, 500) * MS
            if rng.random() < 0.1:
                stamp = now_ns  # a replay of the same stamp, now and then
            pos = (rng.uniform(-900, 900), 0.0, -10.0)
            s = VehicleState(
                vid, q, stamp, pos, (0.0, 0.0, 0.0), 0.0, sig=bytes(64) if q % 5 else b""
            )
            a = whole.admit_state(s, now_ns)
            head = split.admit_head(vid, q, stamp, bool(s.sig), now_ns)
            b = head if head is not None else split.admit_decoded(s, now_ns)
            assert a == b, (trial, q)
        assert whole.refused == split.refused and whole.accepted == split.accepted
        assert (whole.skipped, whole.out_of_reach) == (split.skipped, split.out_of_reach)


def test_a_malformed_newest_state_neither_hides_the_real_one_nor_goes_unreported(
    tmp_path,
) -> None:
    got = Got()
    with keyed_peers(tmp_path, FLEET) as (auth, a, b):
        sub = a.subscribe_cells(got.on_state, ScopeConfig().cells_around((0, 0)), polled=True)
        t0 = time.time_ns()
        warm_up(sub, got, lambda k: b.publish_state(state(3, k + 1, t0 + k * MS), auth=auth[3]))
        now = time.time_ns()
        real = auth[2].sign_state(state(2, 50, now))
        # a good head, newer, on a body no decode takes (armed = 2), on vehicle 2's own key
        bad = _armed_2(auth[2].sign_state(state(2, 51, now + MS)).encode())
        assert VehicleState.peek(bad) == (2, 51, now + MS, True)
        with pytest.raises(DecodeError):
            VehicleState.decode(bad)
        errors = a.stats.decode_errors
        b.session.put(_state_key(b, real), real.encode())
        b.session.put(_state_key(b, real), bad)
        assert wait_until(
            lambda: sub.drain() >= 0 and any(x[:2] == (2, 50) for x in got.states), 5.0
        )
        assert wait_until(lambda: sub.drain() >= 0 and a.stats.decode_errors > errors, 5.0)
        assert (2, 51) not in [x[:2] for x in got.states]


def _state_key(mesh: Mesh, s: VehicleState) -> str:
    from comms import keys

    return keys.state(mesh.fleet, s.vehicle_id, keys.cell_of(s.pos_ned_m))


def test_the_receive_bench_decodes_only_what_goes_on_when_ticking_slowly() -> None:
    """bench/agent_receive.py on this tree: an agent ticking at 1 Hz drains ten states of each
    neighbour a tick and decodes only the one that goes on; at 10 Hz the gate thins at the
    head, undecoded."""
    from bench.agent_receive import receive_cost

    slow = receive_cost(4, 10.0, 1.0, 3.0, 1)
    assert slow["drained_per_tick"] == pytest.approx(40, abs=4)
    assert slow["decoded_per_tick"] == slow["went_on_per_tick"] == pytest.approx(4, abs=0.5)
    busy = receive_cost(4, 10.0, 10.0, 3.0, 1)
    assert busy["decoded_per_tick"] == busy["went_on_per_tick"] < busy["drained_per_tick"]
