"""`covey eval` flies the C core as onboard (c+filter): C decision hold + C separation filter."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from policy import evalsim, scenarios

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


def test_eval_flies_the_c_core_with_its_filter(tmp_path):
    from firmware.ceval import main
    from policy.eval import EvalConfig

    res = main(
        EvalConfig(
            out=str(tmp_path),
            quick=True,
            suites=("circle", "conflict"),
            links=("perfect", "degraded"),
            progress=False,
            figures=False,
            controllers=("c+filter",),
        )
    )
    rows = res["summary"]
    assert {r["controller"] for r in rows} == {"c+filter"} and len(rows) == 4
    for r in rows:
        assert r["collisions"] == 0 and r["success"] == 1.0, r


def test_c_fleet_holds_decisions_between_periods():
    """Between decisions the C fleet's output changes only through the filter: with no
    neighbour in reach it is exactly the held velocity."""
    from firmware.ceval import COnboardFleet
    from firmware.cpolicy import CPolicy

    # the network decides (alone, the sparse rule would fly the same straight line each time)
    fleet = COnboardFleet(CPolicy.load(sparse_rule=False), decision_period_s=1.0)
    starts, goals = scenarios.antipodal_circle(2)
    pos, vel = np.asarray(starts, float) * 3.0, np.zeros((2, 2))  # far apart: no constraint
    goal = np.asarray(goals, float) * 3.0
    heading = np.arctan2(*(goal - pos).T[::-1])
    none = np.zeros((2, 0, 2)), np.zeros((2, 0, 2)), np.zeros((2, 0)), np.zeros((2, 0), bool)
    v0 = fleet(np.arange(2), 0.0, pos, vel, heading, goal, *none)
    moved = pos + 0.5 * v0
    v1 = fleet(np.arange(2), 0.5, moved, v0, heading + 0.3, goal, *none)
    np.testing.assert_array_equal(v0, v1)  # held: a new heading did not change it
    v2 = fleet(np.arange(2), 1.0, moved, v0, heading + 0.3, goal, *none)
    assert not np.allclose(v2, v1)  # decided again with the new heading
    fleet.reset()
    r = evalsim.run(
        starts, goals, fleet, evalsim.PERFECT, evalsim.EvalSimConfig(), np.random.default_rng(0)
    )
    assert r["success"] and r["collisions"] == 0
