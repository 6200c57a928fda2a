"""A polled state subscription (an agent's: `Mesh.subscribe_cells(polled=True)`): nothing runs
on Zenoh's threads, the states wait until `drain()`, then each vehicle's newest that passes the
gate goes on (older ones dropped unverified), with its arrival estimated from its stamp."""

from __future__ import annotations

import contextlib
import threading
import time

import pytest

from comms import keys
from comms.arrival import ArrivalEstimate
from comms.gate import GateConfig
from comms.mesh import Mesh
from comms.schema import Role, VehicleState
from comms.scope import ScopeConfig
from comms.session import embedded_peer, embedded_router, free_tcp_port
from tests.conftest import wait_until
from trust.auth import load_auth
from trust.authority import throwaway_fleet

FLEET = "polled"
MS = 1_000_000


# -- the arrival estimate ----------------------------------------------------------------------
def test_arrival_is_the_stamp_plus_the_least_lag_seen() -> None:
    est = ArrivalEstimate(window_s=10.0)
    # taken 30 ms after its stamp, the queue emptied 100 ms before: the least lag so far is 30
    assert est.arrived_ns(7, 1_000 * MS, 1_030 * MS, 930 * MS) == 1_030 * MS
    # the next waited 90 ms in the queue (lag 120): it arrived 30 ms after its stamp
    assert est.arrived_ns(7, 1_100 * MS, 1_220 * MS, 1_130 * MS) == 1_130 * MS
    # a smaller lag (20) is the new least
    assert est.arrived_ns(7, 1_300 * MS, 1_320 * MS, 1_220 * MS) == 1_320 * MS
    assert est.arrived_ns(7, 1_400 * MS, 1_480 * MS, 1_420 * MS) == 1_420 * MS
    # another sender has its own lag (its clock may be off by seconds)
    assert est.arrived_ns(8, -5_000 * MS, 1_480 * MS, 1_420 * MS) == 1_480 * MS


def test_arrival_stays_between_the_previous_take_and_this_one() -> None:
    est = ArrivalEstimate()
    est.arrived_ns(3, 1_000 * MS, 1_050 * MS, 950 * MS)  # least lag 50 ms
    # a state stamped far back (a forger's, before its signature is checked): never before the
    # previous take
    assert est.arrived_ns(3, 0, 2_000 * MS, 1_900 * MS) == 1_900 * MS
    # stamped in the future: never after this take
    assert est.arrived_ns(3, 9_000 * MS, 2_100 * MS, 2_000 * MS) == 2_100 * MS


def test_arrival_least_lag_is_forgotten_after_its_window() -> None:
    est = ArrivalEstimate(window_s=1.0)
    est.arrived_ns(1, 0, 10 * MS, 0)  # least lag 10 ms
    # the sender's clock stepped back 500 ms: 2 s later the old least is forgotten
    assert est.arrived_ns(1, 1_500 * MS, 2_000 * MS, 1_900 * MS) == 2_000 * MS  # lag 500: new
    assert est.arrived_ns(1, 1_600 * MS, 2_150 * MS, 2_000 * MS) == 2_100 * MS


def test_an_estimate_before_the_checks_counts_nothing() -> None:
    est = ArrivalEstimate()
    assert est.estimate_ns(4, 1_000 * MS, 1_080 * MS, 1_000 * MS) == 1_080 * MS  # none: taken
    est.note(4, 30 * MS, 1_080 * MS)  # a state that passed its checks
    assert est.estimate_ns(4, 1_100 * MS, 1_200 * MS, 1_120 * MS) == 1_130 * MS
    # a (forged) state stamped 10 ms before its take: estimated, but its lag is not counted
    assert est.estimate_ns(4, 1_190 * MS, 1_200 * MS, 1_120 * MS) == 1_200 * MS
    assert est.least_ns(4) == 30 * MS


def test_arrival_keeps_a_bounded_number_of_senders() -> None:
    est = ArrivalEstimate(window_s=1.0, max_senders=4)
    for vid in range(10):
        est.arrived_ns(vid, vid * MS, vid * MS + 5 * MS, 0)
    assert len(est._least) <= 4
    with pytest.raises(ValueError, match="window_s"):
        ArrivalEstimate(window_s=0.0)


# -- on a real Zenoh mesh ----------------------------------------------------------------------
def state(vid: int, seq: int, stamp_ns: int, n_m: float = 5.0) -> VehicleState:
    return VehicleState(vid, seq, stamp_ns, (n_m, 5.0, -10.0), (0.0, 0.0, 0.0), 0.0)


class Got:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.states: list[tuple[int, int, int]] = []  # (vehicle, seq, recv_ns)
        self.threads: set[str] = set()

    def on_state(self, s: VehicleState, recv_ns: int) -> None:
        with self.lock:
            self.states.append((s.vehicle_id, s.seq, recv_ns))
            self.threads.add(threading.current_thread().name)


def warm_up(sub, got: Got, send) -> None:
    """Send until a drain delivers (the subscription takes a moment to reach the publisher)."""
    for k in range(200):
        send(k)
        if wait_until(lambda: sub.drain() >= 0 and bool(got.states), 0.05):
            break
    assert got.states, "the polled subscription never heard anything"
    time.sleep(0.2)
    sub.drain()
    with got.lock:
        got.states.clear()


def test_polled_states_wait_for_the_drain_and_only_the_newest_goes_on(
    mesh_trio, monkeypatch
) -> None:
    """... and the older ones are never decoded (comms/heard.py)."""
    hub, a, b = mesh_trio
    got, station = Got(), Got()
    hub.subscribe_states(station.on_state)
    sub = a.subscribe_cells(got.on_state, ScopeConfig().cells_around((0, 0)), polled=True)
    t0 = time.time_ns()
    warm_up(sub, got, lambda k: b.publish_state(state(9, k + 1, t0 + k * MS)))
    decoded: list[tuple[int, int]] = []
    real = a._decode_state  # the receiver's own decodes (the hub's are its own)

    def counting(key, payload, block=None):
        s = real(key, payload, block)
        if s is not None:
            decoded.append((s.vehicle_id, s.seq))
        return s

    monkeypatch.setattr(a, "_decode_state", counting)
    base = time.time_ns()
    sent = [(2, seq) for seq in range(1, 6)] + [(3, seq) for seq in range(1, 4)]
    for vid, seq in sent:
        b.publish_state(state(vid, seq, base + seq * 10 * MS))
    assert wait_until(
        lambda: all(any(x[:2] == (v, q) for x in station.states) for v, q in sent), 5.0
    )
    time.sleep(0.3)  # the peer has them too by now
    assert got.states == [], "a polled state went on before the drain"
    before = a.stats.states_superseded
    taken_ns = a.clock_ns()
    assert sub.drain() == len(sent)
    assert sorted(x[:2] for x in got.states) == [(2, 5), (3, 3)]
    assert sorted(decoded) == [(2, 5), (3, 3)]  # the six superseded ones never decoded
    assert a.stats.states_superseded - before == len(sent) - 2
    assert got.threads == {threading.current_thread().name}  # the drain's caller, no Zenoh thread
    # the receive stamps are estimates of when they came: before the drain, not after it
    assert all(recv_ns <= taken_ns + 100 * MS for _, _, recv_ns in got.states)
    assert sub.drain() == 0


@contextlib.contextmanager
def keyed_peers(tmp_path, fleet: str = FLEET):
    """A router and two keyed peers on a free loopback port, members of a throwaway fleet of
    vehicles 1-3: yields (each vehicle's auth, the peer of vehicle 1, the peer of vehicle 3)."""
    keys_of = throwaway_fleet(tmp_path, fleet, vehicles=[1, 2, 3], stations=[1])
    auth = {v: load_auth(str(keys_of.member_path(Role.VEHICLE, v))) for v in (1, 2, 3)}
    port = free_tcp_port()
    with (
        Mesh(embedded_router(port, fleet=fleet)) as _hub,
        Mesh(embedded_peer(port, fleet=fleet), auth=auth[1]) as a,
        Mesh(embedded_peer(port, fleet=fleet), auth=auth[3]) as b,
    ):
        yield auth, a, b


def test_polled_forged_newer_state_does_not_hide_the_real_one(tmp_path) -> None:
    got = Got()
    with keyed_peers(tmp_path) as (auth, a, b):
        sub = a.subscribe_cells(got.on_state, ScopeConfig().cells_around((0, 0)), polled=True)
        t0 = time.time_ns()
        warm_up(sub, got, lambda k: b.publish_state(state(3, k + 1, t0 + k * MS)))
        now = time.time_ns()
        b.publish_state(state(2, 50, now), auth=auth[2])  # the real one
        # vehicle 3 claims to be vehicle 2, one state newer: signed with the wrong key
        b.publish_state(state(2, 51, now + MS), auth=auth[3])
        refused = a.stats.states_refused
        seen: list[tuple[int, int]] = []
        assert wait_until(
            lambda: sub.drain() >= 0 and bool(seen.extend(x[:2] for x in got.states) or seen),
            5.0,
        )
        assert wait_until(lambda: sub.drain() >= 0 and a.stats.states_refused > refused, 5.0)
        assert (2, 50) in [x[:2] for x in got.states]
        assert (2, 51) not in [x[:2] for x in got.states]


def test_a_called_back_subscription_has_nothing_to_drain(mesh_trio) -> None:
    _hub, a, _b = mesh_trio
    sub = a.subscribe_cells(Got().on_state, [keys.cell_of((0.0, 0.0, 0.0))])
    assert sub.drain() == 0


def test_a_flood_of_forged_future_states_neither_hides_a_real_one_nor_costs_past_the_budget(
    tmp_path,
) -> None:
    """Vehicle 3 floods states claiming to be vehicle 2, stamped 1 s ahead (within the clock
    skew allowed), with a check budget of 0: each vehicle's most plausible state is still tried
    (the real one: stamped as vehicle 2's verified states arrive), and without a real one the
    flood costs one check a drain, the rest dropped unchecked and reported."""
    got = Got()
    lines: list[str] = []
    with keyed_peers(tmp_path) as (auth, a, b):
        a.on_security = lines.append
        sub = a.subscribe_cells(
            got.on_state,
            ScopeConfig().cells_around((0, 0)),
            gate=GateConfig(batch_budget_s=0.0),
            polled=True,
        )
        seq = iter(range(1, 10_000))
        warm_up(
            sub, got, lambda k: b.publish_state(state(2, next(seq), time.time_ns()), auth=auth[2])
        )

        def flood(real: bool) -> int:
            now = time.time_ns()
            for k in range(100):
                b.publish_state(state(2, next(seq), now + 1_000_000_000 + k * MS), auth=auth[3])
            if real:
                b.publish_state(state(2, next(seq), now), auth=auth[2])
            time.sleep(0.5)  # all arrived: one drain takes them
            return sub.drain()

        with got.lock:
            got.states.clear()
        refused0, unchecked0 = a.stats.states_refused, a.stats.states_unchecked
        assert flood(real=True) == 101
        assert len(got.states) == 1, got.states  # the real one, tried first
        assert a.stats.states_refused == refused0  # no forged one was even checked
        assert flood(real=False) == 100
        assert len(got.states) == 1  # nothing new went on
        assert a.stats.states_refused - refused0 == 1  # one check: the budget is spent
        assert a.stats.states_unchecked - unchecked0 == 99
        assert any("left unchecked" in line for line in lines), lines
