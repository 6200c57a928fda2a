"""The one point-mass model: N vehicles as arrays, advanced by one explicit Euler step.

Every simulator in covey flies its vehicles through `integrate`: the built-in vehicle simulator
behind the agent and `covey fleet-sim` (agent/backends/sim.py), the PX4 emulator
(firmware/sitl/vehicle.py, which adds PX4's modes on top), the policy's evaluation simulator
(policy/evalsim.py) and its training arenas (policy/env.py), both 2-D with no acceleration limit. What differs between them is only how the
wanted velocity is chosen; the physics is this.

Powered rows track their wanted velocity with a limited acceleration (the step of the velocity
is clipped to `max_accel_m_s2 * dt_s` as a vector). Unpowered rows in the air fall: gravity
down, drag on the horizontal speed. Rows in 3-D (N, 3) NED stop at the ground (d = 0).
"""

from __future__ import annotations

import numpy as np

GRAVITY_M_S2 = 9.80665
"""Standard gravity (the one value every model uses)."""
FALL_DRAG_1_S = 0.5
"""Horizontal speed lost per second by a vehicle falling with its motors off."""


def integrate(
    pos_m: np.ndarray,
    vel_m_s: np.ndarray,
    want_vel_m_s: np.ndarray,
    dt_s: float,
    max_accel_m_s2: float | np.ndarray = np.inf,
    powered: np.ndarray | None = None,
) -> np.ndarray:
    """Advance `pos_m` and `vel_m_s` (N, D) in place by `dt_s`; returns the rows that hit the
    ground in this step, moving down, and were stopped there (N,) bool (always False in 2-D).

    `want_vel_m_s` (N, D): the velocity each powered row tracks. `max_accel_m_s2`: a scalar or
    (N,) limit; inf tracks the wanted velocity exactly (the evaluation simulator). `powered`
    (N,) bool, default all: unpowered rows fall when airborne (3-D) and stand still otherwise.
    A row on the ground stays there unless its new velocity points up (d decreasing).
    """
    n, dims = pos_m.shape
    if powered is None:
        powered = np.ones(n, bool)
    dv = want_vel_m_s - vel_m_s
    limit = np.broadcast_to(np.asarray(max_accel_m_s2, dtype=float) * dt_s, (n,))
    norm = np.linalg.norm(dv, axis=1)
    scale = np.ones(n)
    over = norm > limit
    scale[over] = limit[over] / norm[over]
    if np.all(np.isinf(limit)):
        vel_m_s[powered] = want_vel_m_s[powered]  # exactly the wanted velocity
    else:
        vel_m_s[powered] += dv[powered] * scale[powered, None]
    if dims == 3:
        falling = ~powered & (pos_m[:, 2] < 0.0)
        vel_m_s[falling, :2] *= max(0.0, 1.0 - FALL_DRAG_1_S * dt_s)
        vel_m_s[falling, 2] += GRAVITY_M_S2 * dt_s
        vel_m_s[~powered & ~falling] = 0.0
    else:
        vel_m_s[~powered] = 0.0
    pos_m += vel_m_s * dt_s
    if dims != 3:
        return np.zeros(n, bool)
    ground = pos_m[:, 2] >= 0.0
    pos_m[ground, 2] = 0.0
    hit = ground & (vel_m_s[:, 2] > 0.0)
    vel_m_s[hit] = 0.0
    return hit
