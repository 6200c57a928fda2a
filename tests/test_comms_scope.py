"""Spatial scoping: the reach formula, the grid keys, hysteresis, and on a real Zenoh mesh that a
vehicle hears every neighbour that could reach it, not the far ones, while a whole-fleet
subscriber still hears everyone and a state on a wrong cell is refused."""

from __future__ import annotations

import math
import threading
from dataclasses import replace

import numpy as np
import pytest
import zenoh

from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig
from agent.guidance import GuidanceConfig
from agent.hosts import Agent
from agent.shell_config import AgentConfig
from comms import keys
from comms.keys import CELL_M
from comms.schema import Command, Mode, VehicleState
from comms.scope import Scope, ScopeConfig
from tests.conftest import wait_until

FLEET = "scope"


def state(vid: int, n_m: float, e_m: float, seq: int = 1) -> VehicleState:
    return VehicleState(vid, seq, 1_000 + seq, (n_m, e_m, -10.0), (0.0, 0.0, 0.0), 0.0)


# -- the formula and the grid ------------------------------------------------------------------
def test_reach_is_sense_plus_separation_plus_closing_speed_times_handover() -> None:
    cfg = ScopeConfig()
    # 15 m sense + 3 m separation + (2 x 2 m/s) x (0.3 + 0.34 + 0.1 + 0.1 relay) s = 21.36 m for
    # movers; a holder heard every 2 s: 15 + 3 + 2 m/s x (0.3 + 2 + 0.1 + 0.1) s = 23 m, the larger
    assert cfg.handover_s == pytest.approx(0.84)
    assert cfg.reach_m == pytest.approx(max(15.0 + 3.0 + 4.0 * 0.84, 15.0 + 3.0 + 2.0 * 2.5))
    assert cfg.rings == 1  # (23 + 5) m fits one 30 m cell: a 3 x 3 block
    fast = ScopeConfig(max_speed_m_s=20.0)  # a holder's 2 s at 20 m/s: 18 + 20 x 2.5 = 68 m
    assert fast.reach_m == pytest.approx(max(18.0 + 40.0 * 0.84, 18.0 + 20.0 * 2.5))
    assert fast.rings == math.ceil((fast.reach_m + 5.0) / CELL_M) == 3
    assert len(fast.cells_around((0, 0))) == 49
    with pytest.raises(ValueError, match="max_speed_m_s"):
        ScopeConfig(max_speed_m_s=math.nan)


def test_guidance_widens_the_scope_to_what_it_needs() -> None:
    g = GuidanceConfig(separation_m=6.0, cruise_speed_m_s=3.0)
    s = g.scope(ScopeConfig())
    # the filter reaches 6 x (1 + margin 0.2) + 2 x 3 x 4 = 31.2 m; separation and top speed
    # follow guidance
    assert s.sense_range_m == pytest.approx(31.2)
    assert (s.separation_m, s.max_speed_m_s) == (6.0, 3.0)
    assert GuidanceConfig().scope(ScopeConfig()) == ScopeConfig()  # the defaults already cover it


def test_state_keys_carry_the_cell_of_the_position() -> None:
    assert keys.cell_of((29.9, -0.1, 0.0)) == (0, -1)
    assert keys.cell_of((-30.0, 60.0, 0.0)) == (-1, 2)
    key = keys.state(FLEET, 7, (3, -2))
    assert key == "covey/scope/c/3/-2/v/7/state"  # the cell first: docs/scaling.md, "Routers"
    assert keys.parse_state_key(key) == (FLEET, 7, (3, -2))
    assert keys.parse_vehicle_key(key) == (FLEET, 7, "state")  # recorders, replay, foxglove
    assert keys.parse_state_key(keys.state(FLEET, 7)) == (FLEET, 7, None)
    # recordings made with the cell after the id still parse
    assert keys.parse_state_key("covey/scope/v/7/c/3/-2/state") == (FLEET, 7, (3, -2))
    assert keys.parse_vehicle_key("covey/scope/c/3/-2/v/7/ack") is None  # only states have cells
    assert keys.parse_vehicle_key("covey/scope/v/7/c/3/-2/ack") is None
    assert keys.parse_vehicle_key("covey/scope/c/3/v/7/state") is None
    assert keys.parse_vehicle_key(f"covey/scope/c/{keys.MAX_CELL + 1}/0/v/7/state") is None
    assert keys.parse_vehicle_key("covey/scope/c/3/-2/v/0/state") is None
    # who hears what, by Zenoh's own key-expression rules
    placed, unplaced = zenoh.KeyExpr(key), zenoh.KeyExpr(keys.state(FLEET, 7))
    other = zenoh.KeyExpr(keys.state(FLEET, 8, (3, -2)))
    for k in (placed, unplaced):
        assert zenoh.KeyExpr(keys.all_states(FLEET)).intersects(k)
        assert zenoh.KeyExpr(keys.vehicle_states(FLEET, 7)).intersects(k)
    assert not zenoh.KeyExpr(keys.vehicle_states(FLEET, 7)).intersects(other)
    assert zenoh.KeyExpr(keys.cell_states(FLEET, (3, -2))).intersects(placed)
    assert not zenoh.KeyExpr(keys.cell_states(FLEET, (3, -1))).intersects(placed)
    assert not zenoh.KeyExpr(keys.all_states(FLEET)).intersects(zenoh.KeyExpr(keys.feed(FLEET, 7)))


def test_what_a_vehicle_sends_lives_under_msg_and_what_it_declares_under_v() -> None:
    """Acks, events, traces and feeds under msg/<id>/ (a router that forwards them walks no
    sibling per vehicle of the fleet); the command queryable and presence under v/<id>/; keys of
    recordings made before still parse; a leaf in the wrong place does not."""
    assert keys.ack(FLEET, 7) == "covey/scope/msg/7/ack"
    assert keys.event(FLEET, 7) == "covey/scope/msg/7/event"
    assert keys.trace(FLEET, 7) == "covey/scope/msg/7/trace"
    assert keys.feed(FLEET, 7) == "covey/scope/msg/7/feed"
    assert keys.cmd(FLEET, 7) == "covey/scope/v/7/cmd"
    assert keys.alive(FLEET, 7) == "covey/scope/v/7/alive"
    for leaf in ("ack", "event", "trace"):
        assert keys.parse_vehicle_key(f"covey/scope/msg/7/{leaf}") == (FLEET, 7, leaf)
        assert keys.parse_vehicle_key(f"covey/scope/v/7/{leaf}") == (FLEET, 7, leaf)  # old
    for leaf in ("cmd", "alive", "state"):
        assert keys.parse_vehicle_key(f"covey/scope/msg/7/{leaf}") is None
    assert keys.parse_feed_key("covey/scope/msg/7/feed") == (FLEET, 7)
    assert keys.parse_feed_key("covey/scope/v/7/feed") == (FLEET, 7)  # old recordings
    for whole, one in (
        (keys.all_acks, keys.ack),
        (keys.all_events, keys.event),
        (keys.all_feeds, keys.feed),
    ):
        assert zenoh.KeyExpr(whole(FLEET)).intersects(zenoh.KeyExpr(one(FLEET, 7)))
    assert zenoh.KeyExpr(keys.everything(FLEET)).intersects(zenoh.KeyExpr(keys.ack(FLEET, 7)))
    with pytest.raises(ValueError):
        keys.cell_states(FLEET, (1.5, 0))  # type: ignore[arg-type]


def test_cell_of_agrees_with_the_float32_the_wire_carries() -> None:
    """On a border, the sender's float64 and the receiver's float32 must give the same cell."""
    rng = np.random.default_rng(0)
    borders = CELL_M * rng.integers(-1000, 1000, 2000)
    for x in borders + rng.choice([-1e-9, 0.0, 1e-9, -1e-4, 1e-4], len(borders)):
        s = state(1, float(x), -float(x))
        received = VehicleState.decode(s.encode())
        assert keys.cell_of(s.pos_ned_m) == keys.cell_of(received.pos_ned_m)


def test_scope_covers_the_reach_and_has_hysteresis() -> None:
    cfg = ScopeConfig()
    scope = Scope(cfg)
    rng = np.random.default_rng(1)
    pos = np.array([14.0, 14.0])
    assert scope.update(pos) is not None
    for _ in range(3000):  # a random walk: every point within reach is always heard
        pos = pos + rng.normal(0.0, 2.0, 2)
        scope.update(pos)
        ang = rng.uniform(0, 2 * np.pi)
        q = pos + rng.uniform(0, cfg.reach_m) * np.array([np.cos(ang), np.sin(ang)])
        assert keys.cell_of((*q, 0.0)) in scope.cells
    # dithering across a border, within the hysteresis: no subscription change
    scope = Scope(cfg)
    scope.update(np.array([29.0, 5.0]))
    moves = scope.moves
    for k in range(50):
        assert scope.update(np.array([30.0 + (-1) ** k * (cfg.hysteresis_m - 0.5), 5.0])) is None
    assert scope.moves == moves
    assert scope.update(np.array([30.0 + cfg.hysteresis_m + 0.1, 5.0])) is not None


def test_scope_of_many_is_the_union_and_ignores_unplaced_rows() -> None:
    cfg = ScopeConfig()
    scope = Scope(cfg, 3)
    cells = scope.update(np.array([[5.0, 5.0, 0.0], [200.0, 5.0, 0.0], [np.nan, 0.0, 0.0]]))
    assert cells == cfg.cells_around((0, 0)) | cfg.cells_around((6, 0))
    assert scope.update(np.array([[6.0, 5.0, 0.0], [201.0, 5.0, 0.0], [np.nan, 0.0, 0.0]])) is None


def test_one_vehicle_s_fast_path_equals_a_row_of_the_array_path() -> None:
    """`Scope.update` of one vehicle (its no-move test on Python floats) answers as the same
    vehicle beside an unplaced row (the array path), on random walks across cell borders,
    near the hysteresis margin and through NaN fixes."""
    cfg = ScopeConfig()
    rng = np.random.default_rng(5)
    for _ in range(20):
        one, two = Scope(cfg), Scope(cfg, 2)
        pos = rng.uniform(-100.0, 100.0, 3)
        for _ in range(300):
            pos = pos + rng.normal(0.0, rng.choice([0.5, 3.0, 20.0]), 3)
            if rng.random() < 0.3:  # onto a border or the margin exactly
                c = rng.integers(-4, 4)
                pos[rng.integers(0, 2)] = c * keys.CELL_M + rng.choice([0.0, cfg.hysteresis_m])
            fix = pos.copy()
            if rng.random() < 0.03:
                fix[rng.integers(0, 2)] = rng.choice([np.nan, np.inf])
            got = one.update(fix.reshape(1, 3) if rng.random() < 0.5 else fix)
            want = two.update(np.array([fix, [np.nan, 0.0, 0.0]]))
            assert got == want
            assert one.cells == two.cells and one.moves == two.moves
            np.testing.assert_array_equal(one.anchor[0], two.anchor[0])


# -- on a real mesh ----------------------------------------------------------------------------
class Heard:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.seqs: dict[int, list[int]] = {}

    def on_state(self, s: VehicleState, _t: int) -> None:
        with self.lock:
            self.seqs.setdefault(s.vehicle_id, []).append(s.seq)

    def has(self, vid: int, seq: int) -> bool:
        with self.lock:
            return seq in self.seqs.get(vid, [])


def test_scoped_hears_its_cells_only_and_the_station_hears_all(mesh_trio) -> None:
    hub, a, b = mesh_trio
    station, scoped = Heard(), Heard()
    hub.subscribe_states(station.on_state)
    sub = a.subscribe_cells(scoped.on_state, ScopeConfig().cells_around((0, 0)))
    near = [(2, 10.0, 10.0), (3, -29.0, 59.0)]  # in the 3 x 3 block around cell (0, 0)
    far = [(4, 95.0, 0.0), (5, 0.0, -61.0), (6, 1000.0, 1000.0)]
    # repeat until the station has the last round: subscriptions take a moment to propagate
    for seq in range(1, 200):
        for vid, n, e in near + far:
            b.publish_state(state(vid, n, e, seq))
        if wait_until(
            lambda s=seq: (
                all(station.has(v, s) for v, _, _ in near + far)
                and all(scoped.has(v, s) for v, _, _ in near)
            ),
            0.2,
        ):
            break
    assert all(v in station.seqs for v, _, _ in near + far)
    assert set(scoped.seqs) == {2, 3}, "a far vehicle's states reached a scoped subscriber"
    # move the subscription: vehicle 4 (cell (3, 0)) comes in, 3 (cell (-1, 1)) goes
    sub.set_cells(ScopeConfig().cells_around((3, 0)))
    with scoped.lock:
        scoped.seqs.clear()
    for seq in range(200, 400):
        for vid, n, e in near + far:
            b.publish_state(state(vid, n, e, seq))
        if wait_until(lambda s=seq: scoped.has(4, s), 0.2):
            break
    assert wait_until(lambda: station.has(4, seq), 10.0)
    assert set(scoped.seqs) == {4}


def test_a_state_on_a_wrong_cell_is_refused_with_the_reason(mesh_trio) -> None:
    hub, a, b = mesh_trio
    station, scoped = Heard(), Heard()
    hub.subscribe_states(station.on_state)
    a.subscribe_cells(scoped.on_state, [(5, 5)])
    forged = state(9, 1.0, 1.0)  # really in cell (0, 0): hides in cell (5, 5)
    honest = state(9, 160.0, 160.0, seq=2)  # in cell (5, 5)
    for k in range(200):
        b.session.put(keys.state(FLEET, 9, (5, 5)), forged.encode())
        b.publish_state(replace(honest, seq=2 + k))
        # until both heard an honest state AND refused a forged one: the scoped subscription
        # may come up between the two puts, so one round need not show both
        if wait_until(
            lambda s=2 + k: (
                station.has(9, s)
                and scoped.has(9, s)
                and hub.stats.states_misplaced >= 1
                and a.stats.states_misplaced >= 1
            ),
            0.2,
        ):
            break
    assert hub.stats.states_misplaced >= 1 and a.stats.states_misplaced >= 1
    assert 1 not in station.seqs.get(9, []) and 1 not in scoped.seqs.get(9, [])
    assert "is in cell (0, 0), not in cell (5, 5)" in hub.stats.last_decode_error


def heard(ag: Agent, other: Agent, now_s: float) -> bool:
    """Whether `ag` hears `other`'s states, re-sent at `now_s` until they arrive (or 10 s): into
    its table, or, from beyond its reach, dropped there unchecked (agent/neighbours.py). The
    agent's subscription is polled: what came is taken as its tick would (`drain`)."""
    for _ in range(100):
        beyond = ag.mesh.stats.states_beyond_reach
        other.pacer.again()  # publish again at the same instant
        other.tick(now_s)
        seq = other.seq
        if wait_until(
            lambda s=seq, b=beyond: (
                ag.states.drain() >= 0
                and (other.vid in ag.table._latest and ag.table._latest[other.vid][0].seq >= s)
                or ag.mesh.stats.states_beyond_reach > b
            ),
            0.1,
        ):
            return True
    return False


def test_head_on_across_a_cell_corner_each_sees_the_other_in_time(mesh_trio) -> None:
    """Two agents fly at each other diagonally through the corner of four cells; each must hear
    the other while they are still farther apart than sense range + separation, and whenever
    the other is within reach its cell must be subscribed."""
    _hub, a_mesh, b_mesh = mesh_trio
    t = [0.0]
    alt_m = 10.0
    # head-on along the diagonal through (0, 0), the corner of cells (-1, -1) .. (0, 0), to
    # goals just past each other's side of the corner, 7 m apart: they end within reach
    starts = {1: (-40.0, -40.0), 2: (40.0, 40.0)}
    goals = {1: (2.5, 2.5), 2: (-2.5, -2.5)}
    agents = {}
    for vid, mesh in ((1, a_mesh), (2, b_mesh)):
        cfg = AgentConfig(
            vehicle_id=vid,
            failsafe=FailsafeConfig(require_gcs=False),
            guidance=GuidanceConfig(cruise_speed_m_s=2.0),
        )
        be = SimBackend(SimConfig(start_ned_m=(*starts[vid], 0.0)), now_s=0.0)
        agents[vid] = Agent(cfg, be, mesh, clock_s=lambda: t[0])
    scope = agents[1].scope.cfg
    try:
        for vid, ag in agents.items():
            ack = ag.handle_command(Command.takeoff(alt_m, nonce=vid, stamp_ns=0))
            assert ack.result.name == "ACCEPTED", ack
        dt_s = 0.1
        for _ in range(400):  # take off (the action queue's thread starts the climb)
            t[0] += dt_s
            for ag in agents.values():
                ag.tick(t[0])
            if all(ag.mode is Mode.HOLDING for ag in agents.values()):
                break
        assert all(ag.mode is Mode.HOLDING for ag in agents.values())
        for vid, ag in agents.items():
            n, e = goals[vid]
            ack = ag.handle_command(Command.goto_local(n, e, -alt_m, nonce=10 + vid, stamp_ns=0))
            assert ack.result.name == "ACCEPTED", ack
        first_heard_m: dict[int, float] = {}
        min_dist_m = math.inf
        for _ in range(1500):
            t[0] += dt_s
            for ag in agents.values():
                ag.tick(t[0])
            pos = {v: np.array(ag.backend.telemetry().pos_ned_m) for v, ag in agents.items()}
            dist_m = float(np.linalg.norm(pos[1][:2] - pos[2][:2]))
            min_dist_m = min(min_dist_m, dist_m)
            for vid, ag in agents.items():
                other = 3 - vid
                other_cell = keys.cell_of(tuple(pos[other]))
                if dist_m <= scope.reach_m:
                    assert other_cell in ag.states.cells, (vid, dist_m, other_cell)
                if vid not in first_heard_m and other_cell in ag.states.cells:
                    # subscribed: the other's next state must arrive (sim time waits for Zenoh
                    # to route the new subscription; the other re-publishes where it is)
                    assert heard(ag, agents[other], t[0]), (
                        f"vehicle {vid} never heard vehicle {other} in a subscribed cell"
                    )
                    first_heard_m[vid] = dist_m
            if all(np.hypot(*(pos[v][:2] - goals[v])) < 2.0 for v in agents) or t[0] > 200:
                break
        print(f"first heard at {first_heard_m} m; closest approach {min_dist_m:.2f} m")
        assert min_dist_m < scope.reach_m  # the within-reach check above did run
        for vid in agents:
            assert first_heard_m[vid] > scope.sense_range_m + scope.separation_m
        assert min_dist_m >= 0.9 * scope.separation_m
    finally:
        for ag in agents.values():
            ag.close()


def test_a_holder_at_rest_is_heard_within_the_reach() -> None:
    """A holder publishes every MAX_HOLD_PERIOD_S (comms/state_rate.py) and does not move
    between its states: what a vehicle entering its cells needs heard is within the reach the
    cells are chosen for, with the defaults and for faster fleets alike."""
    from comms.scope import ScopeConfig

    for cfg in (ScopeConfig(), ScopeConfig(max_speed_m_s=5.0), ScopeConfig(sense_range_m=30.0)):
        assert cfg.hold_reach_m <= cfg.reach_m
    assert ScopeConfig().hold_reach_m == pytest.approx(23.0)  # 15 + 3 + 2 x (0.3 + 2 + 0.1 + 0.1)
    # a wider sense range adds to both alike: the holder's is still the larger
    wide = ScopeConfig(sense_range_m=30.0)
    assert wide.reach_m == pytest.approx(wide.hold_reach_m) == pytest.approx(30.0 + 3.0 + 5.0)
