"""NeighbourTable.snapshot (array maths over a block cached per table version) equals
snapshot_loop (the reference), exactly; `expire` and `column` equal their plain forms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agent.neighbours import NeighbourConfig, NeighbourSnapshot, NeighbourTable
from comms.schema import Mode, VehicleState
from comms.state_rate import announces_hold


def fill(table: NeighbourTable, rng: np.random.Generator, n: int, now_s: float) -> None:
    modes = [Mode.GOTO, Mode.HOLDING, Mode.LANDED, Mode.KILLED]
    for vid in range(2, 2 + n):
        state = VehicleState(
            vid,
            int(rng.integers(1, 1000)),
            int(rng.integers(1, 10**9)),
            tuple(rng.uniform(-50, 50, 3) + (0, 0, -10)),
            tuple(rng.uniform(-5, 5, 3) * (rng.random() < 0.7)),  # some at rest
            float(rng.uniform(-3, 3)),
            modes[int(rng.integers(0, 4))],
            bool(rng.integers(0, 2)),
            pos_sigma_m=float(rng.uniform(0, 2)),
        )
        table.update(state, now_s - float(rng.uniform(0, 6)))


ARRAYS = ("pos_ned_m", "vel_ned_m_s", "heading_rad", "age_s", "pos_sigma_m")


def same(a, b) -> None:
    """Exactly the same snapshot: equal tuples, arrays of the same dtype, shape and layout
    holding the same numbers."""
    assert a.ids == b.ids and a.seqs == b.seqs and a.stale_ids == b.stale_ids
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.flags.c_contiguous and y.flags.c_contiguous, name
        np.testing.assert_array_equal(x, y, strict=True, err_msg=name)
    assert a.cooperative is None and b.cooperative is None
    assert a.manned is None and b.manned is None


@pytest.mark.parametrize("seed", range(6))
def test_snapshot_equals_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    table = NeighbourTable(1, NeighbourConfig(vertical_band_m=float(rng.uniform(1, 20))))
    now_s = 100.0
    fill(table, rng, int(rng.integers(0, 40)), now_s)
    for _ in range(5):
        own = np.array([0.0, 0.0, float(rng.uniform(-30, 10))])
        for pos in (own, None):
            fast = table.snapshot(now_s, pos)
            same(fast, table.snapshot_loop(now_s, pos))
        now_s += float(rng.uniform(0, 1.0))  # a later tick: dead reckoning moves, some expire


@pytest.mark.parametrize("seed", range(40))
def test_snapshot_equals_reference_tick_after_tick(seed: int) -> None:
    """The tables of a flight: states arriving, repeated, reordered, forgotten and expiring
    between ticks, two snapshots a tick (the landing order's and guidance's), writes into
    what a caller got; every snapshot equals the plain reference exactly."""
    rng = np.random.default_rng(1000 + seed)
    table = NeighbourTable(
        1,
        NeighbourConfig(
            vertical_band_m=float(rng.uniform(1, 20)), drop_s=float(rng.uniform(1.5, 4))
        ),
    )
    now_s = 50.0
    for _ in range(12):
        fill(table, rng, int(rng.integers(0, 30)), now_s)  # older receive times too
        if rng.random() < 0.3:  # received "after" now (a clock step): age 0
            fill(table, rng, 3, now_s + 1.0)
        if rng.random() < 0.3:
            table.forget(int(rng.integers(2, 20)))
        own = np.array([0.0, 0.0, float(rng.uniform(-30, 10))])
        for pos in (None, own, own):  # the second one from the cache
            fast = table.snapshot(now_s, pos)
            same(fast, table.snapshot_loop(now_s, pos))
            for name in ARRAYS:
                getattr(fast, name)[...] = -1.0  # a caller that writes into its copy
        now_s += float(rng.choice([0.0, 0.1, 0.1, 1.0, 3.0]))


def test_expire_forgets_as_the_plain_scan_does() -> None:
    """`expire` skips its scan while nobody can be `drop_s` old (its lower bound on the
    receive times): it forgets the same entries, tick after tick, as a scan of all of them,
    whatever order the receive times arrive in."""
    rng = np.random.default_rng(7)
    cfg = NeighbourConfig()
    table = NeighbourTable(1, cfg)
    now_s = 20.0
    for _ in range(300):
        for _ in range(int(rng.integers(0, 4))):
            vid = int(rng.integers(2, 12))
            vel = (0.0, 0.0, 0.0) if rng.random() < 0.5 else (1.0, 0.0, 0.0)
            mode = Mode.HOLDING if rng.random() < 0.5 else Mode.GOTO
            state = VehicleState(
                vid, int(rng.integers(1, 10**6)), 1, (0.0, 0.0, -10.0), vel, 0.0, mode, True
            )
            table.update(state, now_s - float(rng.choice([0.0, 0.0, 2.0, 5.0, 12.0])))
        held = dict(table._latest)
        want = {
            v
            for v, (s, t) in held.items()
            if not (
                now_s - t > cfg.drop_s
                and (now_s - t > cfg.hold_drop_s or not announces_hold(s.mode, s.vel_ned_m_s))
            )
        }
        table.expire(now_s)
        assert set(table.latest()) == want
        now_s += float(rng.choice([0.1, 0.1, 0.5, 2.0]))


def _column_reference(snap: NeighbourSnapshot, name: str, fill) -> np.ndarray:
    """`column` as it was written first: fill every row, then overwrite those given."""
    k = len(snap.ids)
    out = np.full(k, fill, dtype=np.asarray(fill).dtype)
    got = getattr(snap, name)
    if got is not None:
        got = np.asarray(got).reshape(-1)[:k]
        out[: len(got)] = got
    return out


@pytest.mark.parametrize("k", [0, 1, 5])
def test_column_equals_filling_and_overwriting(k: int) -> None:
    rng = np.random.default_rng(k)
    for got in (
        None,
        rng.random(k) < 0.5,
        rng.random(k),
        rng.random(k + 2),
        rng.random(max(k - 1, 0)),
        (rng.random(k) * 3).astype(np.int64),
        rng.random(k).astype(np.float32),
        list(rng.random(k)),
    ):
        for name in ("pos_sigma_m", "cooperative", "manned"):
            snap = NeighbourSnapshot(
                np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k), tuple(range(k)), np.zeros(k), ()
            )
            snap = dataclasses.replace(snap, **{name: got})
            for fill in (True, False, 0.0, -0.0, 1.5, 0):
                col = snap.column(name, fill)
                np.testing.assert_array_equal(col, _column_reference(snap, name, fill), strict=True)
                assert col.flags.c_contiguous and col.flags.owndata
                if isinstance(got, np.ndarray):
                    assert not np.shares_memory(col, got)  # a copy: the caller may write


def test_cache_follows_updates_and_callers_cannot_spoil_it() -> None:
    table = NeighbourTable(1)
    s = VehicleState(2, 1, 1, (0.0, 0.0, -10.0), (1.0, 0.0, 0.0), 0.0, Mode.GOTO, True)
    table.update(s, 10.0)
    first = table.snapshot(10.5)
    first.pos_ned_m[:] = 999.0  # a consumer that writes into its copy
    assert table.snapshot(10.5).pos_ned_m[0, 0] == pytest.approx(0.5)
    table.update(
        VehicleState(2, 2, 2, (5.0, 0.0, -10.0), (0.0, 0.0, 0.0), 0.0, Mode.GOTO, True), 10.5
    )
    assert table.snapshot(10.5).pos_ned_m[0, 0] == pytest.approx(5.0)
    table.forget(2)
    assert len(table.snapshot(10.5)) == 0


def _holder(vid: int, vel=(0.0, 0.0, 0.0), mode=Mode.HOLDING) -> VehicleState:
    return VehicleState(vid, 1, 1, (5.0 * vid, 0.0, -10.0), vel, 0.0, mode, True)


def test_a_holder_at_rest_is_waited_for_longer_than_a_mover() -> None:
    """A neighbour whose last state announces that it holds at rest publishes every 2 s
    (comms/state_rate.py): stale after hold_stale_s (5 s), forgotten after hold_drop_s (10 s);
    a holder drifting faster than rest, or a vehicle at rest in a goto, after stale_s and
    drop_s as before."""
    table = NeighbourTable(1)
    table.update(_holder(2), 0.0)
    table.update(_holder(3, vel=(0.2, 0.0, 0.0)), 0.0)
    table.update(_holder(4, mode=Mode.GOTO), 0.0)
    snap = table.snapshot(2.0)
    assert snap.stale_ids == (3, 4)
    same(snap, table.snapshot_loop(2.0))
    assert table.snapshot(3.5).ids == (2,)  # the movers forgotten after 3 s, the holder kept
    assert table.snapshot(4.9).stale_ids == ()
    assert table.snapshot(5.1).stale_ids == (2,)
    assert table.snapshot(10.1).ids == ()


@pytest.mark.parametrize(
    ("kw", "why"),
    [
        ({"stale_s": 0.0}, "stale_s must be a positive"),
        ({"hold_drop_s": float("nan")}, "hold_drop_s"),
        ({"hold_stale_s": 1.5}, "hold_stale_s must be at least 2 s"),
    ],
)
def test_bad_neighbour_settings_are_refused_with_the_reason(kw, why) -> None:
    with pytest.raises(ValueError, match=why):
        NeighbourConfig(**kw)
