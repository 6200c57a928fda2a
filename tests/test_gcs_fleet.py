"""The ground station's fleet model: link rate, loss from seq gaps, trails, separation, presence."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import views_by_id

from comms.schema import Mode, StateFlag, VehicleState
from groundstation.fleet import NS_PER_S, FleetConfig, FleetModel, close_pairs, link_health


def state(vid: int, seq: int, pos=(0.0, 0.0, -5.0), vel=(1.0, 0.0, 0.0), **kw) -> VehicleState:
    return VehicleState(
        vehicle_id=vid,
        seq=seq,
        stamp_ns=seq,
        pos_ned_m=pos,
        vel_ned_m_s=vel,
        heading_rad=0.0,
        mode=kw.pop("mode", Mode.GOTO),
        **kw,
    )


def feed(
    model: FleetModel,
    vid: int,
    n: int,
    rate_hz: float,
    t0_s: float = 0.0,
    drop=lambda seq: False,
    pos=lambda seq: (0.0, 0.0, -5.0),
) -> float:
    """Feed n states at rate_hz starting at t0_s; returns the time of the last one (s)."""
    t = t0_s
    for seq in range(n):
        t = t0_s + seq / rate_hz
        if not drop(seq):
            model.on_state(state(vid, seq, pos=pos(seq)), int(t * NS_PER_S))
    return t


def test_rate_and_no_loss_at_10_hz():
    model = FleetModel()
    t = feed(model, 1, 50, 10.0)
    v = model.snapshot(int(t * NS_PER_S)).vehicles[0]
    assert v.rate_hz == pytest.approx(10.0, rel=1e-6)
    assert v.loss_pct == 0.0
    assert v.age_s == 0.0 and not v.stale


def test_loss_estimated_from_sequence_gaps():
    model = FleetModel(FleetConfig(rate_window_s=10.0))
    t = feed(model, 1, 101, 10.0, drop=lambda seq: seq % 5 == 2)  # one in five lost
    v = model.snapshot(int(t * NS_PER_S)).vehicles[0]
    assert v.loss_pct == pytest.approx(20.0, abs=1.5)
    assert v.rate_hz == pytest.approx(8.0, abs=0.3)


def test_through_the_feed_loss_counts_lost_entries_not_thinned_states():
    """A 10 Hz vehicle seen through a 5 Hz feed: every other state never leaves its process
    (seq steps by 2), which is no loss; a lost feed entry (a gap in its entry numbers) is."""
    model = FleetModel(FleetConfig(rate_window_s=10.0, stale_after_s=1.0))
    model.on_presence(1, True, 0)
    got = [n for n in range(1, 51) if n % 5 != 3]  # one entry in five lost on the way
    for n in got:
        model.on_state(state(1, 2 * n), int(n * 0.2 * NS_PER_S), n)
    v = model.snapshot(int(got[-1] * 0.2 * NS_PER_S)).vehicles[0]
    assert v.loss_pct == pytest.approx(20.0, abs=2.5)
    assert v.rate_hz == pytest.approx(4.0, abs=0.3)  # updates reaching the station
    assert not v.stale  # a 0.2 s feed period is well inside the 1 s stale threshold
    # A restarted publisher numbers its entries from 1 again: counted afresh, no false loss.
    t_s = got[-1] * 0.2
    for k in range(1, 11):
        model.on_state(state(1, 1000 + 2 * k), int((t_s + k * 0.2) * NS_PER_S), k)
    v = model.snapshot(int((t_s + 2.0) * NS_PER_S)).vehicles[0]
    assert v.loss_pct == 0.0 and v.rate_hz == pytest.approx(5.0)


def test_age_grows_and_stale_flag_when_states_stop():
    model = FleetModel(FleetConfig(stale_after_s=1.0))
    t = feed(model, 1, 10, 10.0)
    v = model.snapshot(int((t + 1.5) * NS_PER_S)).vehicles[0]
    assert v.age_s == pytest.approx(1.5) and v.stale
    assert v.rate_hz == pytest.approx(10.0)  # still from the window's samples


def test_window_forgets_old_samples():
    model = FleetModel(FleetConfig(rate_window_s=2.0))
    feed(model, 1, 20, 10.0)  # 0 .. 1.9 s
    v = model.snapshot(int(10 * NS_PER_S)).vehicles[0]
    assert v.rate_hz == 0.0 and v.loss_pct == 0.0


def test_duplicates_and_late_states_are_ignored_restart_resets():
    model = FleetModel()
    model.on_state(state(1, 10, pos=(1.0, 0.0, 0.0)), 1 * NS_PER_S)
    model.on_state(state(1, 10, pos=(9.0, 0.0, 0.0)), 2 * NS_PER_S)  # duplicate
    model.on_state(state(1, 8, pos=(8.0, 0.0, 0.0)), 3 * NS_PER_S)  # late
    assert model.positions()[1] == (1.0, 0.0, 0.0)
    model.on_state(
        state(1, 0, pos=(2.0, 0.0, 0.0)), 4 * NS_PER_S
    )  # seq 10 -> 0: small jump back, late
    assert model.positions()[1] == (1.0, 0.0, 0.0)
    model.on_state(state(1, 5000, pos=(3.0, 0.0, 0.0)), 5 * NS_PER_S)
    model.on_state(state(1, 1, pos=(4.0, 0.0, 0.0)), 6 * NS_PER_S)  # big jump back: agent restarted
    assert model.positions()[1] == (4.0, 0.0, 0.0)


def test_trail_keeps_60_s_thinned():
    cfg = FleetConfig(trail_s=60.0, trail_min_step_s=0.2)
    model = FleetModel(cfg)
    model.on_presence(1, True, 0)  # present: a vehicle without a token is forgotten after 10 s
    t = feed(model, 1, 1200, 10.0, pos=lambda seq: (seq * 0.1, 0.0, -5.0))  # 120 s at 10 Hz
    trail = model.snapshot(int(t * NS_PER_S)).vehicles[0].trail_ned_m
    assert trail.shape[1] == 3
    assert 295 <= len(trail) <= 301  # 60 s at one point per 0.2 s
    assert trail[-1][0] == pytest.approx(119.9, abs=0.2)
    assert trail[0][0] == pytest.approx(60.0, abs=0.5)
    assert np.all(np.diff(trail[:, 0]) > 0)


def test_separation_alerts_pairs_closer_than_3_m():
    model = FleetModel(FleetConfig(separation_m=3.0))
    model.on_state(state(1, 1, pos=(0.0, 0.0, -5.0)), NS_PER_S)
    model.on_state(state(2, 1, pos=(2.0, 0.0, -5.0)), NS_PER_S)  # 2 m from 1
    model.on_state(state(3, 1, pos=(0.0, 10.0, -5.0)), NS_PER_S)
    model.on_state(state(4, 1, pos=(0.0, 10.0, -7.9)), NS_PER_S)  # 2.9 m above 3
    snap = model.snapshot(NS_PER_S)
    assert [(a, b) for a, b, _ in snap.close_pairs] == [(1, 2), (3, 4)]
    assert all(v.too_close for v in snap.vehicles)
    model.on_state(state(2, 2, pos=(3.5, 0.0, -5.0)), 2 * NS_PER_S)
    snap = model.snapshot(2 * NS_PER_S)
    assert [(a, b) for a, b, _ in snap.close_pairs] == [(3, 4)]
    assert [v.too_close for v in snap.vehicles] == [False, False, True, True]


def test_close_pairs_matches_a_plain_loop():
    rng = np.random.default_rng(3)
    positions = [(i + 1, tuple(rng.uniform(-10, 10, 3))) for i in range(40)]
    expected = sorted(
        (a, b)
        for i, (a, pa) in enumerate(positions)
        for b, pb in positions[i + 1 :]
        if math.dist(pa, pb) < 3.0
    )
    assert sorted((a, b) for a, b, _ in close_pairs(positions, 3.0)) == expected


def _plain_close_pairs(positions, separation_m):
    """The reference: every pair, compared one by one."""
    return sorted(
        (min(a, b), max(a, b), math.dist(pa, pb))
        for i, (a, pa) in enumerate(positions)
        for b, pb in positions[i + 1 :]
        if math.dist(pa, pb) < separation_m
    )


@pytest.mark.parametrize("seed", range(6))
def test_close_pairs_grid_equals_the_plain_loop_on_hard_layouts(seed):
    """The vectorised grid against the plain loop: spread out, all in one cell, exactly on cell
    borders, negative coordinates, ids in any order, 0-300 vehicles."""
    rng = np.random.default_rng(seed)
    sep = float(rng.choice([0.5, 3.0, 7.5]))
    layouts = [
        rng.uniform(-40, 40, (300, 3)),  # spread: a few close pairs
        rng.uniform(-0.4, 0.4, (60, 3)) * sep,  # one cell: every pair
        np.round(rng.uniform(-5, 5, (200, 3))) * sep,  # on the borders, many at exactly sep
        rng.normal(0, 2 * sep, (150, 3)) + [[-1e5, 2e4, 0.0]],  # far from the origin
        rng.uniform(-10, 10, (2, 3)),
        rng.uniform(-10, 10, (1, 3)),
        np.zeros((0, 3)),
    ]
    for pos in layouts:
        vids = rng.permutation(np.arange(1, len(pos) + 1) * 3).tolist()
        positions = [(vid, tuple(float(x) for x in p)) for vid, p in zip(vids, pos, strict=True)]
        got = close_pairs(positions, sep)
        want = _plain_close_pairs(positions, sep)
        assert [(a, b) for a, b, _ in got] == [(a, b) for a, b, _ in want]
        assert np.allclose([d for *_, d in got], [d for *_, d in want], rtol=0, atol=1e-9)


def test_snapshot_link_health_equals_the_window_it_summarises():
    """The snapshot reads the rate window at its ends; the reference filters the whole window:
    irregular arrivals, gaps longer than the window, losses, and snapshots at earlier and later
    instants than the last arrival."""
    cfg = FleetConfig(rate_window_s=3.0)
    rng = np.random.default_rng(5)
    model = FleetModel(cfg)
    model.on_presence(1, True, 0)  # present: never forgotten
    window_ns = int(cfg.rate_window_s * NS_PER_S)
    history: list[tuple[int, int]] = []
    t_ns, seq = NS_PER_S, 0
    for _ in range(400):
        t_ns += int(
            rng.choice([0.05, 0.1, 0.1, 0.3, 4.0], p=[0.2, 0.5, 0.2, 0.09, 0.01]) * NS_PER_S
        )
        seq += int(rng.choice([1, 1, 1, 2, 5]))
        model.on_state(state(1, seq), t_ns)
        history.append((t_ns, seq))
        for now_ns in (t_ns, t_ns - NS_PER_S // 2, t_ns + int(rng.uniform(0, 5) * NS_PER_S)):
            kept = [(t, s) for t, s in history if t >= t_ns - window_ns]
            recent = [(t, s) for t, s in kept if t >= now_ns - window_ns]
            view = model.snapshot(now_ns, trails=False).vehicles[0]
            assert (view.rate_hz, view.loss_pct) == pytest.approx(link_health(recent))


def test_snapshot_without_trails_shares_one_read_only_empty_trail():
    model = FleetModel()
    for vid in (1, 2):
        model.on_state(state(vid, 1, pos=(vid * 10.0, 0.0, -5.0)), NS_PER_S)
    views = model.snapshot(NS_PER_S, trails={2}).vehicles
    assert views[0].trail_ned_m.shape == (0, 3) and not views[0].trail_ned_m.flags.writeable
    assert views[1].trail_ned_m.tolist() == [[20.0, 0.0, -5.0]]


def test_presence_loss_and_return():
    model = FleetModel()
    model.on_presence(7, True, 0)
    assert model.snapshot(0).vehicles[0].alive and model.snapshot(0).vehicles[0].state is None
    model.on_state(state(7, 1, flags=StateFlag.HAS_GOAL, goal_ned_m=(1.0, 2.0, -3.0)), 10)
    v = model.snapshot(10).vehicles[0]
    assert v.has_goal and v.alt_m == 5.0 and v.speed_m_s == 1.0
    model.on_presence(7, False, 20)
    v = model.snapshot(20).vehicles[0]
    assert not v.alive and v.state is not None  # last state is kept to show where it was lost
    model.on_presence(7, True, 30)
    assert model.snapshot(30).vehicles[0].alive


def test_link_health_edge_cases():
    assert link_health([]) == (0.0, 0.0)
    assert link_health([(0, 5)]) == (0.0, 0.0)
    assert link_health([(0, 5), (0, 6)]) == (0.0, 0.0)  # same stamp: no rate, no loss


@pytest.mark.parametrize("field", ["trail_s", "rate_window_s", "separation_m"])
@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_config_rejects_bad_values(field, bad):
    with pytest.raises(ValueError, match=field):
        FleetConfig(**{field: bad})


def test_vehicles_without_a_token_expire_and_the_table_is_bounded():
    model = FleetModel(FleetConfig(unconfirmed_expire_s=10.0, lost_expire_s=60.0, max_vehicles=50))
    model.on_presence(1, True, 0)
    model.on_presence(2, True, 0)
    model.on_presence(2, False, int(5 * NS_PER_S))  # vehicle 2 lost at 5 s
    # A flood of 5,000 made-up ids for 20 s: the table never holds more than max_vehicles.
    for k in range(5000):
        t_ns = int(k * 20.0 / 5000 * NS_PER_S)
        model.on_state(state(100 + k, 1), t_ns)
        model.on_state(state(1, k + 1), t_ns)
        assert len(model.ids()) <= 50
    assert model.refused_states > 4000
    # A real vehicle that joins during the flood takes the place of a phantom.
    model.on_presence(3, True, int(20 * NS_PER_S))
    assert 3 in model.ids()
    # Within the expiry time after the flood, only real vehicles are listed (2 is shown LOST).
    snap = model.snapshot(int(31 * NS_PER_S))
    assert [v.vehicle_id for v in snap.vehicles] == [1, 2, 3]
    assert not views_by_id(snap)[2].alive
    # A lost vehicle is forgotten lost_expire_s after it was lost.
    assert [v.vehicle_id for v in model.snapshot(int(66 * NS_PER_S)).vehicles] == [1, 3]
    assert model.expired > 0


def test_refused_states_mark_a_known_vehicle_and_never_create_a_phantom() -> None:
    m = FleetModel(FleetConfig(unverified_window_s=3.0))
    m.on_presence(1, True, 0)
    m.on_state(state(1, 1), 0)
    m.on_state_refused(1, "forged", 1 * NS_PER_S)
    for vid in range(100, 5100):  # 5000 phantom ids whose states the mesh refused
        m.on_state_refused(vid, "unknown signer", 1 * NS_PER_S)
    snap = views_by_id(m.snapshot(2 * NS_PER_S))
    assert set(snap) == {1} and m.phantom_refusals == 5000
    assert snap[1].unverified and snap[1].refused_states == 1 and snap[1].refused_cause == "forged"
    assert not views_by_id(m.snapshot(5 * NS_PER_S))[
        1
    ].unverified  # the mark fades after the window


def test_vehicles_never_present_are_forgotten_but_present_ones_stay() -> None:
    m = FleetModel(FleetConfig(unconfirmed_expire_s=10.0, lost_expire_s=60.0))
    m.on_presence(1, True, 0)
    m.on_state(state(1, 1), 0)
    m.on_state(state(7, 1), 0)  # states, but never a liveliness token (open mode phantom)
    assert m.ids() == [1, 7]
    m.on_presence(1, False, 1 * NS_PER_S)  # a real vehicle that left stays, shown LOST
    assert [v.vehicle_id for v in m.snapshot(31 * NS_PER_S).vehicles] == [1]
