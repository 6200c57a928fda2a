"""Coincident vehicles in the batched guidance (what `covey fleet-sim` and a host fly): the
views carry ids, and two rows at one point are pushed apart, each its own way (issue 39 #7)."""

from __future__ import annotations

import numpy as np

from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews


def _step(with_ids: bool) -> np.ndarray:
    pos = np.array([[2.0, 3.0, -5.0], [2.0, 3.0, -5.0], [40.0, 0.0, -5.0]])
    ids = np.array([4, 9, 11])
    rows = np.arange(3)
    views = NeighbourViews.nearest(
        pos,
        rows,
        pos,
        np.zeros((3, 3)),
        np.zeros(3),
        np.ones(3, bool),
        np.zeros(3, bool),
        None,
        ids if with_ids else None,
        ids if with_ids else None,
    )
    out = BatchGuidance(GuidanceConfig(), 3).step(
        0.0, rows, pos, np.zeros((3, 3)), np.zeros(3), pos.copy(), np.ones(3, bool), views
    )
    return out.vel_ned_m_s[:, :2]


def test_two_rows_at_one_point_are_pushed_apart_by_id() -> None:
    assert np.allclose(_step(with_ids=False), 0.0), "without ids: no direction"
    v = _step(with_ids=True)
    assert np.hypot(*v[0]) > 0.5 and np.allclose(v[0], -v[1])
    assert np.allclose(v[2], 0.0), "a vehicle far off is not touched"
