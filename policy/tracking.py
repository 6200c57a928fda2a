"""Tracking compensation: the part of the flown velocity the velocity loop did not command
(gusts it does not reject, a slower loop than assumed), estimated and taken off the next command.

The safety filter picks each vehicle's velocity; the vehicle then flies that velocity plus
whatever its loop does not reject. With 0.5 m/s gusts and a 0.5 s loop a vehicle strays by more
than the filter's 0.6 m margin between its ticks, and crowds lose the 3 m on true positions
(docs/sky.md, "Gusts: the tracking compensation"). So each row keeps a model of its loop (a
first-order lag with an acceleration limit, `TrackingConfig.lag_s` and `max_accel_m_s2`: what
the vehicle should be flying now after the commands it was given) and a low-passed estimate of
the error, measured ground velocity less the model's (`window_s`), and each new command is the
wanted velocity less that error, the error capped at `max_correction_m_s`. This is the outer
integral a velocity loop that rejects wind (PX4's, with its integrator) already has: behind
such a loop the measured error is about 0 and the command goes through unchanged, and with a
loop that flies exactly what it is told (the ideal vehicles) it is exactly 0.

Horizontal only (north, east); a row not guided for `max_gap_s` (landed, in an autopilot
action, a new goto after a pause) starts again from its measured velocity with no error. Time
is what the caller says it is (`now_s`): ticks may be 10 Hz, calm (3.3 Hz) or held (1 Hz).
`correct` is the one implementation, used by `covey eval` (policy/evalsim.py) and the agents'
shell (agent/shell.py) alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from policy.pointmass import VehicleModel


@dataclass(frozen=True)
class TrackingConfig:
    """The loop model and the estimator of the tracking compensation (module docstring)."""

    enabled: bool = True
    """False: commands go to the vehicle as the guidance made them (before)."""
    lag_s: float = 0.3
    """Time constant of the vehicle's velocity loop as the model takes it (first order; 0: the
    vehicle reaches a new setpoint at once). 0.3 s: a multirotor's (PX4's MPC at its defaults);
    a model slower or faster than the vehicle still converges (tests/test_tracking.py)."""
    max_accel_m_s2: float = 2.5
    """Acceleration limit of the modelled loop (inf: none)."""
    window_s: float = 1.0
    """Time constant of the error's low-pass: shorter follows gusts faster and passes more
    of the measurement's noise and of the loop model's mismatch in turns."""
    max_correction_m_s: float = 1.0
    """Largest correction taken off a command (m/s): a vehicle held by something the model does
    not know (a wall, a tether, its autopilot's own limit) is not pushed harder than this."""
    max_gap_s: float = 2.5
    """A row not corrected for longer than this starts afresh (at least the 1 Hz hold tick)."""

    def __post_init__(self) -> None:
        for name in ("lag_s", "max_correction_m_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"tracking {name} must be finite and >= 0, got {v}")
        for name in ("window_s", "max_gap_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"tracking {name} must be finite and > 0, got {v}")
        if not self.max_accel_m_s2 > 0:  # NaN too; inf allowed
            raise ValueError(f"tracking max_accel_m_s2 must be > 0, got {self.max_accel_m_s2}")

    @classmethod
    def assumed(
        cls, model: VehicleModel | None, enabled: bool = True, lag_s: float | None = None
    ) -> TrackingConfig:
        """What a vehicle's shell (or `covey eval`) assumes: `for_model` of a simulated
        vehicle's `model`, the defaults behind a real autopilot (None); `lag_s` (None: that
        one's) replaces the loop's lag, `enabled` False turns it off."""
        changes: dict = {} if lag_s is None else {"lag_s": lag_s}
        if model is None:
            return cls(enabled=enabled, **changes)
        return cls.for_model(model, enabled=enabled, **changes)

    @classmethod
    def for_model(cls, model: VehicleModel, **changes: object) -> TrackingConfig:
        """The loop of a simulated vehicle as the simulator flies it (its lag and acceleration
        limit): what the agent on a simulated vehicle and `covey eval` assume. Off for a model
        with neither lag nor gusts: such a vehicle flies its setpoint (the simulator limits the
        3-D acceleration, which a horizontal model would only mistake for an error)."""
        fields: dict = {"lag_s": model.lag_s, "max_accel_m_s2": model.max_accel_m_s2, **changes}
        if model.lag_s == 0 and model.gust_m_s == 0:
            fields["enabled"] = False
        return cls(**fields)


class Tracking:
    """The compensation of n rows (vehicles): each row's modelled loop velocity, error estimate,
    last command and when it was given."""

    def __init__(self, cfg: TrackingConfig, n: int) -> None:
        self.cfg = cfg
        self.loop_m_s = np.zeros((n, 2))
        """What each row's loop should be flying after its commands (the model)."""
        self.error_m_s = np.zeros((n, 2))
        """Each row's estimated tracking error: measured less modelled, low-passed."""
        self.cmd_m_s = np.zeros((n, 2))
        """Each row's last command as sent (the wanted velocity less the error)."""
        self.t_s = np.full(n, np.nan)
        """When each row was last corrected (NaN: not yet, or forgotten)."""

    def forget(self, rows: np.ndarray | None = None) -> None:
        """Rows (all: None) start afresh at their next correction."""
        self.t_s[slice(None) if rows is None else rows] = np.nan

    def correct(
        self, rows: np.ndarray, now_s: float, want_m_s: np.ndarray, measured_m_s: np.ndarray
    ) -> np.ndarray:
        """The commands (k, 2) for `rows` (k,) wanting to fly `want_m_s` (k, 2) over the ground,
        whose ground velocity measured now is `measured_m_s` (k, 2). Rows starting afresh get
        their wanted velocity."""
        want = np.asarray(want_m_s, dtype=float).reshape(-1, 2)
        if not self.cfg.enabled or want.shape[0] == 0:
            return want.copy()
        rows = np.asarray(rows)
        if want.shape[0] == 1:  # an agent's one vehicle: the same on Python floats
            return self._correct_one(int(rows.reshape(-1)[0]), now_s, want, measured_m_s)
        return self.correct_rows(rows, now_s, want, measured_m_s)

    def correct_rows(
        self, rows: np.ndarray, now_s: float, want: np.ndarray, measured_m_s: np.ndarray
    ) -> np.ndarray:
        """`correct` on arrays, any number of rows (the reference for `_correct_one`)."""
        rows = np.asarray(rows)
        meas = np.asarray(measured_m_s, dtype=float).reshape(-1, 2)
        cfg = self.cfg
        dt = now_s - self.t_s[rows]
        fresh = ~((dt > 0) & (dt <= cfg.max_gap_s)) | ~np.isfinite(meas).all(axis=1)
        dt = np.where(fresh, 0.0, dt)
        loop = self.loop_m_s[rows]
        # the model's loop, flown over dt with the last command (exact for a first-order lag)
        last = self.cmd_m_s[rows]
        dv = last - loop
        if cfg.lag_s > 0:
            dv *= -np.expm1(-dt / cfg.lag_s)[:, None]
        over = np.zeros(len(rows), bool)
        if math.isfinite(cfg.max_accel_m_s2):
            limit = cfg.max_accel_m_s2 * dt
            norm = np.hypot(dv[:, 0], dv[:, 1])
            over = norm > limit
            dv[over] *= (limit[over] / norm[over])[:, None]
        reached = ~over if cfg.lag_s == 0 else np.zeros(len(rows), bool)
        loop = np.where(reached[:, None], last, loop + dv)  # exactly the command where reached
        err = self.error_m_s[rows]
        gain = -np.expm1(-dt / cfg.window_s)
        err += gain[:, None] * (np.where(np.isfinite(meas), meas, loop) - loop - err)
        size = np.hypot(err[:, 0], err[:, 1])
        big = size > cfg.max_correction_m_s
        err[big] *= (cfg.max_correction_m_s / size[big])[:, None]
        loop[fresh] = np.where(np.isfinite(meas[fresh]), meas[fresh], 0.0)
        err[fresh] = 0.0
        cmd = want - err
        self.loop_m_s[rows], self.error_m_s[rows], self.cmd_m_s[rows] = loop, err, cmd
        self.t_s[rows] = now_s
        return cmd

    def _correct_one(
        self, i: int, now_s: float, want: np.ndarray, measured_m_s: np.ndarray
    ) -> np.ndarray:
        """`correct_rows` for the one row `i`, on Python floats (~10x fewer numpy calls; equal
        to it: tests/test_tracking.py)."""
        cfg = self.cfg
        wn, we = want[0].tolist()
        mn, me = np.asarray(measured_m_s, dtype=float).reshape(2).tolist()
        dt = now_s - float(self.t_s[i])
        fresh = not (0 < dt <= cfg.max_gap_s) or not (math.isfinite(mn) and math.isfinite(me))
        if fresh:
            ln, le = (mn if math.isfinite(mn) else 0.0), (me if math.isfinite(me) else 0.0)
            en = ee = 0.0
        else:
            ln, le = self.loop_m_s[i].tolist()
            cn, ce = self.cmd_m_s[i].tolist()
            dn, de = cn - ln, ce - le
            if cfg.lag_s > 0:
                f = -math.expm1(-dt / cfg.lag_s)
                dn, de = dn * f, de * f
            over = False
            if math.isfinite(cfg.max_accel_m_s2):
                limit = cfg.max_accel_m_s2 * dt
                norm = math.hypot(dn, de)
                if norm > limit:
                    over = True
                    dn, de = dn * (limit / norm), de * (limit / norm)
            if cfg.lag_s == 0 and not over:
                ln, le = cn, ce
            else:
                ln, le = ln + dn, le + de
            en, ee = self.error_m_s[i].tolist()
            g = -math.expm1(-dt / cfg.window_s)
            en += g * (mn - ln - en)
            ee += g * (me - le - ee)
            size = math.hypot(en, ee)
            if size > cfg.max_correction_m_s:
                en, ee = en * (cfg.max_correction_m_s / size), ee * (cfg.max_correction_m_s / size)
        cn, ce = wn - en, we - ee
        self.loop_m_s[i] = (ln, le)
        self.error_m_s[i] = (en, ee)
        self.cmd_m_s[i] = (cn, ce)
        self.t_s[i] = now_s
        return np.array([[cn, ce]])
