"""The simulator's one-row fast path (agent/backends/sim_one.py `integrate_one`, an agent's vehicle) equals the
array path (`SimFleet._integrate`) step for step, on random command sequences: take-off, land,
hold, velocity setpoints (some too fast, some left to lapse), kills, long and zero steps, with
the ideal model and the realistic one (lag, gusts, GNSS drift)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.backends.base import BackendError
from agent.backends.sim import SimConfig, SimFleet
from policy.pointmass import VehicleModel

_FIELDS = (
    "true_pos_m",
    "pos_m",
    "vel_m_s",
    "heading_rad",
    "armed",
    "battery_pct",
    "mode",
    "target_alt_m",
    "hold_m",
    "sp_vel_m_s",
    "sp_heading_rad",
    "sp_stamp_s",
)


def _reference_step(fleet: SimFleet, now_s: float) -> None:
    """`SimFleet.step` through the array path whatever the fleet's size."""
    dt_s = now_s - fleet.now_s
    fleet.now_s = now_s
    if dt_s > 0 and not fleet.at_rest():
        fleet._integrate(min(dt_s, fleet.cfg.max_step_s))


def _command(fleet: SimFleet, row: int, rng: np.random.Generator) -> str | None:
    """One random command to `row` (or none); the error a refused one raised, if any."""
    r = rng.random()
    try:
        if r < 0.04:
            fleet.takeoff(row, float(rng.uniform(1.0, 15.0)))
        elif r < 0.07:
            fleet.land(row)
        elif r < 0.09:
            fleet.hold(row)
        elif r < 0.10:
            fleet.kill(row)
        elif r < 0.55:  # some faster than max_speed_m_s (scaled down)
            v = rng.normal(0.0, 5.0, 3)
            fleet.set_velocity(row, v.tolist(), float(rng.uniform(-4.0, 4.0)))
        # else: nothing (a velocity setpoint lapses after setpoint_timeout_s)
    except BackendError as exc:
        return str(exc)
    return None


def _dt(rng: np.random.Generator) -> float:
    r = rng.random()
    if r < 0.05:
        return 0.0
    if r < 0.08:
        return float(rng.uniform(0.5, 2.0))  # longer than max_step_s
    return float(rng.uniform(0.02, 0.3))


def _assert_rows_equal(a: SimFleet, ra: int, b: SimFleet, rb: int) -> None:
    for name in _FIELDS:
        x, y = getattr(a, name)[ra], getattr(b, name)[rb]
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12, err_msg=name)
    np.testing.assert_allclose(a.body.gust_m_s[ra], b.body.gust_m_s[rb], rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.body.drift_m[ra], b.body.drift_m[rb], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("model", [None, VehicleModel.realistic()], ids=["ideal", "realistic"])
def test_one_row_equals_the_array_path(seed: int, model: VehicleModel | None) -> None:
    """Same seed, same commands: the fast path's fleet of one and the array path's agree."""
    cfg = SimConfig(start_ned_m=(3.0, -2.0, 0.0), start_heading_rad=0.4, vehicle=model)
    fast = SimFleet(cfg, rng=np.random.default_rng(seed))
    ref = SimFleet(cfg, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(1000 + seed)
    t = 0.0
    modes = set()
    for _ in range(600):
        state = rng.bit_generator.state
        got = _command(fast, 0, rng)
        rng.bit_generator.state = state  # the same command to both
        assert _command(ref, 0, rng) == got
        t += _dt(rng)
        fast.step(t)
        _reference_step(ref, t)
        _assert_rows_equal(fast, 0, ref, 0)
        modes.add(int(fast.mode[0]))
    assert len(modes) == 6  # every SimMode was flown through


@pytest.mark.parametrize("seed", range(4))
def test_one_row_equals_its_row_in_a_fleet(seed: int) -> None:
    """An agent's vehicle flies as the same row of a multi-row fleet does (ideal model: no
    random draws, so the other rows do not change what it sees)."""
    starts = np.array([[0.0, 0.0, 0.0], [5.0, 1.0, 0.0], [-3.0, 7.0, -0.0]])
    fleet = SimFleet(SimConfig(), starts_ned_m=starts)
    ones = [SimFleet(SimConfig(start_ned_m=tuple(s))) for s in starts.tolist()]
    rng = np.random.default_rng(seed)
    t = 0.0
    for _ in range(300):
        for row, one in enumerate(ones):
            state = rng.bit_generator.state
            got = _command(fleet, row, rng)
            rng.bit_generator.state = state
            assert _command(one, 0, rng) == got
        t += _dt(rng)
        fleet.step(t)
        for row, one in enumerate(ones):
            one.step(t)
            _assert_rows_equal(one, 0, fleet, row)


def test_a_fleet_of_one_at_rest_is_left_alone() -> None:
    """Landed and disarmed: the fast path skips the step as `at_rest` does (no battery, no
    random draws)."""
    fleet = SimFleet(SimConfig(vehicle=VehicleModel.realistic()), rng=np.random.default_rng(3))
    assert fleet.at_rest()
    gust = fleet.body.gust_m_s.copy()
    fleet.step(5.0)
    assert fleet.now_s == 5.0 and fleet.at_rest()
    np.testing.assert_array_equal(fleet.body.gust_m_s, gust)
    assert math.isclose(float(fleet.battery_pct[0]), 100.0)
