"""The built-in simulator: point-mass multirotors behind the same interface as a real vehicle.

`SimFleet` holds N simulated vehicles as arrays (one process can fly hundreds: `covey
fleet-sim`); `SimBackend` is one of them behind the `VehicleBackend` interface (`covey agent
--backend sim`). Each vehicle tracks velocity with an acceleration limit, takes off and lands
vertically at fixed rates, drains a battery in the air, and falls when killed; the physics is
the one point-mass model (policy/pointmass.py). The simulator integrates only when `step(now_s)`
is called, so time is whatever the caller says it is. Thread-safe: one lock guards the arrays.

With a `VehicleModel` (`SimConfig.vehicle`, e.g. `realistic`: velocity lag, gusts, a drifting
GNSS estimate) the vehicles fly like real ones: `pos_m` is then what each autopilot believes and
reports (its estimate, which its position holds act on), `true_pos_m` where it really is (what
separation is judged on), and telemetry carries the estimate's 1-sigma (`pos_sigma_m`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from agent.backends.base import BackendError, Capability, Telemetry, VehicleBackend
from agent.backends.sim_modes import _COMING_DOWN, _IDLE, _POSITIONAL, SimMode
from agent.backends.sim_one import integrate_one
from policy.pointmass import VehicleModel, Vehicles


@dataclass(frozen=True)
class SimConfig:
    """Physical parameters of the simulated multirotor."""

    start_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where the vehicle stands at power-on (d = 0 is the ground); `SimFleet` takes one per row."""
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
    max_step_s: float = 0.5
    """Longest time one `step` integrates: a stalled process must not teleport the vehicles."""
    vehicle: VehicleModel | None = None
    """How real the vehicles are (policy.pointmass: VehicleModel.realistic() for lag, gusts and
    GNSS drift; its acceleration limit then replaces max_accel_m_s2). None: no lag, no gusts,
    exact positions, max_accel_m_s2 (the simulator as it always was)."""

    def __post_init__(self) -> None:
        for name in (
            "max_accel_m_s2",
            "max_speed_m_s",
            "climb_rate_m_s",
            "descent_rate_m_s",
            "max_step_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if not all(math.isfinite(v) for v in self.start_ned_m):
            raise ValueError(f"start_ned_m must be finite, got {self.start_ned_m}")


class SimFleet:
    """N simulated vehicles. Commands address one row and raise `BackendError` with the reason
    a real autopilot would give; `set_velocities` and `step` work on all rows at once."""

    def __init__(
        self,
        cfg: SimConfig = SimConfig(),
        starts_ned_m: np.ndarray | None = None,
        now_s: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> None:
        """`rng` draws the gusts and the drift of `cfg.vehicle` (None: fresh entropy)."""
        self.cfg = cfg
        starts = np.array([cfg.start_ned_m] if starts_ned_m is None else starts_ned_m, float)
        if starts.ndim != 2 or starts.shape[1] != 3 or not np.all(np.isfinite(starts)):
            raise ValueError(f"starts_ned_m must be finite (N, 3), got shape {starts.shape}")
        n = len(starts)
        self.n = n
        starts = starts.copy()
        starts[:, 2] = np.minimum(starts[:, 2], 0.0)
        model = cfg.vehicle or VehicleModel(max_accel_m_s2=cfg.max_accel_m_s2)
        self.body = Vehicles(starts, model, rng if rng is not None else np.random.default_rng())
        """The vehicles' physics (policy.pointmass): truth, loop velocity, gusts, drift."""
        self.true_pos_m = self.body.pos_m
        """Where the vehicles really are (N, 3)."""
        self.pos_m = self.true_pos_m if model.drift_m == 0 else self.body.est_pos_m
        """Where each autopilot believes it is (N, 3): the truth with exact positions."""
        self.pos_sigma_m = model.pos_sigma_m
        """The 1-sigma each reports of its horizontal position estimate."""
        self.vel_m_s = self.body.vel_m_s
        self.heading_rad = np.full(n, cfg.start_heading_rad)
        self.armed = np.zeros(n, bool)
        self.battery_pct = np.full(n, 100.0)
        self.mode = np.full(n, SimMode.IDLE, np.int8)
        self.target_alt_m = np.zeros(n)
        self.hold_m = self.pos_m.copy()
        self.sp_vel_m_s = np.zeros((n, 3))
        self.sp_heading_rad = self.heading_rad.copy()
        self.sp_stamp_s = np.full(n, -np.inf)
        self.closed = np.zeros(n, bool)
        self.now_s = now_s
        self.lock = threading.RLock()

    # -- one row's commands ---------------------------------------------------------------------
    def _check_open(self, i: int) -> None:
        if self.closed[i]:
            raise BackendError("simulator is closed")

    def in_air(self, i: int) -> bool:
        return self.pos_m.item(i, 2) < -0.05

    def telemetry(self, i: int) -> Telemetry:
        with self.lock:
            p, v = self.pos_m[i].tolist(), self.ground_vel_m_s[i].tolist()
            return Telemetry(
                stamp_s=self.now_s,
                pos_ned_m=(p[0], p[1], p[2]),
                vel_ned_m_s=(v[0], v[1], v[2]),
                heading_rad=float(self.heading_rad[i]),
                armed=bool(self.armed[i]),
                in_air=self.in_air(i),
                battery_pct=float(self.battery_pct[i]),
                link_ok=not self.closed[i],
                pos_sigma_m=self.pos_sigma_m,
            )

    def takeoff(self, i: int, alt_m: float) -> None:
        with self.lock:
            self._check_open(i)
            if not (math.isfinite(alt_m) and alt_m > 0):
                raise BackendError(f"takeoff altitude must be positive, got {alt_m}")
            if self.battery_pct[i] < 5.0:
                raise BackendError(f"battery too low to take off ({self.battery_pct[i]:.0f} %)")
            self.armed[i] = True
            self.target_alt_m[i] = alt_m
            self.hold_m[i] = self.pos_m[i]
            self.mode[i] = SimMode.TAKEOFF

    def land(self, i: int) -> None:
        with self.lock:
            self._check_open(i)
            if not self.armed[i]:
                return
            self.hold_m[i] = self.pos_m[i]
            self.mode[i] = SimMode.LAND

    def hold(self, i: int) -> None:
        with self.lock:
            self._check_open(i)
            if not self.armed[i]:
                raise BackendError("cannot hold: vehicle is disarmed")
            self.hold_m[i] = self.pos_m[i]
            self.mode[i] = SimMode.HOLD

    def kill(self, i: int) -> None:
        with self.lock:
            self._check_open(i)
            self.armed[i] = False
            self.mode[i] = SimMode.FALLING if self.in_air(i) else SimMode.IDLE

    def set_velocity(self, i: int, vel_ned_m_s: Sequence[float], heading_rad: float) -> None:
        v = np.asarray(vel_ned_m_s, dtype=float)
        if v.shape != (3,) or not np.all(np.isfinite(v)) or not math.isfinite(heading_rad):
            raise BackendError(f"velocity setpoint must be 3 finite numbers, got {vel_ned_m_s}")
        with self.lock:
            self._check_open(i)
            if not self.armed[i]:
                raise BackendError("cannot fly a velocity setpoint: vehicle is disarmed")
            self.set_velocities(np.array([i]), v[None], np.array([heading_rad]))

    def set_velocities(self, rows: np.ndarray, vel_ned_m_s: np.ndarray, heading_rad: np.ndarray):
        """Velocity setpoints for `rows` (armed, open, finite: the caller checked)."""
        with self.lock:
            if self.n == 1 and len(rows) == 1:  # an agent's every tick: on Python floats
                (vn, ve, vd), top = (
                    np.asarray(vel_ned_m_s, float)[0].tolist(),
                    self.cfg.max_speed_m_s,
                )
                speed = math.sqrt(vn * vn + ve * ve + vd * vd)
                if speed > top:
                    k = top / speed
                    vn, ve, vd = vn * k, ve * k, vd * k
                self.sp_vel_m_s[0] = (vn, ve, vd)
                self.sp_heading_rad[0] = np.asarray(heading_rad, float).reshape(-1)[0]
                self.sp_stamp_s[0] = self.now_s
                self.mode[0] = SimMode.VELOCITY
                return
            v = np.array(vel_ned_m_s, dtype=float)
            speed = np.linalg.norm(v, axis=1)
            fast = speed > self.cfg.max_speed_m_s
            v[fast] *= (self.cfg.max_speed_m_s / speed[fast])[:, None]
            self.sp_vel_m_s[rows] = v
            self.sp_heading_rad[rows] = heading_rad
            self.sp_stamp_s[rows] = self.now_s
            self.mode[rows] = SimMode.VELOCITY

    def close(self, i: int) -> None:
        with self.lock:
            self.closed[i] = True

    # -- physics --------------------------------------------------------------------------------
    def step(self, now_s: float) -> None:
        """Integrate every vehicle up to `now_s` (at most `max_step_s` at once)."""
        with self.lock:
            dt_s = now_s - self.now_s
            self.now_s = now_s
            if dt_s <= 0:
                return
            if self.n == 1:  # an agent's one vehicle: the same maths on Python floats
                integrate_one(self, min(dt_s, self.cfg.max_step_s))
            elif not self.at_rest():
                self._integrate(min(dt_s, self.cfg.max_step_s))

    @property
    def ground_vel_m_s(self) -> np.ndarray:
        """What each autopilot measures of its velocity (N, 3): the loop's plus the gust on
        airborne rows, as GNSS sees it (the loop's own array where there are no gusts)."""
        if self.body.model.gust_m_s <= 0:
            return self.vel_m_s
        v = self.vel_m_s.copy()
        if self.n == 1:  # an agent's one vehicle: no mask
            if self.true_pos_m.item(2) < 0.0:
                v[0, :2] += self.body.gust_m_s[0]
            return v
        air = self.true_pos_m[:, 2] < 0.0
        v[air, :2] += self.body.gust_m_s[air]
        return v

    def at_rest(self) -> bool:
        """Every vehicle stands still on the ground, motors off: a fixed point of `_integrate`
        (unpowered on the ground: zero velocity, no fall, no heading change, no battery drain), so
        a step may skip it. Most of a landed agent's tick otherwise (tests/test_agent_sim.py)."""
        return bool(
            (self.mode == _IDLE).all()
            and not self.armed.any()
            and (self.pos_m[:, 2] >= 0.0).all()
            and not self.vel_m_s.any()
        )

    def _wanted_velocity(self) -> np.ndarray:
        cfg, mode, pos = self.cfg, self.mode, self.pos_m
        lapsed = (mode == SimMode.VELOCITY) & (
            self.now_s - self.sp_stamp_s > cfg.setpoint_timeout_s
        )
        self.hold_m[lapsed] = pos[lapsed]  # setpoints stopped: hold, as PX4 does
        mode[lapsed] = SimMode.HOLD
        want = np.zeros_like(self.vel_m_s)
        vel = mode == SimMode.VELOCITY
        want[vel] = self.sp_vel_m_s[vel]
        positional = _POSITIONAL[mode]
        want[positional] = cfg.hold_gain_1_s * (self.hold_m[positional] - pos[positional])
        up = mode == SimMode.TAKEOFF
        below = -pos[:, 2] < self.target_alt_m - 0.05
        want[up, 2] = np.where(below[up], -cfg.climb_rate_m_s, 0.0)
        done = up & ~below  # at the take-off altitude: hold there
        self.hold_m[done] = pos[done]
        self.hold_m[done, 2] = -self.target_alt_m[done]
        mode[done] = SimMode.HOLD
        down = mode == SimMode.LAND
        want[down, 2] = np.where(-pos[down, 2] > 2.0, 1.0, 0.5) * cfg.descent_rate_m_s
        return want

    def _integrate(self, dt_s: float) -> None:
        """Every row at once (the reference for agent/backends/sim_one.py `integrate_one`)."""
        cfg = self.cfg
        powered = (self.mode != SimMode.IDLE) & (self.mode != SimMode.FALLING)
        hit = self.body.step(self._wanted_velocity(), dt_s, powered)
        if self.pos_m is not self.true_pos_m:  # the estimate follows the truth, off by the drift
            self.pos_m[:] = self.true_pos_m
            self.pos_m[:, :2] += self.body.drift_m
        down = hit & _COMING_DOWN[self.mode]
        self.armed[down] = False
        self.mode[down] = SimMode.IDLE
        vel = self.mode == SimMode.VELOCITY
        self.heading_rad[vel] = self.sp_heading_rad[vel]
        moving = ~vel & self.armed & (np.hypot(self.vel_m_s[:, 0], self.vel_m_s[:, 1]) > 0.2)
        self.heading_rad[moving] = np.arctan2(self.vel_m_s[moving, 1], self.vel_m_s[moving, 0])
        flying = (self.pos_m[:, 2] < -0.05) & self.armed
        self.battery_pct[flying] = np.maximum(
            0.0, self.battery_pct[flying] - cfg.battery_drain_pct_s * dt_s
        )


class SimBackend(VehicleBackend):
    """One simulated vehicle: row `index` of a `SimFleet` (its own fleet of one by default)."""

    capabilities = frozenset({Capability.VELOCITY_SETPOINT})

    def __init__(
        self,
        cfg: SimConfig = SimConfig(),
        now_s: float = 0.0,
        *,
        fleet: SimFleet | None = None,
        index: int = 0,
    ) -> None:
        self.fleet = fleet if fleet is not None else SimFleet(cfg, now_s=now_s)
        self.cfg = self.fleet.cfg
        self.index = index

    def close(self) -> None:
        self.fleet.close(self.index)

    def telemetry(self) -> Telemetry | None:
        return self.fleet.telemetry(self.index)

    def takeoff(self, alt_m: float) -> None:
        self.fleet.takeoff(self.index, alt_m)

    def land(self) -> None:
        self.fleet.land(self.index)

    def hold(self) -> None:
        self.fleet.hold(self.index)

    def kill(self) -> None:
        self.fleet.kill(self.index)

    def set_velocity_ned(self, vel_ned_m_s: Sequence[float], heading_rad: float) -> None:
        self.fleet.set_velocity(self.index, vel_ned_m_s, heading_rad)

    def step(self, now_s: float) -> None:
        self.fleet.step(now_s)
