"""Airframe and autopilot settings of the emulated vehicle, named after PX4's parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class VehicleParams:
    """Airframe and autopilot settings (PX4 parameter names in brackets)."""

    cruise_speed_m_s: float = 5.0
    """Horizontal speed of goto/hold/RTL flight [MPC_XY_CRUISE]."""
    max_speed_m_s: float = 12.0
    """Largest horizontal offboard velocity accepted [MPC_XY_VEL_MAX]."""
    climb_speed_m_s: float = 3.0
    """Largest climb rate [MPC_Z_VEL_MAX_UP]."""
    descent_speed_m_s: float = 1.5
    """Largest descent rate outside LAND [MPC_Z_VEL_MAX_DN]."""
    takeoff_speed_m_s: float = 1.5
    """Climb rate in TAKEOFF [MPC_TKO_SPEED]."""
    land_speed_m_s: float = 0.7
    """Descent rate in LAND [MPC_LAND_SPEED]."""
    accel_m_s2: float = 3.0
    """Largest acceleration the velocity controller asks for [MPC_ACC_HOR]."""
    pos_gain_1_s: float = 1.0
    """Position loop gain: v = gain * position error [MPC_XY_P]."""
    yaw_rate_rad_s: float = math.radians(60.0)
    """Largest yaw rate [MPC_YAWRAUTO_MAX]."""
    takeoff_alt_m: float = 2.5
    """Takeoff altitude when the command gives none [MIS_TAKEOFF_ALT]."""
    rtl_alt_m: float = 30.0
    """Lowest altitude of the return leg [RTL_RETURN_ALT]."""
    offboard_loss_s: float = 1.0
    """Setpoint age after which offboard fails over to HOLD [COM_OF_LOSS_T]."""
    disarm_after_land_s: float = 2.0
    """Auto-disarm delay after touchdown [COM_DISARM_LAND]."""
    disarm_preflight_s: float = 10.0
    """Auto-disarm when armed on the ground without taking off [COM_DISARM_PRFLT]."""
    arrive_radius_m: float = 1.0
    """A goto is done within this horizontal distance [NAV_ACC_RAD]."""
    battery_drain_pct_s: float = 0.05
    """Battery use per second while armed."""
    max_alt_m: float = 120.0
    """Highest goto/takeoff altitude above home accepted [GF_MAX_VER_DIST]."""
