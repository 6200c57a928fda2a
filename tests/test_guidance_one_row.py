"""One vehicle's guidance tick in Python floats (`BatchGuidance._step_one`, what every agent
runs) against the array path of any number of rows (`_step_rows`, the reference): the same
setpoints, flags and held decisions, tick by tick, on random scenes."""

from __future__ import annotations

import numpy as np
import pytest

from agent.guidance import BatchGuidance, GuidanceConfig, GuidanceStep, NeighbourViews


def _valid(rng, k: int, run: bool) -> np.ndarray:
    """(1, k) valid flags: scattered, or one run (an agent's views: its own entry first and
    invalid, then every neighbour: NeighbourViews.select slices them)."""
    if not run:
        return rng.random((1, k)) > 0.1
    first = int(rng.integers(0, 2)) if k else 0
    return (np.arange(k) >= first).reshape(1, k)


def _views(rng, k: int, sky: bool, run: bool = False) -> NeighbourViews:
    ang = rng.uniform(0, 2 * np.pi, k)
    r = rng.uniform(2.5, 16.0, k)
    pos = np.zeros((1, k, 3))
    pos[0, :, 0], pos[0, :, 1], pos[0, :, 2] = r * np.cos(ang), r * np.sin(ang), -10.0
    vel = np.zeros((1, k, 3))
    vel[0, :, :2] = rng.normal(0.0, 0.8, (k, 2))
    valid = _valid(rng, k, run)
    coop = rng.random((1, k)) > 0.2
    return NeighbourViews(
        pos,
        vel,
        rng.uniform(-np.pi, np.pi, (1, k)),
        valid,
        valid & (rng.random((1, k)) < 0.3),
        np.arange(2, 2 + k, dtype=np.int64).reshape(1, k),
        np.array([1], np.int64),
        rng.uniform(0.0, 0.6, (1, k)) if sky else None,
        coop if sky else None,
        np.array([0.5]) if sky else None,
        (~coop & (rng.random((1, k)) > 0.5)) if sky else None,
    )


def _same(a: GuidanceStep, b: GuidanceStep, what: str) -> None:
    np.testing.assert_allclose(a.vel_ned_m_s, b.vel_ned_m_s, rtol=0, atol=1e-12, err_msg=what)
    np.testing.assert_allclose(a.heading_rad, b.heading_rad, rtol=0, atol=1e-12, err_msg=what)
    for name in ("filtered", "slowed_for_stale", "decided"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), f"{what}: {name}"
        assert getattr(a, name).dtype == bool, f"{what}: {name}"
    if a.waypoint_m is None or b.waypoint_m is None:
        assert a.waypoint_m is None and b.waypoint_m is None, what
    else:
        np.testing.assert_array_equal(a.waypoint_m, b.waypoint_m, err_msg=what)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("zones", [False, True])
@pytest.mark.parametrize("c_core", [False, True])
@pytest.mark.parametrize("run", [False, True])
def test_one_row_in_floats_equals_the_rows_in_arrays(
    seed: int, zones: bool, c_core: bool, run: bool
) -> None:
    rng = np.random.default_rng(seed)
    cfg = GuidanceConfig(c_core=c_core)
    ref = BatchGuidance(cfg, 1)
    one = BatchGuidance(cfg, 1, ref.policy)
    if zones:
        square = np.array([[20.0, -4.0], [28.0, -4.0], [28.0, 4.0], [20.0, 4.0]])
        for g in (ref, one):
            g.set_zones([square])
    rows = np.zeros(1, int)
    pos = np.array([[0.0, 0.0, -10.0]])
    goal = np.array([[60.0, rng.uniform(-10, 10), -12.0]])
    acted = {"filtered": False, "slowed_for_stale": False, "holding": False, "capped": False}
    for t in range(40):
        now = None if rng.random() < 0.05 else 0.1 * t
        vel = np.array([[*rng.normal(0.6, 0.4, 2), 0.0]])
        heading = np.array([rng.uniform(-np.pi, np.pi)])
        holding = np.array([rng.random() < 0.25])
        if rng.random() < 0.1:  # a new goal now and then
            goal = np.array([[rng.uniform(-60, 60), rng.uniform(-60, 60), -10.0]])
        target = pos + np.array([[0.3, 0.0, 0.0]]) if holding[0] else goal
        decide = None if rng.random() < 0.7 else np.array([rng.random() < 0.5])
        cap = None if rng.random() < 0.6 else np.array([rng.choice([0.0, 0.4, 3.0])])
        views = _views(rng, int(rng.integers(0, 14)), sky=rng.random() < 0.7, run=run)
        args = (now, rows, pos, vel, heading, target, holding, views, decide, cap)
        a, b = one._step_one(*args), ref._step_rows(*args)
        what = f"seed {seed} tick {t}"
        _same(a, b, what)
        for name in ("held_m_s", "held_goal_m", "decided_s", "waypoint_m"):
            np.testing.assert_array_equal(getattr(one, name), getattr(ref, name), err_msg=what)
        acted["filtered"] |= bool(a.filtered[0])
        acted["slowed_for_stale"] |= bool(a.slowed_for_stale[0])
        acted["holding"] |= bool(holding[0])
        acted["capped"] |= cap is not None and 0 < cap[0] < 1
        pos = pos + 0.1 * a.vel_ned_m_s
    assert all(acted.values()), f"the scenes must exercise every branch: {acted}"


def test_step_takes_the_float_path_for_one_row_and_the_arrays_for_more() -> None:
    """`step` sends one row to `_step_one` and several to `_step_rows`."""
    g = BatchGuidance(GuidanceConfig(), 2)
    seen = []
    g._step_one = lambda *a: seen.append("one")  # type: ignore[method-assign]
    g._step_rows = lambda *a: seen.append("rows")  # type: ignore[method-assign]
    views = NeighbourViews(*(np.zeros((n, 0, 3)) for n in (1, 1)), *(np.zeros((1, 0)),) * 3)
    for n in (1, 2):
        g.step(
            0.0,
            np.arange(n),
            np.zeros((n, 3)),
            np.zeros((n, 3)),
            np.zeros(n),
            np.ones((n, 3)),
            np.zeros(n, bool),
            views,
        )
    assert seen == ["one", "rows"]


@pytest.mark.parametrize("seed", range(6))
def test_select_row_and_sky_take_the_neighbours_the_mask_takes(seed: int) -> None:
    """`select` (a slice over one run of valid entries, else the mask) picks exactly what the
    row's mask picks, field by field, in `row` and `sky` alike; a run is not copied."""
    rng = np.random.default_rng(seed)
    for _ in range(60):
        k = int(rng.integers(0, 10))
        n = int(rng.integers(1, 4))
        if rng.random() < 0.5:  # runs: all, none, a prefix, a suffix, a middle
            a, b = np.sort(rng.integers(0, k + 1, 2))
            valid = np.zeros((n, k), bool)
            valid[:, a:b] = True
        else:
            valid = rng.random((n, k)) < 0.6
        views = NeighbourViews(
            rng.normal(size=(n, k, 3)),
            rng.normal(size=(n, k, 3)),
            rng.normal(size=(n, k)),
            valid,
            valid & (rng.random((n, k)) < 0.5),
            rng.integers(1, 99, (n, k)),
            rng.integers(1, 99, n),
            rng.uniform(0, 1, (n, k)),
            rng.random((n, k)) < 0.5,
            rng.uniform(0, 1, n),
            rng.random((n, k)) < 0.5,
        )
        for r in range(n):
            mask = valid[r]
            sel = views.select(r)
            run = np.flatnonzero(mask)
            if run.size == 0 or run[-1] - run[0] + 1 == run.size:
                assert isinstance(sel, slice)
            for got, field in zip(
                views.row(r),
                (views.pos_m, views.vel_m_s, views.heading_rad, views.stale),
                strict=True,
            ):
                np.testing.assert_array_equal(got, field[r][mask])
                if isinstance(sel, slice) and got.size:
                    assert np.shares_memory(got, field)
            sky = views.sky(r, manned=True)
            assert sky["pos_sigma_m"] == views.own_pos_sigma_m[r]
            for name, field in (
                ("nbr_pos_sigma_m", views.pos_sigma_m),
                ("nbr_cooperative", views.cooperative),
                ("nbr_manned", views.manned),
            ):
                np.testing.assert_array_equal(sky[name], field[r][mask])
            assert views.sky(r, manned=True, sel=sel).keys() == sky.keys()


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("c_core", [False, True])
def test_one_rows_filter_in_floats_equals_the_filter_on_arrays(seed: int, c_core: bool) -> None:
    """`_filter_one` (own state in floats, neighbours as `select` picks them, the C core's
    kept arguments) answers exactly what the filter answers on the masked arrays: the C
    core's `evaluate` with the core on, policy.safety.filter_one with it off."""
    from policy import safety

    rng = np.random.default_rng(seed)
    g = BatchGuidance(GuidanceConfig(c_core=c_core), 1)
    assert (g.c_core is not None) == c_core
    changed = 0
    for _ in range(80):
        views = _views(
            rng, int(rng.integers(0, 14)), sky=rng.random() < 0.7, run=rng.random() < 0.5
        )
        own = rng.normal(0.0, 0.5, 2), rng.normal(0.6, 0.4, 2), rng.normal(0.6, 0.6, 2)
        pos_m, vel_m_s, pref_m_s = (tuple(x.tolist()) for x in own)
        vn, ve, filtered = g._filter_one(pos_m, vel_m_s, pref_m_s, views, None)
        mask = views.valid[0]
        if not mask.any():
            assert (vn, ve, filtered) == (*pref_m_s, False)
            continue
        nbrs = views.pos_m[0][mask][:, :2], views.vel_m_s[0][mask][:, :2]
        ids = (int(views.own_ids[0]), views.ids[0][mask])
        sky = {} if views.own_pos_sigma_m is None else {"pos_sigma_m": 0.5}
        for name, field in (
            ("nbr_pos_sigma_m", views.pos_sigma_m),
            ("nbr_cooperative", views.cooperative),
            ("nbr_manned", views.manned),
        ):
            if field is not None:
                sky[name] = field[0][mask]
        if c_core:
            assert g.c_core is not None
            r = g.c_core._filter.evaluate(*own, *nbrs, *ids, **sky)
            assert r.status == "ok"
            want = r.vel_m_s
        else:
            want = safety.filter_one(*own, *nbrs, g.safety_cfg, *ids, **sky)
        assert (vn, ve) == tuple(np.asarray(want, float).tolist())
        assert filtered == bool(np.linalg.norm(np.asarray(want) - own[2]) > 1e-6)
        changed += filtered
    assert changed >= 5, "the scenes must make the filter act"


def test_one_rows_step_shares_no_writable_array() -> None:
    """`_step_one`'s flags are shared read-only constants, its setpoints fresh arrays: a
    caller writing into one step's output cannot change another's."""
    rng = np.random.default_rng(3)
    g = BatchGuidance(GuidanceConfig(), 1)
    rows, pos = np.zeros(1, int), np.array([[0.0, 0.0, -10.0]])
    goal = np.array([[60.0, 0.0, -10.0]])
    steps = [
        g.step(
            0.1 * t, rows, pos, pos * 0, np.zeros(1), goal, np.zeros(1, bool), _views(rng, 6, True)
        )
        for t in range(3)
    ]
    a, b = steps[0], steps[1]
    for name in ("filtered", "slowed_for_stale", "decided"):
        with pytest.raises(ValueError):
            getattr(a, name)[0] = True
    assert not np.shares_memory(a.vel_ned_m_s, b.vel_ned_m_s)
    assert not np.shares_memory(a.heading_rad, b.heading_rad)
    before = b.vel_ned_m_s.copy()
    a.vel_ned_m_s[:] = 99.0
    np.testing.assert_array_equal(b.vel_ned_m_s, before)
