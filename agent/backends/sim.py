"""The built-in simulator: a point-mass multirotor behind the same interface as a real vehicle.

Velocity tracking with an acceleration limit, vertical take-off and landing at fixed rates, a
battery that drains with flight time, and kill that cuts the motors so the vehicle falls. The
simulator integrates only when the agent calls `step(now_s)`, so time is whatever the caller
says it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from agent.backends.base import BackendError, Capability, Telemetry, VehicleBackend

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class SimConfig:
    """Physical parameters of the simulated multirotor."""

    start_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where the vehicle stands at power-on (d = 0 is the ground)."""
    start_heading_rad: float = 0.0
    max_accel_m_s2: float = 4.0
    """Horizontal and vertical acceleration limit of velocity tracking."""
    max_speed_m_s: float = 12.0
    climb_rate_m_s: float = 2.0
    """Take-off climb rate."""
    descent_rate_m_s: float = 1.0
    """Landing descent rate."""
    hold_gain_1_s: float = 1.0
    """Position-hold gain: commanded speed = gain * position error."""
    battery_drain_pct_s: float = 100.0 / (20 * 60)
    """Battery used per second in the air (20 min endurance)."""
    setpoint_timeout_s: float = 0.5
    """Like PX4 offboard: with no velocity setpoint for this long, the vehicle holds."""

    def __post_init__(self) -> None:
        for name in ("max_accel_m_s2", "max_speed_m_s", "climb_rate_m_s", "descent_rate_m_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if not all(math.isfinite(v) for v in self.start_ned_m):
            raise ValueError(f"start_ned_m must be finite, got {self.start_ned_m}")


class SimBackend(VehicleBackend):
    """A simulated vehicle. Not thread-safe on its own: the agent serialises calls."""

    capabilities = frozenset({Capability.VELOCITY_SETPOINT})

    def __init__(self, cfg: SimConfig = SimConfig(), now_s: float = 0.0) -> None:
        self.cfg = cfg
        self.pos_m = np.array(cfg.start_ned_m, dtype=float)
        self.pos_m[2] = min(self.pos_m[2], 0.0)
        self.vel_m_s = np.zeros(3)
        self.heading_rad = cfg.start_heading_rad
        self.armed = False
        self.battery_pct = 100.0
        self._mode = "idle"  # idle | takeoff | hold | velocity | land | falling
        self._target_alt_m = 0.0
        self._hold_m = self.pos_m.copy()
        self._setpoint_m_s = np.zeros(3)
        self._setpoint_heading_rad = self.heading_rad
        self._setpoint_stamp_s = -math.inf
        self._now_s = now_s
        self._closed = False

    # -- VehicleBackend ---------------------------------------------------------------------
    def close(self) -> None:
        self._closed = True

    def telemetry(self) -> Telemetry | None:
        return Telemetry(
            stamp_s=self._now_s,
            pos_ned_m=tuple(float(x) for x in self.pos_m),  # type: ignore[arg-type]
            vel_ned_m_s=tuple(float(x) for x in self.vel_m_s),  # type: ignore[arg-type]
            heading_rad=self.heading_rad,
            armed=self.armed,
            in_air=self.in_air,
            battery_pct=self.battery_pct,
            link_ok=not self._closed,
        )

    @property
    def in_air(self) -> bool:
        return bool(self.pos_m[2] < -0.05)

    def takeoff(self, alt_m: float) -> None:
        self._check_open()
        if not (math.isfinite(alt_m) and alt_m > 0):
            raise BackendError(f"takeoff altitude must be positive, got {alt_m}")
        if self.battery_pct < 5.0:
            raise BackendError(f"battery too low to take off ({self.battery_pct:.0f} %)")
        self.armed = True
        self._target_alt_m = alt_m
        self._hold_m = self.pos_m.copy()
        self._mode = "takeoff"

    def land(self) -> None:
        self._check_open()
        if not self.armed:
            return
        self._hold_m = self.pos_m.copy()
        self._mode = "land"

    def hold(self) -> None:
        self._check_open()
        if not self.armed:
            raise BackendError("cannot hold: vehicle is disarmed")
        self._hold_m = self.pos_m.copy()
        self._mode = "hold"

    def kill(self) -> None:
        self._check_open()
        self.armed = False
        self._mode = "falling" if self.in_air else "idle"

    def set_velocity_ned(self, vel_ned_m_s: Sequence[float], heading_rad: float) -> None:
        self._check_open()
        v = np.asarray(vel_ned_m_s, dtype=float)
        if v.shape != (3,) or not np.all(np.isfinite(v)) or not math.isfinite(heading_rad):
            raise BackendError(f"velocity setpoint must be 3 finite numbers, got {vel_ned_m_s}")
        if not self.armed:
            raise BackendError("cannot fly a velocity setpoint: vehicle is disarmed")
        speed = float(np.linalg.norm(v))
        if speed > self.cfg.max_speed_m_s:
            v *= self.cfg.max_speed_m_s / speed
        self._setpoint_m_s = v
        self._setpoint_heading_rad = heading_rad
        self._setpoint_stamp_s = self._now_s
        self._mode = "velocity"

    def step(self, now_s: float) -> None:
        dt_s = now_s - self._now_s
        self._now_s = now_s
        if dt_s <= 0:
            return
        dt_s = min(dt_s, 0.5)  # a stalled process must not teleport the vehicle
        self._integrate(dt_s)

    # -- physics ------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise BackendError("simulator is closed")

    def _desired_velocity(self) -> np.ndarray:
        cfg = self.cfg
        if (
            self._mode == "velocity"
            and self._now_s - self._setpoint_stamp_s > cfg.setpoint_timeout_s
        ):
            self._hold_m = self.pos_m.copy()  # setpoints stopped: hold, as PX4 does
            self._mode = "hold"
        if self._mode == "velocity":
            return self._setpoint_m_s.copy()
        if self._mode in ("hold", "takeoff", "land"):
            err = self._hold_m - self.pos_m
            v = cfg.hold_gain_1_s * err
            if self._mode == "takeoff":
                v[2] = -cfg.climb_rate_m_s if -self.pos_m[2] < self._target_alt_m - 0.05 else 0.0
                if -self.pos_m[2] >= self._target_alt_m - 0.05:
                    self._hold_m = self.pos_m.copy()
                    self._hold_m[2] = -self._target_alt_m
                    self._mode = "hold"
            elif self._mode == "land":
                v[2] = cfg.descent_rate_m_s if -self.pos_m[2] > 2.0 else 0.5 * cfg.descent_rate_m_s
            return v
        return np.zeros(3)

    def _integrate(self, dt_s: float) -> None:
        cfg = self.cfg
        if self._mode == "falling":
            self.vel_m_s[:2] *= max(0.0, 1.0 - 0.5 * dt_s)  # drag
            self.vel_m_s[2] += GRAVITY_M_S2 * dt_s
        elif self._mode != "idle":
            dv = self._desired_velocity() - self.vel_m_s
            dv_norm = float(np.linalg.norm(dv))
            max_dv = cfg.max_accel_m_s2 * dt_s
            if dv_norm > max_dv:
                dv *= max_dv / dv_norm
            self.vel_m_s += dv
        else:
            self.vel_m_s[:] = 0.0
        self.pos_m += self.vel_m_s * dt_s
        if self.pos_m[2] >= 0.0:  # ground contact
            self.pos_m[2] = 0.0
            if self.vel_m_s[2] > 0:
                self.vel_m_s[:] = 0.0
                if self._mode in ("land", "falling"):
                    self.armed = False
                    self._mode = "idle"
        horizontal_m_s = math.hypot(self.vel_m_s[0], self.vel_m_s[1])
        if self._mode == "velocity":
            self.heading_rad = self._setpoint_heading_rad
        elif horizontal_m_s > 0.2 and self.armed:
            self.heading_rad = math.atan2(self.vel_m_s[1], self.vel_m_s[0])
        if self.in_air and self.armed:
            self.battery_pct = max(0.0, self.battery_pct - cfg.battery_drain_pct_s * dt_s)
