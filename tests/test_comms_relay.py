"""The router's cell relay (comms/relay.py): its keys and batches, what it refuses, and on real
Zenoh sessions that a vehicle hears its block through it (in-process and from a `covey router`
process), falls back to its own cells when the relay goes, and is handed nothing misplaced."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from dataclasses import replace

import pytest

from comms import keys
from comms.mesh import Mesh
from comms.relay import (
    RELAY_SILENT_S,
    CellRelay,
    MisplacedState,
    RelayConfig,
    batches,
    decode_placed,
)
from comms.schema import MAX_FEED_BYTES, MAX_STATE_BYTES, DecodeError, RelayBatch, VehicleState
from comms.session import MeshConfig, embedded_router, free_tcp_port
from tests.conftest import wait_until

FLEET = "relay"


def state(vid: int, n_m: float, e_m: float, seq: int = 1) -> VehicleState:
    return VehicleState(vid, seq, time.time_ns(), (n_m, e_m, -10.0), (0.0, 0.0, 0.0), 0.0)


# -- keys, batches, placement ----------------------------------------------------------------
def test_relay_keys_round_trip_and_refuse_what_is_not_theirs() -> None:
    rid = "8ffc7457f8f08f09f5e1a40f5128c772"
    block = keys.relay_block(FLEET, rid, 1, (-2, 3))
    assert block == f"covey/{FLEET}/relay/{rid}/1/-2/3"
    assert keys.parse_relay_block(block) == (FLEET, rid, 1, (-2, 3))
    want = keys.relay_want(FLEET, 7, rid, 2, (0, 0))
    assert want == f"covey/{FLEET}/v/7/want/{rid}/2/0/0"  # under v/7/: what ACLs let 7 declare
    assert keys.parse_relay_want(want) == (FLEET, 7, rid, 2, (0, 0))
    for bad in (f"covey/{FLEET}/relay/{rid}/4/0/0", f"covey/{FLEET}/relay/XYZ/1/0/0"):
        assert keys.parse_relay_block(bad) is None
    assert keys.parse_relay_want(f"covey/{FLEET}/v/0/want/{rid}/1/0/0") is None
    with pytest.raises(ValueError, match="hex"):
        keys.all_relay_wants("not-a-zid")
    with pytest.raises(ValueError, match="1..3 cells"):
        keys.relay_block(FLEET, rid, 0, (0, 0))


def test_block_of_is_the_inverse_of_block_cells() -> None:
    for k in (1, 2, 3):
        cells = keys.block_cells(k, (4, -5))
        assert len(cells) == (2 * k + 1) ** 2
        assert keys.block_of(frozenset(cells)) == (k, (4, -5))
    assert keys.block_of(frozenset()) is None
    assert keys.block_of(frozenset(keys.block_cells(1, (0, 0))[:-1])) is None  # not a square
    assert keys.block_of(frozenset({(0, 0), (0, 1), (1, 0), (1, 1)})) is None  # even side
    assert keys.block_of(frozenset({(0, 0)})) is None  # k = 0: no block


def test_batches_carry_every_state_within_the_size_limit() -> None:
    big = state(9, 1.0, 1.0).encode() + b"\0" * 0  # 70 bytes unsigned
    states = [big] * 200 + [b"x" * MAX_STATE_BYTES] * 3
    out = batches(states, seq=5)
    assert len(out) > 1 and all(len(b) <= MAX_FEED_BYTES for b in out)
    decoded = [RelayBatch.decode(b) for b in out]
    assert [d.relay_seq for d in decoded] == list(range(5, 5 + len(out)))
    assert [s for d in decoded for s in d.states] == states  # all of them, in order
    (empty,) = batches([], seq=1)
    assert RelayBatch.decode(empty).states == ()  # a quiet block still hears its relay


@pytest.mark.parametrize(
    "data, why",
    [
        (RelayBatch(1, (b"ab",)).encode()[:-1], "ends inside|within the batch"),
        (RelayBatch(1, (b"ab",)).encode() + b"\0", "after its 1 states"),
        (b"\x0d\x01" + b"\0" * (MAX_FEED_BYTES + 1), "RelayBatch must be"),
        (RelayBatch(1, ()).encode()[:-2] + b"\x05\x00", "ends inside state 0"),
    ],
)
def test_a_malformed_relay_batch_is_refused_with_the_reason(data: bytes, why: str) -> None:
    with pytest.raises(DecodeError, match=why):
        RelayBatch.decode(data)


def test_placement_is_checked_against_the_key_or_the_block() -> None:
    payload = state(3, 5.0, 40.0).encode()  # cell (0, 1)
    assert decode_placed(keys.state(FLEET, 3, (0, 1)), payload).vehicle_id == 3
    with pytest.raises(MisplacedState, match="not in cell"):
        decode_placed(keys.state(FLEET, 3, (0, 0)), payload)
    with pytest.raises(DecodeError, match="arrived on"):
        decode_placed(keys.state(FLEET, 4, (0, 1)), payload)
    assert decode_placed("relayed", payload, (1, (1, 2))).vehicle_id == 3
    with pytest.raises(MisplacedState, match="relay block"):
        decode_placed("relayed", payload, (1, (2, 2)))


def test_relay_config_and_mesh_config_refuse_bad_periods() -> None:
    with pytest.raises(ValueError, match="period_s"):
        RelayConfig(period_s=0.0)
    with pytest.raises(ValueError, match="cell_relay_period_s"):
        MeshConfig(cell_relay_period_s=5.0)


# -- on real Zenoh sessions --------------------------------------------------------------------
def _client(port: int) -> MeshConfig:
    return MeshConfig(fleet=FLEET, mode="client", connect=(f"tcp/127.0.0.1:{port}",), listen=())


def _vehicle_7(me: Mesh, got: list[int]):
    """Vehicle 7 at (0, 0): the block of cells around (0, 0), polled, through its router's relay;
    the ids of the states it hears go to `got`."""
    return me.subscribe_cells(
        lambda s, _t: got.append(s.vehicle_id),
        keys.block_cells(1, (0, 0)),
        polled=True,
        relay_for=7,
    )


def _hear(sub, got: list, pub: Mesh, rounds: int, seq0: int = 1) -> None:
    for i in range(rounds):
        pub.publish_state(state(3, 5.0, 5.0, seq0 + i))  # cell (0, 0)
        pub.publish_state(state(4, 35.0, -20.0, seq0 + i))  # cell (1, -1): in the block
        pub.publish_state(state(5, 100.0, 100.0, seq0 + i))  # cell (3, 3): outside it
        time.sleep(0.03)
        sub.drain()


def test_a_vehicle_hears_its_block_through_the_relay_and_falls_back_when_it_goes() -> None:
    port = free_tcp_port()
    router_cfg = replace(embedded_router(port, fleet=FLEET), cell_relay_period_s=0.05)
    with Mesh(router_cfg) as router, Mesh(_client(port)) as pub, Mesh(_client(port)) as me:
        assert router.relay is not None
        got: list[int] = []
        sub = _vehicle_7(me, got)
        assert wait_until(lambda: (sub.drain(), router.relay.stats.blocks == 1)[1], 5.0)
        _hear(sub, got, pub, 30)
        assert sub.relayed  # its own cell subscribers went: only the relay's block is heard
        assert me.stats.relay_batches_received >= 5
        assert {3, 4} <= set(got) and 5 not in got
        assert router.relay.stats.refused == 0
        # What it heard came once: the newest state of each vehicle per drain, none twice.
        before = len(got)
        _hear(sub, got, pub, 20, seq0=100)
        assert 0 < len(got) - before <= 2 * 20
        # The relay goes: after RELAY_SILENT_S without a batch the vehicle hears its cells itself.
        router.relay.close()
        assert wait_until(lambda: (sub.drain(), not sub.relayed)[1], 5.0)
        assert me.stats.decode_errors == 0
        time.sleep(0.3)  # the new cell subscribers reach the router
        before = len(got)
        _hear(sub, got, pub, 10, seq0=200)
        assert got[before:].count(3) >= 5 and 5 not in got[before:]


def test_a_misplaced_state_is_neither_relayed_nor_heard() -> None:
    """A state put on a cell key that is not its position's: the relay refuses it (counted with
    the reason) and never forwards it; the vehicle never hears it."""
    port = free_tcp_port()
    router_cfg = replace(embedded_router(port, fleet=FLEET), cell_relay_period_s=0.05)
    with Mesh(router_cfg) as router, Mesh(_client(port)) as pub, Mesh(_client(port)) as me:
        got: list[int] = []
        sub = _vehicle_7(me, got)
        assert wait_until(lambda: (_hear(sub, got, pub, 1), sub.relayed)[1], 8.0)
        far = state(9, 500.0, 500.0).encode()  # really in cell (16, 16)
        for _ in range(10):
            pub.session.put(keys.state(FLEET, 9, (0, 0)), far)
            time.sleep(0.03)
            sub.drain()
        assert wait_until(lambda: router.relay.stats.refused >= 5, 5.0)
        assert "not in cell" in router.relay.stats.last_refusal
        assert 9 not in got


def test_the_relay_of_a_covey_router_process_serves_its_clients() -> None:
    """`covey router` (a process of its own) relays; a client vehicle hears its block from it."""
    port = free_tcp_port()
    argv = [sys.executable, "-m", "covey_cli", "router", "--listen", f"tcp/127.0.0.1:{port}"]
    argv += ["--cell-relay-period-s", "0.05", "--count-period-s", "0.2"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(3)]
        assert any("relaying cells" in line for line in lines), lines
        with Mesh(_client(port)) as pub, Mesh(_client(port)) as me:
            got: list[int] = []
            sub = _vehicle_7(me, got)
            ok = wait_until(lambda: (_hear(sub, got, pub, 3), sub.relayed)[1], 10.0)
            assert ok and me.stats.relay_batches_received > 0
            assert {3, 4} <= set(got) and 5 not in got
            time.sleep(0.5)  # a count period: the router says what its relay serves
        proc.terminate()
        rest = proc.communicate(timeout=20)[0]
        # the operator's view: the block it served, its 9 cells (then none once the vehicle left)
        assert "covey router: cell relay: 1 block(s) wanted, 9 cell(s) heard" in rest, rest
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=10)
        if proc.poll() is None:
            proc.kill()


def test_covey_router_refuses_a_bad_relay_period() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "covey_cli", "router", "--listen", "tcp/127.0.0.1:0"]
        + ["--cell-relay-period-s", "3"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (
        out.returncode == 2 and "cell_relay_period_s=3.0 must be within [0.01, 0.3]" in out.stderr
    )


def test_without_a_relay_a_vehicle_hears_its_cells_itself() -> None:
    """A router with no relay (--no-cell-relay, a plain zenohd): the vehicle's want is never answered,
    so it keeps its own cell subscribers and hears everything as before."""
    port = free_tcp_port()
    cfg = replace(embedded_router(port, fleet=FLEET), cell_relay_period_s=None)
    with Mesh(cfg) as router, Mesh(_client(port)) as pub, Mesh(_client(port)) as me:
        assert router.relay is None
        with CellRelay(router.session, start=False) as relay:
            assert relay.flush() == 0 and relay.stats.blocks == 0  # nobody wants a block yet
        got: list[int] = []
        sub = _vehicle_7(me, got)
        assert wait_until(lambda: (_hear(sub, got, pub, 1), {3, 4} <= set(got))[1], 8.0)
        _hear(sub, got, pub, 20, seq0=10)
        assert not sub.relayed and me.stats.relay_batches_received == 0 and 5 not in got


def test_a_quiet_block_is_kept_alive_not_flooded() -> None:
    """A block with states gets a batch every period; a quiet one an empty batch every
    keepalive_s, fewer wake-ups for a hovering vehicle, but often enough for RELAY_SILENT_S."""
    port = free_tcp_port()
    cfg = replace(embedded_router(port, fleet=FLEET), cell_relay_period_s=None)
    now = [100.0]
    with (
        Mesh(cfg) as router,
        Mesh(_client(port)) as me,
        CellRelay(
            router.session, RelayConfig(period_s=0.1), start=False, clock_s=lambda: now[0]
        ) as relay,
    ):
        token = me.session.liveliness().declare_token(
            keys.relay_want(FLEET, 7, relay.relay_id, 1, (0, 0))
        )
        assert wait_until(lambda: bool(relay._wants), 5.0)
        put = []
        for _ in range(10):  # 1 s of a quiet block at a 0.1 s period: kept alive every 0.3 s
            put.append(relay.flush())
            now[0] += 0.1
        assert put == [1, 0, 0, 1, 0, 0, 1, 0, 0, 1]
        assert 0.3 <= RelayConfig().keepalive_s * 3 < RELAY_SILENT_S
        token.undeclare()
        assert wait_until(lambda: not relay._wants, 5.0)
        assert relay.flush() == 0 and relay.stats.blocks == 0
    with pytest.raises(ValueError, match="keepalive_s"):
        RelayConfig(period_s=0.2, keepalive_s=0.1)


def test_one_vehicle_cannot_make_the_relay_subscribe_the_grid() -> None:
    """Wants beyond max_wants_per_vehicle (a member declaring tokens for many blocks) are
    refused with the reason (the vehicle hears its cells itself), and taken when room is made."""
    port = free_tcp_port()
    cfg = replace(embedded_router(port, fleet=FLEET), cell_relay_period_s=None)
    with (
        Mesh(cfg) as router,
        Mesh(_client(port)) as greedy,
        CellRelay(router.session, RelayConfig(max_wants_per_vehicle=4), start=False) as relay,
    ):
        tokens = [
            greedy.session.liveliness().declare_token(
                keys.relay_want(FLEET, 9, relay.relay_id, 1, (10 * i, 0))
            )
            for i in range(6)
        ]
        assert wait_until(lambda: relay.stats.refused >= 2, 5.0)
        time.sleep(0.2)
        assert len(relay._wants) == 4 and relay.stats.refused == 2
        assert "vehicle 9 of fleet 'relay' already wants 4 blocks" in relay.stats.last_refusal
        relay.flush()
        assert relay.stats.blocks == 4 and relay.stats.cells == 4 * 9
        # One of its wants goes (its vehicle moved on): a refused one is taken in its place.
        served = set(relay._wants.values())
        tokens[0].undeclare()
        assert wait_until(
            lambda: len(relay._wants) == 4 and set(relay._wants.values()) != served, 5.0
        )
        assert (FLEET, 1, (0, 0)) not in relay._wants.values()
        for t in tokens[1:]:
            t.undeclare()
        assert wait_until(lambda: not relay._wants, 5.0)
    with pytest.raises(ValueError, match="max_wants_per_vehicle"):
        RelayConfig(max_wants_per_vehicle=0)


def test_after_its_router_restarts_a_vehicle_finds_the_new_relay() -> None:
    """The router goes and comes back on the same endpoint with a new Zenoh id: the vehicle,
    reconnected, falls back to its own cells, then wants its block from the new relay."""
    port = free_tcp_port()
    router_cfg = replace(embedded_router(port, fleet=FLEET), cell_relay_period_s=0.05)
    got: list[int] = []
    with Mesh(router_cfg) as first, Mesh(_client(port)) as me:
        old = first.relay.relay_id if first.relay else ""
        sub = _vehicle_7(me, got)
        with Mesh(_client(port)) as pub:
            assert wait_until(lambda: (_hear(sub, got, pub, 1), sub.relayed)[1], 10.0)
        first.close()
        with Mesh(router_cfg) as second, Mesh(_client(port)) as pub:
            assert second.relay is not None and second.relay.relay_id != old
            assert wait_until(
                lambda: (_hear(sub, got, pub, 1), sub.relayed and second.relay.stats.blocks == 1)[
                    1
                ],
                30.0,
            ), f"not relayed again: {second.relay.stats}"
