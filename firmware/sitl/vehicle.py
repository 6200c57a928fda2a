"""Point-mass multicopter with PX4's modes and refusals: the pure core of the emulator.

Positions are NED metres relative to the home position (the ground is d = 0). Nothing here reads
the clock: every call takes `now_s`, and `step(now_s)` integrates up to it, so tests drive hours of
flight in milliseconds. Commands return a `Px4Result` whose `result` is a MAV_RESULT value, and
whose `reason` is the STATUSTEXT PX4 would print.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from firmware.sitl import px4
from firmware.sitl.params import VehicleParams
from firmware.sitl.px4 import OK, Px4Mode, Px4Result
from policy.pointmass import VehicleModel, gauss_markov, integrate

if TYPE_CHECKING:
    from firmware.sitl.onboard import OnboardGuidance

MAX_SUBSTEP_S = 0.02
"""Integration step; `step()` splits longer gaps so the controllers stay stable."""
TAKEOFF_ACCEPT_M = 0.25
"""TAKEOFF is done within this vertical distance of the takeoff altitude."""


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class Vehicle:
    """One emulated multicopter: state, PX4 mode machine and point-mass physics."""

    params: VehicleParams = field(default_factory=VehicleParams)
    healthy: bool = True
    """Pre-arm checks pass (False emulates a failed sensor: arming is refused)."""
    guidance: OnboardGuidance | None = None
    """When set, goto targets are flown by this (onboard mode); otherwise straight at cruise speed."""
    now_s: float = 0.0
    pos_ned_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    vel_ned_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    heading_rad: float = 0.0
    armed: bool = False
    mode: Px4Mode = Px4Mode.HOLD
    battery_pct: float = 100.0
    target_ned_m: np.ndarray | None = None
    """Position the position controller flies to (HOLD, goto, TAKEOFF, RTL)."""
    goto_active: bool = False
    """A DO_REPOSITION target is being flown (guidance applies)."""
    sp_vel_ned_m_s: np.ndarray | None = None
    sp_pos_ned_m: np.ndarray | None = None
    sp_yaw_rad: float | None = None
    sp_stamp_s: float = -math.inf
    """Receive time of the last offboard setpoint."""
    falling: bool = False
    """Motors off in the air (kill, termination): only gravity acts."""
    armed_at_s: float = 0.0
    landed_at_s: float = math.inf
    """When the vehicle last touched down (inf while flying)."""
    took_off: bool = False
    events: list[str] = field(default_factory=list)
    """STATUSTEXTs to send; the link layer drains it."""
    model: VehicleModel | None = None
    """How real the airframe is (policy.pointmass): velocity lag, gusts the loop does not
    reject, a drifting GNSS estimate (reported in the position messages, its 1-sigma as
    GPS_RAW_INT h_acc). None: exactly the setpoint within accel_m_s2, exact positions. Its
    acceleration limit is params.accel_m_s2 (MPC_ACC_HOR) either way."""
    rng: np.random.Generator | None = None
    """Draws the gusts and the drift (None with a model: fresh entropy)."""
    gust_m_s: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """The wind gust now (north, east), m/s."""
    drift_m: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """The GNSS estimate's error now (north, east), m."""

    def __post_init__(self) -> None:
        m = self.model
        if m is not None and (m.gust_m_s > 0 or m.drift_m > 0):
            if self.rng is None:
                self.rng = np.random.default_rng()
            # stationary from the start, as policy.pointmass.Vehicles
            self.gust_m_s = self.rng.standard_normal(2) * m.gust_m_s
            self.drift_m = self.rng.standard_normal(2) * m.drift_m

    # ---- state ---------------------------------------------------------------------------------

    @property
    def landed(self) -> bool:
        return self.pos_ned_m[2] >= -1e-3 and self.vel_ned_m_s[2] >= -1e-3

    @property
    def est_pos_ned_m(self) -> np.ndarray:
        """Where the autopilot believes it is (what it reports): the truth plus the drift."""
        est = self.pos_ned_m.copy()
        est[:2] += self.drift_m
        return est

    @property
    def ground_vel_ned_m_s(self) -> np.ndarray:
        """The velocity it reports: the loop's plus the gust while airborne (what GNSS sees)."""
        v = self.vel_ned_m_s.copy()
        if self.pos_ned_m[2] < 0.0:
            v[:2] += self.gust_m_s
        return v

    @property
    def pos_sigma_m(self) -> float:
        """The 1-sigma of the horizontal estimate it simulates (and reports)."""
        return 0.0 if self.model is None else self.model.pos_sigma_m

    @property
    def alt_m(self) -> float:
        return -float(self.pos_ned_m[2])

    def _say(self, text: str) -> None:
        self.events.append(text)

    def _refuse(self, result: int, reason: str) -> Px4Result:
        self._say(reason)
        return Px4Result(result, reason)

    def _switch_px4_mode(self, mode: Px4Mode, now_s: float) -> None:
        """PX4's own flight modes (the emulated autopilot's), not covey's mode machine."""
        self.mode = mode
        self.goto_active = False
        if mode in (
            Px4Mode.HOLD,
            Px4Mode.POSCTL,
            Px4Mode.ALTCTL,
            Px4Mode.MANUAL,
            Px4Mode.STABILIZED,
        ):
            # Brake and hold where we are; on the ground, stay on the ground.
            self.target_ned_m = self.pos_ned_m.copy()
        elif mode is Px4Mode.LAND:
            self.target_ned_m = None

    # ---- commands ------------------------------------------------------------------------------

    def arm(self, now_s: float) -> Px4Result:
        if self.armed:
            return OK
        if not self.healthy:
            return self._refuse(px4.TEMPORARILY_REJECTED, "Arming denied: preflight checks failed")
        if self.falling:
            return self._refuse(px4.TEMPORARILY_REJECTED, "Arming denied: vehicle is falling")
        if self.mode not in (
            Px4Mode.HOLD,
            Px4Mode.POSCTL,
            Px4Mode.TAKEOFF,
            Px4Mode.OFFBOARD,
            Px4Mode.MISSION,
            Px4Mode.LAND,
            Px4Mode.READY,
        ):
            return self._refuse(px4.TEMPORARILY_REJECTED, f"Arming denied: not in {self.mode.name}")
        self.armed, self.armed_at_s, self.took_off = True, now_s, False
        if self.mode is not Px4Mode.OFFBOARD:
            self._switch_px4_mode(Px4Mode.HOLD, now_s)  # hold on the ground until told to climb
        self._say("Armed by external command")
        return OK

    def disarm(self, now_s: float, force: bool = False) -> Px4Result:
        if not self.armed:
            return OK
        if not force and not self.landed:
            return self._refuse(px4.TEMPORARILY_REJECTED, "Disarming denied: not landed")
        if not self.landed:
            self.falling = True
            self._say("Kill switch engaged: motors off in the air")
        else:
            self._say("Disarmed by external command")
        self._disarmed()
        return OK

    def _disarmed(self) -> None:
        # Forget every target, so that re-arming never resumes a stale takeoff or goto.
        self.armed, self.goto_active, self.target_ned_m = False, False, None
        if self.mode is not Px4Mode.OFFBOARD:
            self.mode = Px4Mode.HOLD

    def kill(self, now_s: float) -> Px4Result:
        return self.disarm(now_s, force=True)

    def set_mode(self, mode: Px4Mode, now_s: float) -> Px4Result:
        if mode is self.mode:
            return OK
        if mode is Px4Mode.OFFBOARD and now_s - self.sp_stamp_s > self.params.offboard_loss_s:
            return self._refuse(
                px4.TEMPORARILY_REJECTED,
                "Switching to Offboard is currently not possible: no setpoints",
            )
        if mode in (Px4Mode.MISSION, Px4Mode.READY):
            return self._refuse(
                px4.TEMPORARILY_REJECTED, f"Switching to {mode.name} is not possible: no mission"
            )
        if mode is Px4Mode.TAKEOFF:
            return self.takeoff(math.nan, now_s)
        if mode is Px4Mode.RTL and self.landed:
            return self._refuse(px4.TEMPORARILY_REJECTED, "RTL denied: landed")
        self._switch_px4_mode(mode, now_s)
        if mode is Px4Mode.RTL:
            alt_m = max(self.alt_m, self.params.rtl_alt_m)
            self.target_ned_m = np.array([self.pos_ned_m[0], self.pos_ned_m[1], -alt_m])
        return OK

    def takeoff(self, alt_m: float, now_s: float) -> Px4Result:
        if math.isnan(alt_m):
            alt_m = self.params.takeoff_alt_m
        if not math.isfinite(alt_m) or not 0.5 <= alt_m <= self.params.max_alt_m:
            return self._refuse(
                px4.DENIED,
                f"Takeoff denied: altitude {alt_m} m outside [0.5, {self.params.max_alt_m}]",
            )
        if not self.armed:
            return self._refuse(px4.TEMPORARILY_REJECTED, "Takeoff denied: disarmed")
        if not self.landed:
            return self._refuse(px4.TEMPORARILY_REJECTED, "Takeoff denied: already flying")
        self._switch_px4_mode(Px4Mode.TAKEOFF, now_s)
        self.target_ned_m = np.array([self.pos_ned_m[0], self.pos_ned_m[1], -alt_m])
        self.took_off = True
        return OK

    def land(self, now_s: float) -> Px4Result:
        # PX4 takes LAND as a mode switch, disarmed or not; on the ground it just stays there.
        self._switch_px4_mode(Px4Mode.LAND, now_s)
        return OK

    def reposition(self, target_ned_m: np.ndarray, now_s: float) -> Px4Result:
        """DO_REPOSITION: fly to the target and hold there. NaN down keeps the altitude."""
        target = np.asarray(target_ned_m, dtype=float).copy()
        if not np.all(np.isfinite(target[:2])):
            return self._refuse(px4.DENIED, "Reposition denied: position is not finite")
        if math.isnan(target[2]):
            target[2] = self.pos_ned_m[2]
        if not math.isfinite(target[2]) or not 0.5 <= -target[2] <= self.params.max_alt_m:
            return self._refuse(
                px4.DENIED,
                f"Reposition denied: altitude {-target[2]:.1f} m outside [0.5, {self.params.max_alt_m}]",
            )
        if not self.armed or self.landed:
            return self._refuse(px4.TEMPORARILY_REJECTED, "Reposition denied: not flying")
        self._switch_px4_mode(Px4Mode.HOLD, now_s)
        self.target_ned_m, self.goto_active = target, True
        return OK

    def offboard_setpoint(
        self,
        now_s: float,
        vel_ned_m_s: np.ndarray | None = None,
        pos_ned_m: np.ndarray | None = None,
        yaw_rad: float | None = None,
    ) -> bool:
        """Store a SET_POSITION_TARGET_LOCAL_NED setpoint; False (ignored) if not finite."""
        for v in (vel_ned_m_s, pos_ned_m):
            if v is not None and not np.all(np.isfinite(v)):
                return False
        if vel_ned_m_s is None and pos_ned_m is None:
            return False
        if yaw_rad is not None and not math.isfinite(yaw_rad):
            yaw_rad = None
        self.sp_vel_ned_m_s = None if vel_ned_m_s is None else np.asarray(vel_ned_m_s, float).copy()
        self.sp_pos_ned_m = None if pos_ned_m is None else np.asarray(pos_ned_m, float).copy()
        self.sp_yaw_rad, self.sp_stamp_s = yaw_rad, now_s
        return True

    # ---- physics -------------------------------------------------------------------------------

    def step(self, now_s: float) -> None:
        """Integrate from the last call up to `now_s`."""
        gap_s = now_s - self.now_s
        if gap_s <= 0.0:
            return
        n = math.ceil(gap_s / MAX_SUBSTEP_S - 1e-9)
        start_s = self.now_s
        for k in range(1, n + 1):
            self.now_s = start_s + gap_s * k / n
            self._substep(gap_s / n)
        self.now_s = now_s

    def _substep(self, dt: float) -> None:
        p, now = self.params, self.now_s
        if self.falling or not self.armed:
            self._fall(dt)
            return
        self.battery_pct = max(0.0, self.battery_pct - p.battery_drain_pct_s * dt)
        self._failsafes(now)
        vel_cmd, yaw_cmd = self._control(now)
        if self.landed and vel_cmd[2] >= 0.0:
            # On the ground and not asked to climb: stay put (PX4's land detector holds it).
            self.vel_ned_m_s[:] = 0.0
            self._ground_checks(now)
            return
        self.landed_at_s, self.took_off = math.inf, True
        m = self.model
        hit = integrate(
            self.pos_ned_m[None],
            self.vel_ned_m_s[None],
            vel_cmd[None],
            dt,
            p.accel_m_s2,
            lag_s=0.0 if m is None else m.lag_s,
            wind_m_s=None if m is None or m.gust_m_s == 0 else self.gust_m_s[None],
        )
        if m is not None:
            gauss_markov(self.gust_m_s, m.gust_m_s, m.gust_corr_s, dt, self.rng)
            gauss_markov(self.drift_m, m.drift_m, m.drift_corr_s, dt, self.rng)
        if hit[0]:
            self.landed_at_s = now
            self._say("Landing detected")
        if yaw_cmd is not None:
            err = _wrap_pi(yaw_cmd - self.heading_rad)
            step = max(-p.yaw_rate_rad_s * dt, min(p.yaw_rate_rad_s * dt, err))
            self.heading_rad = _wrap_pi(self.heading_rad + step)

    def _fall(self, dt: float) -> None:
        unpowered = np.zeros(1, bool)  # motors off: gravity and drag only
        integrate(
            self.pos_ned_m[None], self.vel_ned_m_s[None], np.zeros((1, 3)), dt, powered=unpowered
        )
        if self.pos_ned_m[2] >= 0.0:
            self.pos_ned_m[2] = 0.0
            self.vel_ned_m_s[:] = 0.0
            if self.falling:
                self._say("Vehicle hit the ground")
            self.falling = False

    def _ground_checks(self, now: float) -> None:
        p = self.params
        if self.landed_at_s == math.inf:
            self.landed_at_s = now
        if self.took_off and now - self.landed_at_s >= p.disarm_after_land_s:
            self._disarmed()
            self._say("Disarmed by landing")
        elif not self.took_off and now - self.armed_at_s >= p.disarm_preflight_s:
            self._disarmed()
            self._say("Disarmed by auto preflight disarming")

    def _failsafes(self, now: float) -> None:
        if self.mode is Px4Mode.OFFBOARD and now - self.sp_stamp_s > self.params.offboard_loss_s:
            self._say("Failsafe: no offboard setpoints, holding")
            self._switch_px4_mode(Px4Mode.HOLD, now)
        if (
            self.mode is Px4Mode.TAKEOFF
            and self.target_ned_m is not None
            and abs(self.pos_ned_m[2] - self.target_ned_m[2]) < TAKEOFF_ACCEPT_M
        ):
            # PX4 switches to HOLD at the takeoff altitude.
            alt_d_m = self.target_ned_m[2]
            self._say("Takeoff complete")
            self._switch_px4_mode(Px4Mode.HOLD, now)
            assert self.target_ned_m is not None
            self.target_ned_m[2] = alt_d_m
        if (
            self.mode is Px4Mode.RTL
            and self.target_ned_m is not None
            and float(np.linalg.norm(self.pos_ned_m[:2])) < self.params.arrive_radius_m
        ):
            self._switch_px4_mode(Px4Mode.LAND, now)

    def _control(self, now: float) -> tuple[np.ndarray, float | None]:
        """Velocity command (NED) and yaw command for the current mode."""
        p = self.params
        if self.mode is Px4Mode.LAND:
            return np.array([-self.vel_ned_m_s[0], -self.vel_ned_m_s[1], p.land_speed_m_s]), None
        if self.mode is Px4Mode.OFFBOARD:
            return self._offboard_control()
        if self.mode is Px4Mode.RTL and self.target_ned_m is not None:
            climbing = self.pos_ned_m[2] - self.target_ned_m[2] > 0.5
            goal = self.target_ned_m if climbing else np.array([0.0, 0.0, self.target_ned_m[2]])
            return self._fly_to(goal, p.climb_speed_m_s)
        if self.target_ned_m is None:
            return np.zeros(3), None
        if self.mode is Px4Mode.TAKEOFF:
            return self._fly_to(self.target_ned_m, p.takeoff_speed_m_s)
        if self.goto_active and self.guidance is not None:
            return self._guided(now)
        return self._fly_to(self.target_ned_m, p.climb_speed_m_s)

    def _fly_to(self, goal: np.ndarray, climb_m_s: float) -> tuple[np.ndarray, float | None]:
        p = self.params
        err = goal - self.pos_ned_m
        v_ne = _clip_norm(p.pos_gain_1_s * err[:2], p.cruise_speed_m_s)
        v_d = max(-climb_m_s, min(p.descent_speed_m_s, p.pos_gain_1_s * err[2]))
        yaw = math.atan2(err[1], err[0]) if float(np.linalg.norm(err[:2])) > 2.0 else None
        return np.array([v_ne[0], v_ne[1], v_d]), yaw

    def _guided(self, now: float) -> tuple[np.ndarray, float | None]:
        """Onboard mode: the guidance flies the horizontal leg, a P loop holds the altitude."""
        p, goal = self.params, self.target_ned_m
        assert goal is not None and self.guidance is not None
        dist_m = float(np.linalg.norm(goal[:2] - self.pos_ned_m[:2]))
        if dist_m < p.arrive_radius_m:
            self._say("Reposition: target reached")
            self.goto_active = False
            return self._fly_to(goal, p.climb_speed_m_s)
        v_ne = np.asarray(
            self.guidance.velocity_ne_m_s(
                self.pos_ned_m.copy(), self.vel_ned_m_s.copy(), self.heading_rad, goal.copy(), now
            ),
            float,
        )
        if v_ne.shape != (2,) or not np.all(np.isfinite(v_ne)):
            self._say("Guidance fault: holding")
            self._switch_px4_mode(Px4Mode.HOLD, now)
            return np.zeros(3), None
        v_ne = _clip_norm(v_ne, p.max_speed_m_s)
        v_d = max(
            -p.climb_speed_m_s,
            min(p.descent_speed_m_s, p.pos_gain_1_s * (goal[2] - self.pos_ned_m[2])),
        )
        # The policy's heading is the direction of motion (as in the paper).
        yaw = math.atan2(v_ne[1], v_ne[0]) if float(np.linalg.norm(v_ne)) > 0.2 else None
        return np.array([v_ne[0], v_ne[1], v_d]), yaw

    def _offboard_control(self) -> tuple[np.ndarray, float | None]:
        p = self.params
        if self.sp_pos_ned_m is not None:
            vel, _ = self._fly_to(self.sp_pos_ned_m, p.climb_speed_m_s)
            if self.sp_vel_ned_m_s is not None:
                vel = vel + self.sp_vel_ned_m_s
        elif self.sp_vel_ned_m_s is not None:
            vel = self.sp_vel_ned_m_s.copy()
        else:
            vel = np.zeros(3)
        vel[:2] = _clip_norm(vel[:2], p.max_speed_m_s)
        vel[2] = max(-p.climb_speed_m_s, min(p.descent_speed_m_s, vel[2]))
        return vel, self.sp_yaw_rad
