"""One vehicle's guidance tick in Python floats (`BatchGuidance._step_one`, what every agent
runs) against the array path of any number of rows (`_step_rows`, the reference): the same
setpoints, flags and held decisions, tick by tick, on random scenes."""

from __future__ import annotations

import numpy as np
import pytest

from agent.guidance import BatchGuidance, GuidanceConfig, GuidanceStep, NeighbourViews


def _views(rng, k: int, sky: bool) -> NeighbourViews:
    ang = rng.uniform(0, 2 * np.pi, k)
    r = rng.uniform(2.5, 16.0, k)
    pos = np.zeros((1, k, 3))
    pos[0, :, 0], pos[0, :, 1], pos[0, :, 2] = r * np.cos(ang), r * np.sin(ang), -10.0
    vel = np.zeros((1, k, 3))
    vel[0, :, :2] = rng.normal(0.0, 0.8, (k, 2))
    valid = rng.random((1, k)) > 0.1
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
def test_one_row_in_floats_equals_the_rows_in_arrays(seed: int, zones: bool, c_core: bool) -> None:
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
        views = _views(rng, int(rng.integers(0, 14)), sky=rng.random() < 0.7)
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
