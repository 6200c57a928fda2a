"""The emulator's pure core: point-mass physics and PX4's mode machine, on injected time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware.sitl import px4
from firmware.sitl.px4 import Px4Mode
from firmware.sitl.vehicle import Vehicle, VehicleParams

FAST = VehicleParams(
    takeoff_speed_m_s=3.0,
    land_speed_m_s=2.0,
    accel_m_s2=8.0,
    pos_gain_1_s=2.0,
    disarm_after_land_s=1.0,
    disarm_preflight_s=5.0,
)


def run(v: Vehicle, until_s: float, dt_s: float = 0.05, stop=lambda v: False) -> float:
    """Step the vehicle to `until_s`; returns the time `stop` became true (or until_s)."""
    t = v.now_s
    while t < until_s:
        t = min(until_s, t + dt_s)
        v.step(t)
        if stop(v):
            return t
    return t


def flying(alt_m: float = 5.0, **kw) -> Vehicle:
    v = Vehicle(params=FAST, **kw)
    assert v.arm(0.0).ok
    assert v.takeoff(alt_m, 0.0).ok
    run(v, 20.0, stop=lambda v: v.mode is Px4Mode.HOLD)
    assert v.mode is Px4Mode.HOLD
    return v


def test_custom_mode_is_main_shl_16_or_sub_shl_24() -> None:
    assert Px4Mode.HOLD.custom_mode == (4 << 16) | (3 << 24)
    assert Px4Mode.OFFBOARD.custom_mode == 6 << 16
    for mode in Px4Mode:
        assert Px4Mode.from_custom_mode(mode.custom_mode) is mode
    assert Px4Mode.from_main_sub(9, 9) is None


def test_takeoff_climbs_to_the_altitude_then_holds() -> None:
    v = Vehicle(params=FAST)
    assert v.landed and not v.armed
    assert v.arm(0.0).ok and v.takeoff(6.0, 0.0).ok
    assert v.mode is Px4Mode.TAKEOFF
    run(v, 1.0)
    assert 0.5 < v.alt_m < 6.0 and not v.landed
    run(v, 20.0, stop=lambda v: v.mode is Px4Mode.HOLD)
    assert v.mode is Px4Mode.HOLD and abs(v.alt_m - 6.0) < 0.3
    run(v, v.now_s + 3.0)
    assert abs(v.alt_m - 6.0) < 0.05 and np.linalg.norm(v.vel_ned_m_s) < 0.05
    assert np.allclose(v.pos_ned_m[:2], 0.0)


def test_takeoff_without_altitude_uses_mis_takeoff_alt() -> None:
    v = Vehicle(params=VehicleParams(takeoff_alt_m=3.5, pos_gain_1_s=2.0))
    v.arm(0.0)
    assert v.takeoff(math.nan, 0.0).ok
    run(v, 30.0, stop=lambda v: v.mode is Px4Mode.HOLD)
    assert abs(v.alt_m - 3.5) < 0.3


@pytest.mark.parametrize(
    ("setup", "command", "result"),
    [
        ("ground", lambda v: v.takeoff(5.0, 0.0), px4.TEMPORARILY_REJECTED),  # disarmed
        ("armed", lambda v: v.takeoff(math.inf, 0.0), px4.DENIED),
        ("armed", lambda v: v.takeoff(-2.0, 0.0), px4.DENIED),
        ("armed", lambda v: v.takeoff(500.0, 0.0), px4.DENIED),
        (
            "armed",
            lambda v: v.reposition(np.array([5.0, 0.0, -5.0]), 0.0),
            px4.TEMPORARILY_REJECTED,
        ),
        (
            "ground",
            lambda v: v.set_mode(Px4Mode.OFFBOARD, 0.0),
            px4.TEMPORARILY_REJECTED,
        ),  # no setpoints
        ("ground", lambda v: v.set_mode(Px4Mode.MISSION, 0.0), px4.TEMPORARILY_REJECTED),
        ("ground", lambda v: v.set_mode(Px4Mode.RTL, 0.0), px4.TEMPORARILY_REJECTED),
        ("ground", lambda v: v.land(0.0), px4.ACCEPTED),  # a mode switch; it stays on the ground
        ("unhealthy", lambda v: v.arm(0.0), px4.TEMPORARILY_REJECTED),
        ("ground", lambda v: v.arm(0.0), px4.ACCEPTED),
        ("armed", lambda v: v.disarm(0.0), px4.ACCEPTED),
        ("ground", lambda v: v.disarm(0.0), px4.ACCEPTED),  # already disarmed: PX4 acks
    ],
)
def test_command_table_on_the_ground(setup, command, result) -> None:
    v = Vehicle(params=FAST, healthy=setup != "unhealthy")
    if setup == "armed":
        v.arm(0.0)
    outcome = command(v)
    assert outcome.result == result, outcome.reason
    assert bool(outcome.reason) == (result != px4.ACCEPTED)
    if result != px4.ACCEPTED:
        assert outcome.reason in v.events  # refusals are explained in a STATUSTEXT


@pytest.mark.parametrize(
    ("command", "result"),
    [
        (
            lambda v: v.disarm(v.now_s),
            px4.TEMPORARILY_REJECTED,
        ),  # PX4: "Disarming denied: not landed"
        (lambda v: v.takeoff(5.0, v.now_s), px4.TEMPORARILY_REJECTED),  # already flying
        (lambda v: v.reposition(np.array([math.nan, 0.0, -5.0]), v.now_s), px4.DENIED),
        (lambda v: v.reposition(np.array([0.0, math.inf, -5.0]), v.now_s), px4.DENIED),
        (lambda v: v.reposition(np.array([0.0, 0.0, -1000.0]), v.now_s), px4.DENIED),
        (lambda v: v.reposition(np.array([0.0, 0.0, 3.0]), v.now_s), px4.DENIED),  # below ground
        (lambda v: v.reposition(np.array([10.0, 0.0, math.nan]), v.now_s), px4.ACCEPTED),
        (lambda v: v.set_mode(Px4Mode.RTL, v.now_s), px4.ACCEPTED),
    ],
)
def test_command_table_in_the_air(command, result) -> None:
    v = flying()
    assert command(v).result == result
    assert v.armed


def test_refused_disarm_keeps_flying_and_kill_drops() -> None:
    v = flying(alt_m=8.0)
    assert not v.disarm(v.now_s).ok
    run(v, v.now_s + 1.0)
    assert v.armed and abs(v.alt_m - 8.0) < 0.3
    assert v.kill(v.now_s).ok
    assert not v.armed and v.falling
    t0 = v.now_s
    t_hit = run(v, t0 + 5.0, dt_s=0.01, stop=lambda v: v.landed)
    # Free fall from 8 m: t = sqrt(2h/g) = 1.28 s.
    assert t_hit - t0 == pytest.approx(math.sqrt(2 * 8.0 / 9.80665), abs=0.05)
    assert not v.falling and v.landed and not v.armed
    assert v.arm(v.now_s).ok  # PX4 lets a healthy vehicle re-arm after a crash


def test_offboard_needs_a_fresh_setpoint_and_flies_it() -> None:
    v = flying()
    t = v.now_s
    assert v.set_mode(Px4Mode.OFFBOARD, t).result == px4.TEMPORARILY_REJECTED
    assert v.offboard_setpoint(t, vel_ned_m_s=np.array([2.0, -1.0, 0.0]), yaw_rad=math.pi / 2)
    assert v.set_mode(Px4Mode.OFFBOARD, t).ok
    start = v.pos_ned_m.copy()
    for _ in range(40):  # 2 s of setpoints at 20 Hz
        t += 0.05
        v.offboard_setpoint(t, vel_ned_m_s=np.array([2.0, -1.0, 0.0]), yaw_rad=math.pi / 2)
        v.step(t)
    moved = v.pos_ned_m - start
    assert moved[0] > 2.5 and moved[1] < -1.2 and abs(moved[2]) < 0.1
    assert np.allclose(v.vel_ned_m_s, [2.0, -1.0, 0.0], atol=1e-6)
    assert v.heading_rad == pytest.approx(math.pi / 2, abs=1e-6)
    # Setpoints stop: after COM_OF_LOSS_T PX4 fails over to HOLD and brakes.
    run(v, t + FAST.offboard_loss_s + 3.0)
    assert v.mode is Px4Mode.HOLD
    assert np.linalg.norm(v.vel_ned_m_s) < 0.1
    assert "Failsafe: no offboard setpoints, holding" in v.events


def test_offboard_rejects_non_finite_setpoints() -> None:
    v = flying()
    assert not v.offboard_setpoint(v.now_s, vel_ned_m_s=np.array([math.nan, 0.0, 0.0]))
    assert not v.offboard_setpoint(v.now_s)
    assert v.set_mode(Px4Mode.OFFBOARD, v.now_s).result == px4.TEMPORARILY_REJECTED


def test_reposition_flies_there_and_holds() -> None:
    v = flying(alt_m=5.0)
    assert v.reposition(np.array([20.0, -10.0, -8.0]), v.now_s).ok
    assert v.mode is Px4Mode.HOLD and v.goto_active
    run(v, v.now_s + 30.0)
    assert np.allclose(v.pos_ned_m, [20.0, -10.0, -8.0], atol=0.05)
    assert np.linalg.norm(v.vel_ned_m_s) < 0.05
    # NaN altitude keeps the current one.
    assert v.reposition(np.array([0.0, 0.0, math.nan]), v.now_s).ok
    run(v, v.now_s + 30.0)
    assert np.allclose(v.pos_ned_m, [0.0, 0.0, -8.0], atol=0.05)


def test_hold_brakes_where_it_is() -> None:
    v = flying()
    v.reposition(np.array([50.0, 0.0, -5.0]), v.now_s)
    run(v, v.now_s + 2.0)
    assert v.vel_ned_m_s[0] > 2.0
    assert v.set_mode(Px4Mode.POSCTL, v.now_s).ok and v.set_mode(Px4Mode.HOLD, v.now_s).ok
    here = v.pos_ned_m.copy()
    run(v, v.now_s + 10.0)
    assert np.linalg.norm(v.pos_ned_m - here) < 3.0  # braking distance v^2 / 2a, then back
    assert np.linalg.norm(v.vel_ned_m_s) < 0.05 and v.pos_ned_m[0] < 45.0


def test_land_touches_down_and_disarms_after_com_disarm_land() -> None:
    v = flying(alt_m=4.0)
    assert v.land(v.now_s).ok
    touch = run(v, v.now_s + 10.0, dt_s=0.01, stop=lambda v: v.landed)
    assert v.landed and v.armed and v.mode is Px4Mode.LAND
    disarm = run(v, touch + 5.0, dt_s=0.01, stop=lambda v: not v.armed)
    assert disarm - touch == pytest.approx(FAST.disarm_after_land_s, abs=0.05)


def test_armed_on_the_ground_disarms_by_itself() -> None:
    v = Vehicle(params=FAST)
    v.arm(0.0)
    run(v, FAST.disarm_preflight_s - 0.1)
    assert v.armed
    run(v, FAST.disarm_preflight_s + 0.1)
    assert not v.armed


def test_rtl_climbs_returns_and_lands() -> None:
    v = flying(alt_m=5.0)
    v.reposition(np.array([30.0, 10.0, -5.0]), v.now_s)
    run(v, v.now_s + 20.0)
    assert v.set_mode(Px4Mode.RTL, v.now_s).ok
    peak = [0.0]
    run(
        v,
        v.now_s + 120.0,
        stop=lambda v: (peak.__setitem__(0, max(peak[0], v.alt_m)), not v.armed)[1],
    )
    assert peak[0] > FAST.rtl_alt_m - 0.5
    assert np.linalg.norm(v.pos_ned_m[:2]) < FAST.arrive_radius_m + 0.2 and v.landed and not v.armed


def test_one_big_step_equals_many_small_ones() -> None:
    a, b = flying(), flying()
    for v in (a, b):
        v.reposition(np.array([15.0, 5.0, -7.0]), v.now_s)
    t0 = a.now_s
    a.step(t0 + 4.0)
    for k in range(1, 201):
        b.step(t0 + k * 0.02)
    assert np.allclose(a.pos_ned_m, b.pos_ned_m, atol=1e-9) and np.allclose(
        a.vel_ned_m_s, b.vel_ned_m_s, atol=1e-9
    )


class Steer:
    """A stand-in onboard guidance: fly east at 2 m/s whatever the goal (or fail on demand)."""

    def __init__(self, result=(0.0, 2.0)) -> None:
        self.result, self.calls = result, 0

    def velocity_ne_m_s(self, pos_ned_m, vel_ned_m_s, heading_rad, goal_ned_m, now_s):
        self.calls += 1
        return self.result


def test_goto_with_onboard_guidance_follows_the_guidance_and_holds_altitude() -> None:
    steer = Steer()
    v = flying(alt_m=5.0, guidance=steer)
    v.reposition(np.array([0.0, 30.0, -9.0]), v.now_s)
    run(v, v.now_s + 30.0, stop=lambda v: not v.goto_active)
    assert steer.calls > 0 and not v.goto_active
    assert np.linalg.norm(v.pos_ned_m[:2] - [0.0, 30.0]) < FAST.arrive_radius_m + 0.2
    assert abs(v.alt_m - 9.0) < 0.5
    assert v.heading_rad == pytest.approx(math.pi / 2, abs=0.01)  # heading = direction of motion


def test_guidance_fault_holds() -> None:
    v = flying(guidance=Steer((math.nan, 0.0)))
    v.reposition(np.array([0.0, 30.0, -5.0]), v.now_s)
    run(v, v.now_s + 1.0)
    assert v.mode is Px4Mode.HOLD and not v.goto_active
    assert "Guidance fault: holding" in v.events


def test_battery_drains_only_while_armed() -> None:
    v = Vehicle(params=FAST)
    run(v, 100.0)
    assert v.battery_pct == 100.0
    v = flying()
    assert v.battery_pct < 100.0


def test_rearming_after_a_kill_or_a_landing_does_not_resume_old_targets() -> None:
    v = flying(alt_m=6.0)
    v.reposition(np.array([20.0, 0.0, -6.0]), v.now_s)
    run(v, v.now_s + 1.0)
    v.kill(v.now_s)
    run(v, v.now_s + 5.0)
    assert v.landed and v.mode is Px4Mode.HOLD and v.target_ned_m is None
    assert v.arm(v.now_s).ok
    here = v.pos_ned_m.copy()
    run(v, v.now_s + 3.0)
    assert v.landed and np.allclose(v.pos_ned_m, here)  # armed, but nobody asked it to fly


def test_landing_from_offboard_disarms_like_any_landing() -> None:
    v = flying()
    t = v.now_s
    v.offboard_setpoint(t, vel_ned_m_s=np.array([0.0, 0.0, 1.5]))
    assert v.set_mode(Px4Mode.OFFBOARD, t).ok
    t_end = t + 30.0
    while v.armed and t < t_end:
        t += 0.05
        v.offboard_setpoint(t, vel_ned_m_s=np.array([0.0, 0.0, 1.5]))
        v.step(t)
    assert v.landed and not v.armed and "Disarmed by landing" in v.events
