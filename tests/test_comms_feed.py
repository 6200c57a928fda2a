"""The fleet feed (comms/feed.py): each process's latest states, batched at a bounded rate, for
ground stations.

Pure: the batching rules with an injected clock. On a real Zenoh mesh on loopback (no
multicast): a `covey fleet-sim --vehicles 50` child seen by a station-side FleetModel through the
feed (every vehicle, exact positions, batches per second bounded, no loss counted for the
thinning); in keyed mode a forged entry is refused while its batch-mates are accepted, and a
replayed batch is refused whole; malformed batches and entries are refused with the reason and
the receiver lives on.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
import zenoh

from agent.shell_config import start_grid
from comms import keys
from comms.feed import DUE_SLACK, FeedBuffer
from comms.gate import Refusal
from comms.mesh import Mesh
from comms.schema import (
    MAX_FEED_BYTES,
    DecodeError,
    FeedBatch,
    FeedEntry,
    Role,
    VehicleState,
)
from comms.session import MeshConfig, embedded_peer, embedded_router, free_tcp_port
from groundstation.fleet import FleetModel
from tests.conftest import views_by_id, wait_until
from trust.auth import load_auth
from trust.authority import throwaway_fleet

FLEET = "feedtest"
MS = 1_000_000


def state(vid: int, seq: int = 1, stamp_ns: int = 0, n_m: float = 0.0) -> VehicleState:
    return VehicleState(vid, seq, stamp_ns, (n_m, float(vid), -5.0), (0.0, 0.0, 0.0), 0.0)


def entries_of(batches: list[bytes]) -> list[tuple[int, int, VehicleState]]:
    """(feed_seq, entry_seq, state) of every entry of these batches, in order."""
    out = []
    for raw in batches:
        batch = FeedBatch.decode(raw)
        out += [(batch.feed_seq, e.entry_seq, VehicleState.decode(e.state)) for e in batch.entries]
    return out


# -- the batching rules (no Zenoh) --------------------------------------------------------------
def test_a_batch_carries_the_latest_state_of_every_vehicle_that_published_since_the_last() -> None:
    feed = FeedBuffer(5.0)  # a 200 ms period, due after 180 ms
    first = feed.offer(1, state(1, 1).encode(), 0)
    assert [(e[0], e[1], e[2].seq) for e in entries_of(first)] == [(1, 1, 1)]  # at once
    assert feed.offer(2, state(2, 1).encode(), 50 * MS) == []
    assert feed.offer(1, state(1, 2).encode(), 100 * MS) == []
    assert feed.offer(1, state(1, 3).encode(), 150 * MS) == []
    due = feed.offer(3, state(3, 1).encode(), 180 * MS)
    got = {s.vehicle_id: (feed_seq, n, s.seq) for feed_seq, n, s in entries_of(due)}
    # vehicle 1's latest (seq 3, its 2nd entry), vehicle 2's state of 130 ms ago, vehicle 3's own
    assert got == {1: (2, 2, 3), 2: (2, 1, 1), 3: (2, 1, 1)}
    # Only those that published since: vehicle 2 is silent and is not repeated.
    assert feed.offer(1, state(1, 4).encode(), 300 * MS) == []
    again = feed.offer(3, state(3, 2).encode(), 360 * MS)
    assert sorted((s.vehicle_id, n) for _, n, s in entries_of(again)) == [(1, 3), (3, 2)]


def test_a_publisher_at_twice_the_feed_rate_feeds_every_other_state_despite_jitter() -> None:
    feed, rng = FeedBuffer(5.0), np.random.default_rng(3)
    sent_at = []
    for k in range(200):  # 10 Hz with +-8 ms of jitter
        t_ns = int((k * 100 + rng.uniform(-8, 8)) * MS)
        if feed.offer(1, state(1, k + 1).encode(), t_ns):
            sent_at.append(k)
    assert np.all(np.diff(sent_at) == 2), sent_at


def test_a_clock_stepped_back_does_not_stop_the_feed() -> None:
    feed = FeedBuffer(5.0)
    assert feed.offer(1, state(1, 1).encode(), 10_000 * MS)
    assert feed.offer(1, state(1, 2).encode(), 5_000 * MS)  # stepped back: due at once
    assert not feed.offer(1, state(1, 3).encode(), 5_100 * MS)
    assert feed.offer(1, state(1, 4).encode(), 5_200 * MS)


def test_long_feeds_are_split_into_batches_within_the_size_limit() -> None:
    signed = [dataclasses.replace(state(v), sig=bytes(range(64))).encode() for v in range(1, 101)]
    unsigned = [state(v).encode() for v in range(101, 201)]
    feed = FeedBuffer(5.0)
    for k, payload in enumerate(signed + unsigned):
        feed.offer(1 + k, payload, 0 if k == 0 else MS)  # the first goes alone, at once
    batches = feed.flush()
    sizes = [len(b) for b in batches]
    # 99 x 139 + 100 x 75 = 21,261 bytes of entries, 4,088 to a batch: 6 batches, filled greedily
    assert max(sizes) <= MAX_FEED_BYTES and len(batches) == 6, sizes
    got = entries_of(batches)
    assert [s.vehicle_id for _, _, s in got] == list(range(2, 201))
    assert [f for f, _, _ in got] == sorted(f for f, _, _ in got)  # consecutive batch numbers
    assert {f for f, _, _ in got} == set(range(2, 8))
    assert feed.flush() == []
    batch = FeedBatch.decode(batches[-1])
    assert len(batch.entries) <= FeedBatch.MAX_ENTRIES == 54


def test_the_feed_rate_must_keep_vehicles_from_looking_stale() -> None:
    assert MeshConfig().feed_hz == 5.0
    for bad in (1.0, 0.0, -5.0, 51.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="feed_hz"):
            MeshConfig(feed_hz=bad)


# -- on a real mesh -----------------------------------------------------------------------------
@pytest.fixture
def station():
    """This process as a ground station: a router session feeding a FleetModel from the feed."""
    port = free_tcp_port()
    with Mesh(embedded_router(port, fleet=FLEET)) as mesh:
        model = FleetModel()
        mesh.subscribe_feed(model.on_state, on_refused=model.on_state_refused)
        yield port, mesh, model


@pytest.mark.e2e
def test_a_fleet_sim_of_50_reaches_the_station_through_its_feed(station, procs) -> None:
    port, mesh, model = station
    spacing_m, corner = 6.0, (10.0, -20.0)
    with Mesh(embedded_peer(port, fleet=FLEET)) as witness:  # hears every state, for contrast
        every = [0]
        witness.subscribe_states(lambda _s, _t: every.__setitem__(0, every[0] + 1))
        sim = procs.start(
            "-m",
            "covey_cli",
            "fleet-sim",
            "--vehicles",
            "50",
            "--fleet",
            FLEET,
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--spacing-m",
            str(spacing_m),
            f"--start-ne-m={corner[0]},{corner[1]}",
            "--no-see-others",
        )
        sim.wait_for("READY", timeout_s=60)
        assert wait_until(lambda: len(model.positions()) == 50, 30), model.ids()
        time.sleep(1.0)
        window_s = 4.0
        b0, e0, s0 = mesh.stats.feed_batches_received, mesh.stats.states_received, every[0]
        time.sleep(window_s)
        b1, e1, s1 = mesh.stats.feed_batches_received, mesh.stats.states_received, every[0]
    batches_s, entries_s, states_s = (
        (b1 - b0) / window_s,
        (e1 - e0) / window_s,
        (s1 - s0) / window_s,
    )
    print(
        f"station: {batches_s:.1f} feed messages/s carrying {entries_s:.0f} states/s; "
        f"every state of the same fleet: {states_s:.0f} messages/s"
    )
    # One process, 50 unsigned states (3.5 KB): one batch per feed period, at most; counted
    # where they arrive, so a batch sent up to 1 s before the window (a loaded machine) may add.
    assert 0 < batches_s <= 5.0 / (1.0 - DUE_SLACK) * (window_s + 1.0) / window_s
    assert entries_s <= 50 * batches_s
    assert mesh.stats.decode_errors == 0 and mesh.stats.states_refused == 0
    views = views_by_id(model.snapshot(time.time_ns(), trails=False))
    assert sorted(views) == list(range(1, 51))
    want = start_grid(50, spacing_m, corner)  # landed: they stay on their start grid
    for vid, v in views.items():
        assert np.allclose(v.state.pos_ned_m, want[vid - 1], atol=1e-3), (vid, v.state)
        # The feed thins states on purpose: its entry numbers count no loss for that (the
        # states' own seq would show half of them lost).
        assert v.loss_pct == 0.0 and v.rate_hz > 0, v

    def fresh() -> bool:  # at a feed period of 0.2 s, none is stale (1 s without news)
        return not any(v.stale for v in model.snapshot(time.time_ns(), trails=False).vehicles)

    assert wait_until(fresh, 10), [v.age_s for v in model.snapshot(time.time_ns()).vehicles]


@pytest.fixture(scope="module")
def fleet_keys(tmp_path_factory):
    d = tmp_path_factory.mktemp("feedkeys") / "keys"
    authority = throwaway_fleet(d, FLEET, vehicles=[1, 2, 3], stations=[1])
    return {
        "station": str(authority.member_path(Role.STATION, 1)),
        **{v: load_auth(str(authority.member_path(Role.VEHICLE, v))) for v in (1, 2, 3)},
    }


def put_batch(session: zenoh.Session, entries: list[bytes], feed_seq: int, under: int = 1) -> None:
    batch = FeedBatch(feed_seq, tuple(FeedEntry(k + 1, e) for k, e in enumerate(entries)))
    session.put(keys.feed(FLEET, under), batch.encode())


@pytest.mark.e2e
def test_a_forged_entry_is_refused_and_its_batch_mates_are_accepted(fleet_keys) -> None:
    port = free_tcp_port()
    with (
        Mesh(embedded_router(port, fleet=FLEET), auth=load_auth(fleet_keys["station"])) as mesh,
        zenoh.open(embedded_peer(port, fleet=FLEET).zenoh_config()) as attacker,
    ):
        model = FleetModel()
        mesh.subscribe_feed(model.on_state, on_refused=model.on_state_refused)
        time.sleep(0.5)
        now = time.time_ns()
        genuine = [fleet_keys[v].sign_state(state(v, 1, now)).encode() for v in (1, 2, 3)]
        put_batch(attacker, genuine, 1)
        assert wait_until(lambda: len(model.positions()) == 3, 10), model.ids()
        # Vehicle 3's key (a captured vehicle) speaks for vehicle 2, between two genuine states.
        now = time.time_ns()
        batch = [
            fleet_keys[1].sign_state(state(1, 2, now, n_m=1.0)).encode(),
            fleet_keys[3].sign_state(state(2, 2, now, n_m=40.0)).encode(),
            fleet_keys[3].sign_state(state(3, 2, now, n_m=1.0)).encode(),
        ]
        put_batch(attacker, batch, 2)
        assert wait_until(lambda: mesh.stats.states_received == 5, 10), mesh.stats
        views = views_by_id(model.snapshot(time.time_ns(), trails=False))
        assert views[1].state.seq == 2 and views[3].state.seq == 2  # accepted
        assert views[2].state.seq == 1 and views[2].state.pos_ned_m[0] == 0.0  # not moved
        assert views[2].unverified and views[2].refused_cause == Refusal.FORGED.value
        assert mesh.gates[0].refused[Refusal.FORGED] == 1 and mesh.stats.states_refused == 1
        # The same batch again: a replay, refused entry by entry (the forgery still as forged).
        put_batch(attacker, batch, 2)
        assert wait_until(lambda: mesh.stats.states_refused == 4, 10), mesh.stats
        assert mesh.gates[0].refused[Refusal.REPLAYED] == 2
        assert mesh.stats.states_received == 5


@pytest.mark.e2e
def test_malformed_batches_and_entries_are_refused_with_the_reason(station) -> None:
    port, mesh, model = station
    good = [state(v, 1).encode() for v in (1, 2, 3)]
    nan_state = bytearray(state(4).encode())
    nan_state[16:20] = b"\x00\x00\xc0\x7f"  # north = NaN
    raw = FeedBatch(1, tuple(FeedEntry(1, g) for g in good)).encode()
    cases = [
        (b"", "message too short"),
        (state(9).encode(), "expected message type 7, got 1"),
        (raw[:-10], "ends inside entry 2 of 3"),
        (raw + b"\x00", "1 bytes after its 3 entries"),
        (raw[:6] + b"\x00\x00" + raw[8:], "0 feed entries"),
        (raw[:12] + b"\x41" + raw[13:], "a state is 70 or 134 bytes, not 65"),
        (bytes(raw[:1]) + b"\x02" + raw[2:], "unsupported FEED_BATCH version 2"),
        (raw + bytes(MAX_FEED_BYTES), "FeedBatch must be 8..4096 bytes"),
    ]
    with zenoh.open(embedded_peer(port, fleet=FLEET).zenoh_config()) as pub:
        time.sleep(0.5)
        for k, (payload, why) in enumerate(cases):
            pub.put(keys.feed(FLEET, 1), payload)
            assert wait_until(lambda k=k: mesh.stats.decode_errors == k + 1, 10), (why, mesh.stats)
            assert why in mesh.stats.last_decode_error, (why, mesh.stats.last_decode_error)
        assert model.ids() == [] and mesh.stats.feed_batches_received == 0
        # One bad entry costs only itself; the receiver lives on.
        put_batch(pub, [good[0], bytes(nan_state), good[2]], 2)
        assert wait_until(lambda: len(model.positions()) == 2, 10), mesh.stats
        assert "entry 1" in mesh.stats.last_decode_error
        assert "must be finite" in mesh.stats.last_decode_error
        put_batch(pub, good, 3)
        assert wait_until(lambda: sorted(model.positions()) == [1, 2, 3], 10)
    with pytest.raises(DecodeError, match="ends inside entry"):
        FeedBatch.decode(raw[:-10])
