"""neighbour_views of one vehicle (an agent's every tick: `_one_vehicle_views`) equals the
general path (`neighbour_views_rows`, the world and NeighbourViews.nearest) exactly: the same
arrays, in the same order, of the same dtypes, and the same fields None, for every mix of
neighbours, traffic, sigmas, stale entries and widths."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from agent import shell_views
from agent.guidance import NeighbourViews
from agent.neighbours import NeighbourConfig, NeighbourSnapshot, NeighbourTable
from agent.shell_rows import stale_mask
from agent.shell_views import neighbour_views, neighbour_views_rows
from agent.traffic import merge_traffic
from comms.schema import Mode, TrafficSource, VehicleState
from comms.traffic import TrafficTable, TrafficTrack

FIELDS = [f.name for f in dataclasses.fields(NeighbourViews)]
MODES = list(Mode)


def same(a: NeighbourViews, b: NeighbourViews) -> None:
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:
            assert x is None and y is None, name
            continue
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.flags.c_contiguous and y.flags.c_contiguous, name
        np.testing.assert_array_equal(x, y, strict=True, err_msg=name)


def _ext(rng: np.random.Generator, now_s: float, own: np.ndarray) -> NeighbourSnapshot:
    """A neighbour snapshot as an agent's tick builds it: the table's flying neighbours in the
    band (some stale, some with position sigmas), maybe with traffic merged."""
    table = NeighbourTable(1, NeighbourConfig(vertical_band_m=float(rng.uniform(2, 40))))
    for _ in range(int(rng.integers(0, 40))):
        state = VehicleState(
            int(rng.integers(2, 60)),
            int(rng.integers(1, 1000)),
            1,
            (*(own[:2] + rng.uniform(-60, 60, 2)), float(rng.uniform(-25, 0))),
            tuple(rng.uniform(-3, 3, 3) * (rng.random() < 0.7)),
            float(rng.uniform(-3, 3)),
            MODES[int(rng.integers(len(MODES)))],
            bool(rng.integers(0, 2)),
            pos_sigma_m=float(rng.uniform(0, 2)) * (rng.random() < 0.5),
        )
        table.update(state, now_s - float(rng.uniform(0, 2.5)))  # stale past 1 s
    ext = table.snapshot(now_s, own if rng.random() < 0.7 else None)
    pick = rng.random()
    if pick < 0.2:  # no sigma column at all
        ext = dataclasses.replace(ext, pos_sigma_m=None)
    elif pick < 0.4:  # all exact
        ext = dataclasses.replace(ext, pos_sigma_m=np.zeros(len(ext)))
    if rng.random() < 0.4:
        traffic = TrafficTable()
        for _ in range(int(rng.integers(1, 6))):
            traffic.put(
                TrafficTrack(
                    int(rng.integers(1, 10**6)),
                    (*(own[:2] + rng.uniform(-80, 80, 2)), float(own[2] + rng.uniform(-8, 8))),
                    tuple(rng.uniform(-20, 20, 3)),
                    TrafficSource(int(rng.integers(1, 4))),
                    bool(rng.integers(0, 2)),
                    now_s - float(rng.uniform(0, 4)),
                )
            )
        ext = merge_traffic(traffic, ext, now_s, own if rng.random() < 0.5 else None)
    elif rng.random() < 0.2 and len(ext):  # the columns given, all plain
        ext = dataclasses.replace(
            ext, cooperative=np.ones(len(ext), bool), manned=np.zeros(len(ext), bool)
        )
    return ext


def _vehicle(rng: np.random.Generator, n: int = 1):
    """(core, obs, pos_sigma_m, ids) of n vehicles, airborne or not."""
    pos = np.column_stack([rng.uniform(-30, 30, (n, 2)), rng.uniform(-20, 0, n)])
    modes = [int(MODES[i]) for i in rng.integers(0, len(MODES), n)]  # LANDED: not airborne
    core = SimpleNamespace(mode=np.array(modes), heading_rad=rng.uniform(-3, 3, n))
    obs = SimpleNamespace(
        pos_m=pos, vel_m_s=rng.uniform(-3, 3, (n, 3)), armed=rng.integers(0, 2, n).astype(bool)
    )
    sigma = rng.uniform(0, 2, n) * (rng.random(n) < 0.5)
    ids = np.arange(1, n + 1, dtype=np.int32 if rng.random() < 0.2 else np.int64)
    return core, obs, sigma, ids


@pytest.mark.parametrize("seed", range(300))
def test_one_vehicle_views_equal_the_general_path(seed: int) -> None:
    rng = np.random.default_rng(seed)
    now_s = 40.0
    core, obs, sigma, ids = _vehicle(rng)
    ext = _ext(rng, now_s, obs.pos_m[0])
    rows = np.array([0])
    k = len(ext)
    widths = {None, 0, 1, 3, 10, k, k + 1, k + 5, int(rng.integers(0, 50))}
    for max_neighbours in widths:
        fast = neighbour_views(core, obs, sigma, ids, ext, rows, max_neighbours)
        same(fast, neighbour_views_rows(core, obs, sigma, ids, ext, rows, max_neighbours))
        assert fast.pos_m.shape[:2] == fast.valid.shape
        if max_neighbours != 0:  # the plain inputs take the fast path
            assert (
                shell_views._one_vehicle_views(core, obs, sigma, ids, ext, rows, max_neighbours)
                is not None
            )


def test_one_vehicle_does_not_build_the_world(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fast path is the one taken for one vehicle: the general one is not called."""
    rng = np.random.default_rng(3)
    core, obs, sigma, ids = _vehicle(rng)
    ext = _ext(rng, 40.0, obs.pos_m[0])

    def general(*args):
        raise AssertionError("the general path was taken")

    monkeypatch.setattr(shell_views, "neighbour_views_rows", general)
    for max_neighbours in (None, 2):
        neighbour_views(core, obs, sigma, ids, ext, np.array([0]), max_neighbours)


def test_the_cases_that_matter_are_drawn() -> None:
    """The seeds above draw every case: more neighbours than the width, none, stale ones,
    traffic (manned too), sigmas absent, the vehicle on the ground."""
    seen: set[str] = set()
    for seed in range(300):
        rng = np.random.default_rng(seed)
        core, obs, sigma, ids = _vehicle(rng)
        ext = _ext(rng, 40.0, obs.pos_m[0])
        seen |= {
            "more than 10" if len(ext) > 10 else "",
            "none" if len(ext) == 0 else "",
            "stale" if ext.stale_ids else "",
            "traffic" if ext.cooperative is not None and not ext.cooperative.all() else "",
            "manned" if ext.manned is not None and ext.manned.any() else "",
            "no sigma" if ext.pos_sigma_m is None else "",
            "landed" if core.mode[0] == Mode.LANDED else "",
        }
    assert seen >= {"more than 10", "none", "stale", "traffic", "manned", "no sigma", "landed"}


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_a_neighbour_where_the_vehicle_is_and_far_ones() -> None:
    """Ties of the distance key (a neighbour on top of the vehicle, several at the same
    distance), non-finite positions: the same argpartition chooses the same entries."""
    core = SimpleNamespace(mode=np.array([int(Mode.GOTO)]), heading_rad=np.array([0.5]))
    obs = SimpleNamespace(
        pos_m=np.array([[1.0, 2.0, -10.0]]), vel_m_s=np.zeros((1, 3)), armed=np.array([True])
    )
    pos = np.array(
        [[1.0, 2.0, -10.0], [4.0, 6.0, -10.0], [-2.0, -2.0, -10.0], [4.0, 6.0, -9.0]]
        + [[np.inf, 0.0, -10.0], [np.nan, 0.0, -10.0], [1e200, 0.0, -10.0], [5.0, 2.0, -10.0]]
    )
    k = len(pos)
    ext = NeighbourSnapshot(
        pos, np.ones((k, 3)), np.zeros(k), tuple(range(10, 10 + k)), np.zeros(k), (11, 13, 14, 15)
    )  # stale: a far one, a tied one, the infinite and the NaN one (not valid: not stale)
    for max_neighbours in (None, 1, 2, 3, 4, 5, 6, 7, 8, 9, 20):
        args = (core, obs, np.zeros(1), np.array([1]), ext, np.array([0]), max_neighbours)
        same(neighbour_views(*args), neighbour_views_rows(*args))


@pytest.mark.parametrize("seed", range(20))
def test_several_vehicles_take_the_general_path(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 5))
    core, obs, sigma, ids = _vehicle(rng, n)
    ext = _ext(rng, 40.0, obs.pos_m[0])
    rows = np.flatnonzero(rng.random(n) < 0.7)
    for max_neighbours in (None, 3):
        same(
            neighbour_views(core, obs, sigma, ids, ext, rows, max_neighbours),
            neighbour_views_rows(core, obs, sigma, ids, ext, rows, max_neighbours),
        )


@pytest.mark.parametrize("seed", range(10))
def test_stale_entries_are_those_isin_finds(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ext = _ext(rng, 40.0, np.array([0.0, 0.0, -10.0]))
    want = np.isin(np.asarray(ext.ids, np.int64), np.asarray(ext.stale_ids, np.int64))
    np.testing.assert_array_equal(stale_mask(ext), want, strict=True)


def _empty() -> NeighbourSnapshot:
    return NeighbourSnapshot(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), (), np.zeros(0), ())


@pytest.mark.parametrize("seed", range(100))
def test_all_kept_views_equal_the_general_path(seed: int) -> None:
    """An agent's every tick (no traffic columns, every entry kept: at the limit, under it,
    none) takes `_all_kept_views`, with or without sigmas, stale entries, neighbours; a
    sigma column shorter than the snapshot (traffic rows appended, here with the traffic
    columns dropped) is left to the array path."""
    rng = np.random.default_rng(1000 + seed)
    core, obs, sigma, ids = _vehicle(rng)
    ext = _ext(rng, 40.0, obs.pos_m[0])
    ext = dataclasses.replace(ext, cooperative=None, manned=None)
    rows = np.array([0])
    for snap in (ext, _empty()):
        k = len(snap)
        fits = snap.pos_sigma_m is None or snap.pos_sigma_m.shape == (k,)
        for max_neighbours in (None, k + 1, k + 4):
            args = (core, obs, sigma, ids, snap, rows, max_neighbours)
            want = neighbour_views_rows(*args)
            fast = shell_views._all_kept_views(core, obs, sigma, ids, snap)
            assert (fast is not None) == fits
            if fast is not None:
                same(fast, want)
            same(neighbour_views(*args), want)


def test_all_kept_cases_are_drawn() -> None:
    """The seeds above draw stale entries, sigmas absent, all 0 and not, on both sides."""
    seen: set[str] = set()
    for seed in range(100):
        rng = np.random.default_rng(1000 + seed)
        core, obs, sigma, ids = _vehicle(rng)
        ext = _ext(rng, 40.0, obs.pos_m[0])
        if ext.cooperative is not None or ext.manned is not None:  # the array path's
            continue
        views = shell_views._all_kept_views(core, obs, sigma, ids, ext)
        assert views is not None
        seen |= {
            "stale" if ext.stale_ids else "",
            "no sigma" if ext.pos_sigma_m is None else "",
            "exact" if views.pos_sigma_m is None else "sigmas",
            "own sigma" if sigma[0] else "",
            "int32 ids" if ids.dtype == np.int32 else "",
        }
    assert seen >= {"stale", "no sigma", "exact", "sigmas", "own sigma", "int32 ids"}


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_all_kept_leaves_the_odd_inputs_to_the_array_path() -> None:
    """Non-finite or huge coordinates or sigmas, other dtypes: `_all_kept_views` answers None
    and `neighbour_views` still equals the general path."""
    rng = np.random.default_rng(7)
    core, obs, _, ids = _vehicle(rng)
    sigma = np.array([0.5])
    ext = _ext(rng, 40.0, obs.pos_m[0])
    while len(ext) < 3 or ext.cooperative is not None or ext.pos_sigma_m is None:
        ext = _ext(rng, 40.0, obs.pos_m[0])
    rows = np.array([0])
    odd = []
    for bad in (np.inf, -np.inf, np.nan, 1e151):
        for column in (0, 1, 2):
            pos = ext.pos_ned_m.copy()
            pos[1, column] = bad
            odd.append((core, obs, sigma, ids, dataclasses.replace(ext, pos_ned_m=pos)))
        own = SimpleNamespace(**{**vars(obs), "pos_m": obs.pos_m.copy()})
        own.pos_m[0, 0] = bad
        odd.append((core, own, sigma, ids, ext))
        odd.append((core, obs, np.array([bad]), ids, ext))
    f4 = np.float32
    odd += [
        (core, obs, sigma, ids, dataclasses.replace(ext, vel_ned_m_s=ext.vel_ned_m_s.astype(f4))),
        (core, obs, sigma, ids, dataclasses.replace(ext, heading_rad=ext.heading_rad.astype(f4))),
        (core, obs, sigma, ids, dataclasses.replace(ext, pos_sigma_m=ext.pos_sigma_m.astype(f4))),
        (core, obs, sigma.astype(f4), ids, ext),
        (core, obs, sigma, ids.astype(np.uint32), ext),
        (SimpleNamespace(mode=core.mode, heading_rad=core.heading_rad.astype(f4)), obs, sigma)
        + (ids, ext),
    ]
    for case in odd:
        assert shell_views._all_kept_views(*case) is None
        args = (*case, rows, None)
        same(neighbour_views(*args), neighbour_views_rows(*args))


def test_all_kept_views_share_only_what_is_read_only() -> None:
    """Two ticks' views share no writable memory: the cached valid and stale are read-only."""
    rng = np.random.default_rng(5)
    core, obs, sigma, ids = _vehicle(rng)
    ext = _ext(rng, 40.0, obs.pos_m[0])
    while ext.stale_ids or ext.cooperative is not None or not len(ext):
        ext = _ext(rng, 40.0, obs.pos_m[0])
    a = shell_views._all_kept_views(core, obs, sigma + 1.0, ids, ext)
    b = shell_views._all_kept_views(core, obs, sigma + 1.0, ids, ext)
    assert a is not None and b is not None
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if x is not None and np.shares_memory(x, y):
            assert not x.flags.writeable and not y.flags.writeable, name
