"""NeighbourTable.snapshot (array maths, cached per tick) equals snapshot_loop (the reference)."""

from __future__ import annotations

import numpy as np
import pytest

from agent.neighbours import NeighbourConfig, NeighbourTable
from comms.schema import Mode, VehicleState


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


def same(a, b) -> None:
    assert a.ids == b.ids and a.seqs == b.seqs and a.stale_ids == b.stale_ids
    for name in ("pos_ned_m", "vel_ned_m_s", "heading_rad", "age_s", "pos_sigma_m"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-12)
        assert getattr(a, name).shape == getattr(b, name).shape


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
