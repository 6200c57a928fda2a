"""One simulated vehicle stepped on Python floats: `SimFleet._wanted_velocity` and
`SimFleet._integrate` (with policy.pointmass.integrate) for a fleet of one, the fast path of an
agent's tick (tests/test_sim_one_row.py holds it equal to the array path)."""

from __future__ import annotations

import math
from typing import Any

from agent.backends.sim_modes import (
    _COMING_DOWN,
    _FALLING,
    _HOLD,
    _IDLE,
    _LAND,
    _POSITIONAL,
    _TAKEOFF,
    _VELOCITY,
)
from policy.pointmass import FALL_DRAG_1_S, GRAVITY_M_S2, gauss_markov


def integrate_one(fleet: Any, dt_s: float) -> None:
    """`fleet`: an agent.backends.sim.SimFleet of one (not imported: sim.py imports this).
    `_wanted_velocity` and `_integrate` (with policy.pointmass.integrate) for a fleet of
    one, on Python floats: the array path costs a one-row fleet ~60 small numpy calls (~0.18
    ms a step, an agent's every tick; this ~5 us). Equal to it (tests/test_sim_one_row.py),
    the at-rest skip (`at_rest`) included."""
    cfg, body, model = fleet.cfg, fleet.body, fleet.body.model
    mode = int(fleet.mode[0])
    armed = bool(fleet.armed[0])
    tn, te, td = fleet.true_pos_m[0].tolist()
    vn, ve, vd = fleet.vel_m_s[0].tolist()
    if mode == _IDLE and not armed and td >= 0.0 and vn == 0.0 and ve == 0.0 and vd == 0.0:
        return  # at rest: a fixed point
    pn, pe, pd = fleet.pos_m[0].tolist()
    # -- _wanted_velocity
    if mode == _VELOCITY and fleet.now_s - float(fleet.sp_stamp_s[0]) > cfg.setpoint_timeout_s:
        fleet.hold_m[0] = (pn, pe, pd)  # setpoints stopped: hold, as PX4 does
        mode = _HOLD
    wn = we = wd = 0.0
    if mode == _VELOCITY:
        wn, we, wd = fleet.sp_vel_m_s[0].tolist()
    elif _POSITIONAL[mode]:
        hn, he, hd = fleet.hold_m[0].tolist()
        k = cfg.hold_gain_1_s
        wn, we, wd = k * (hn - pn), k * (he - pe), k * (hd - pd)
    if mode == _TAKEOFF:
        alt = float(fleet.target_alt_m[0])
        if -pd < alt - 0.05:
            wd = -cfg.climb_rate_m_s
        else:  # at the take-off altitude: hold there
            wd = 0.0
            fleet.hold_m[0] = (pn, pe, -alt)
            mode = _HOLD
    elif mode == _LAND:
        wd = (1.0 if -pd > 2.0 else 0.5) * cfg.descent_rate_m_s
    # -- policy.pointmass.integrate, one row
    powered = mode != _IDLE and mode != _FALLING
    if powered:
        dn, de, dd = wn - vn, we - ve, wd - vd
        if model.lag_s > 0.0:
            f = -math.expm1(-dt_s / model.lag_s)
            dn, de, dd = dn * f, de * f, dd * f
        limit = float(model.max_accel_m_s2) * dt_s
        if model.lag_s <= 0.0 and math.isinf(limit):
            vn, ve, vd = wn, we, wd
        else:
            norm = math.sqrt(dn * dn + de * de + dd * dd)
            scale = limit / norm if norm > limit else 1.0
            vn, ve, vd = vn + dn * scale, ve + de * scale, vd + dd * scale
    elif td < 0.0:  # falling
        drag = max(0.0, 1.0 - FALL_DRAG_1_S * dt_s)
        vn, ve, vd = vn * drag, ve * drag, vd + GRAVITY_M_S2 * dt_s
    else:
        vn = ve = vd = 0.0
    tn, te, td = tn + vn * dt_s, te + ve * dt_s, td + vd * dt_s
    if model.gust_m_s > 0 and td < 0.0:
        gn, ge = body.gust_m_s[0].tolist()
        tn, te = tn + gn * dt_s, te + ge * dt_s
    hit = False
    if td >= 0.0:
        td = 0.0
        if vd > 0.0:
            hit = True
            vn = ve = vd = 0.0
    fleet.true_pos_m[0] = (tn, te, td)
    fleet.vel_m_s[0] = (vn, ve, vd)
    gauss_markov(body.gust_m_s, model.gust_m_s, model.gust_corr_s, dt_s, body.rng)
    gauss_markov(body.drift_m, model.drift_m, model.drift_corr_s, dt_s, body.rng)
    pd = td
    if fleet.pos_m is not fleet.true_pos_m:  # the estimate follows the truth, off by the drift
        rn, re = body.drift_m[0].tolist()
        fleet.pos_m[0] = (tn + rn, te + re, td)
    # -- the rest of _integrate
    if hit and _COMING_DOWN[mode]:
        armed = False
        fleet.armed[0] = False
        mode = _IDLE
    fleet.mode[0] = mode
    if mode == _VELOCITY:
        fleet.heading_rad[0] = fleet.sp_heading_rad[0]
    elif armed and math.hypot(vn, ve) > 0.2:
        fleet.heading_rad[0] = math.atan2(ve, vn)
    if pd < -0.05 and armed:
        b = float(fleet.battery_pct[0])
        fleet.battery_pct[0] = max(0.0, b - cfg.battery_drain_pct_s * dt_s)
