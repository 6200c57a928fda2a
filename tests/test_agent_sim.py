"""The built-in simulator, driven with injected time."""

from __future__ import annotations

import numpy as np
import pytest

from agent.backends.base import BackendError, Capability
from agent.backends.sim import SimBackend, SimConfig, SimFleet


def run(sim: SimBackend, t0: float, seconds: float, dt: float = 0.05) -> float:
    t = t0
    for _ in range(int(seconds / dt)):
        t += dt
        sim.step(t)
    return t


def test_takeoff_climbs_to_altitude_and_holds() -> None:
    sim = SimBackend(SimConfig(start_ned_m=(3.0, 4.0, 0.0)))
    sim.takeoff(10.0)
    t = run(sim, 0.0, 10.0)
    tel = sim.telemetry()
    assert tel.armed and tel.in_air
    assert -tel.pos_ned_m[2] == pytest.approx(10.0, abs=0.2)
    assert tel.pos_ned_m[:2] == pytest.approx((3.0, 4.0), abs=0.05)
    run(sim, t, 5.0)
    assert -sim.telemetry().pos_ned_m[2] == pytest.approx(10.0, abs=0.2)


def test_velocity_setpoint_is_tracked_with_limited_acceleration() -> None:
    sim = SimBackend()
    sim.takeoff(5.0)
    t = run(sim, 0.0, 5.0)
    speeds = []
    for _ in range(40):
        sim.set_velocity_ned((2.0, 0.0, 0.0), 0.0)
        t = run(sim, t, 0.05, 0.05)
        speeds.append(sim.telemetry().vel_ned_m_s[0])
    assert speeds[0] <= 4.0 * 0.05 + 1e-9  # acceleration limit
    assert speeds[-1] == pytest.approx(2.0, abs=1e-6)
    assert sim.telemetry().heading_rad == pytest.approx(0.0)


def test_setpoint_timeout_makes_it_hold() -> None:
    sim = SimBackend()
    sim.takeoff(5.0)
    t = run(sim, 0.0, 5.0)
    sim.set_velocity_ned((1.0, 1.0, 0.0), 0.7)
    t = run(sim, t, 3.0)  # no new setpoints: it must stop
    assert np.hypot(*sim.telemetry().vel_ned_m_s[:2]) < 0.1


def test_kill_makes_it_fall_and_disarm() -> None:
    sim = SimBackend()
    sim.takeoff(10.0)
    t = run(sim, 0.0, 8.0)
    sim.kill()
    assert not sim.telemetry().armed
    t = run(sim, t, 1.0)
    assert sim.telemetry().in_air  # 10 m of free fall takes 1.43 s
    run(sim, t, 0.6)
    tel = sim.telemetry()
    assert not tel.in_air
    with pytest.raises(BackendError, match="disarmed"):
        sim.set_velocity_ned((1.0, 0.0, 0.0), 0.0)


def test_land_touches_down_and_disarms() -> None:
    sim = SimBackend()
    sim.takeoff(4.0)
    t = run(sim, 0.0, 4.0)
    sim.land()
    run(sim, t, 10.0)
    tel = sim.telemetry()
    assert not tel.in_air and not tel.armed


def test_battery_drains_only_in_the_air() -> None:
    sim = SimBackend()
    run(sim, 0.0, 10.0)
    assert sim.telemetry().battery_pct == 100.0
    sim.takeoff(5.0)
    run(sim, 10.0, 60.0)
    assert sim.telemetry().battery_pct < 96.0


def test_bad_setpoints_are_refused() -> None:
    sim = SimBackend()
    sim.takeoff(5.0)
    with pytest.raises(BackendError, match="finite"):
        sim.set_velocity_ned((float("nan"), 0.0, 0.0), 0.0)
    with pytest.raises(BackendError):
        sim.takeoff(-1.0)
    assert Capability.VELOCITY_SETPOINT in sim.capabilities


def _arrays(fleet: SimFleet) -> dict[str, np.ndarray]:
    return {k: v.copy() for k, v in vars(fleet).items() if isinstance(v, np.ndarray)}


def test_a_fleet_at_rest_is_a_fixed_point_so_a_step_may_skip_it() -> None:
    """The fast path (`step` skips `_integrate` while `at_rest`) equals the reference path."""
    rng = np.random.default_rng(7)
    for _ in range(50):
        n = int(rng.integers(1, 6))
        starts = np.column_stack([rng.uniform(-50, 50, (n, 2)), np.zeros(n)])
        fleet = SimFleet(SimConfig(), starts, now_s=0.0)
        fleet.heading_rad[:] = rng.uniform(-3, 3, n)
        fleet.battery_pct[:] = rng.uniform(10, 100, n)
        fleet.hold_m[:] = rng.uniform(-5, 5, (n, 3))
        fleet.sp_vel_m_s[:] = rng.uniform(-1, 1, (n, 3))
        assert fleet.at_rest()
        before = _arrays(fleet)
        fleet._integrate(float(rng.uniform(0.01, 0.5)))  # the reference path
        after = _arrays(fleet)
        for name, value in before.items():
            np.testing.assert_array_equal(after[name], value, err_msg=name)


def test_anything_that_moves_or_may_move_is_not_at_rest() -> None:
    fleet = SimFleet(SimConfig(), np.zeros((3, 3)), now_s=0.0)
    assert fleet.at_rest()
    fleet.takeoff(1, 5.0)
    assert not fleet.at_rest()
    fleet.step(0.1)
    assert fleet.pos_m[1, 2] < 0.0  # the step integrated: it climbs
    for poke in (
        lambda f: f.armed.__setitem__(0, True),
        lambda f: f.vel_m_s.__setitem__((2, 0), 0.1),
        lambda f: f.pos_m.__setitem__((0, 2), -3.0),  # up in the air, motors off: falls
    ):
        rest = SimFleet(SimConfig(), np.zeros((3, 3)), now_s=0.0)
        poke(rest)
        assert not rest.at_rest()
