"""The telemetry PX4 streams, built from the vehicle state.

Rates follow PX4's default onboard profile closely enough for MAVSDK: position and attitude fast,
status slow, HOME_POSITION periodically (MAVSDK's health check waits for it).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from comms.geo import GeoOrigin
from firmware.sitl.traffic import (
    ADSB_FLAGS_SIMULATED,
    ADSB_FLAGS_VALID_ALTITUDE,
    ADSB_FLAGS_VALID_CALLSIGN,
    ADSB_FLAGS_VALID_COORDS,
    ADSB_FLAGS_VALID_HEADING,
    ADSB_FLAGS_VALID_VELOCITY,
    ADSB_FLAGS_VERTICAL_VELOCITY_VALID,
    TrafficEntry,
)
from firmware.sitl.vehicle import Vehicle

# Sensors PX4 reports in SYS_STATUS; MAVSDK's health reads the GPS bit among them.
SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    | mavlink.MAV_SYS_STATUS_AHRS
)
PREARM_OK = mavlink.MAV_SYS_STATUS_PREARM_CHECK

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT  # the geofence transfer (firmware/sitl/fence.py)
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
)
PX4_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255
"""AUTOPILOT_VERSION.flight_sw_version: PX4 v1.15.0, release build."""


def _landed_state(v: Vehicle) -> int:
    if v.landed:
        return mavlink.MAV_LANDED_STATE_ON_GROUND
    if v.mode.name == "TAKEOFF":
        return mavlink.MAV_LANDED_STATE_TAKEOFF
    if v.mode.name == "LAND":
        return mavlink.MAV_LANDED_STATE_LANDING
    return mavlink.MAV_LANDED_STATE_IN_AIR


def heartbeat(v: Vehicle) -> Any:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_AUTO_ENABLED
    if v.armed:
        base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    state = mavlink.MAV_STATE_ACTIVE if v.armed else mavlink.MAV_STATE_STANDBY
    if v.falling:
        state = mavlink.MAV_STATE_FLIGHT_TERMINATION
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, v.mode.custom_mode, state, 3
    )


def sys_status(v: Vehicle, healthy: bool) -> Any:
    health = SENSORS | PREARM_OK if healthy else SENSORS & ~mavlink.MAV_SYS_STATUS_SENSOR_GPS
    return mavlink.MAVLink_sys_status_message(
        SENSORS | PREARM_OK,
        SENSORS | PREARM_OK,
        health,
        250,
        int(14800 + 2000 * v.battery_pct / 100.0),
        1000 if v.armed else 50,
        int(round(v.battery_pct)),
        0,
        0,
        0,
        0,
        0,
        0,
    )


def global_position_int(v: Vehicle, home: GeoOrigin, boot_ms: int) -> Any:
    lat, lon, alt = home.to_global(*map(float, v.est_pos_ned_m))
    vel = np.clip(np.round(v.ground_vel_ned_m_s * 100.0), -32767, 32767).astype(int)
    hdg_cdeg = int(round(math.degrees(v.heading_rad) * 100.0)) % 36000
    return mavlink.MAVLink_global_position_int_message(
        boot_ms,
        int(round(lat * 1e7)),
        int(round(lon * 1e7)),
        int(round(alt * 1000.0)),
        int(round(v.alt_m * 1000.0)),
        int(vel[0]),
        int(vel[1]),
        int(vel[2]),
        hdg_cdeg,
    )


def local_position_ned(v: Vehicle, boot_ms: int) -> Any:
    p, u = v.est_pos_ned_m, v.ground_vel_ned_m_s
    return mavlink.MAVLink_local_position_ned_message(
        boot_ms, float(p[0]), float(p[1]), float(p[2]), float(u[0]), float(u[1]), float(u[2])
    )


def attitude(v: Vehicle, boot_ms: int) -> Any:
    return mavlink.MAVLink_attitude_message(boot_ms, 0.0, 0.0, v.heading_rad, 0.0, 0.0, 0.0)


def extended_sys_state(v: Vehicle) -> Any:
    return mavlink.MAVLink_extended_sys_state_message(
        mavlink.MAV_VTOL_STATE_UNDEFINED, _landed_state(v)
    )


def home_position(home: GeoOrigin, boot_ms: int) -> Any:
    return mavlink.MAVLink_home_position_message(
        int(round(home.lat_deg * 1e7)),
        int(round(home.lon_deg * 1e7)),
        int(round(home.alt_m * 1000.0)),
        0.0,
        0.0,
        0.0,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
        boot_ms * 1000,
    )


def gps_raw_int(v: Vehicle, home: GeoOrigin, boot_ms: int) -> Any:
    """GPS_RAW_INT with the estimate and, as h_acc (mm), the 1-sigma the vehicle simulates."""
    lat, lon, alt = home.to_global(*map(float, v.est_pos_ned_m))
    speed_cm_s = int(min(65534, round(float(np.linalg.norm(v.vel_ned_m_s[:2])) * 100.0)))
    return mavlink.MAVLink_gps_raw_int_message(
        boot_ms * 1000,
        mavlink.GPS_FIX_TYPE_3D_FIX,
        int(round(lat * 1e7)),
        int(round(lon * 1e7)),
        int(round(alt * 1000.0)),
        80,
        120,
        speed_cm_s,
        65535,
        12,
        h_acc=int(round(v.pos_sigma_m * 1000.0)),
    )


def autopilot_version(vehicle_id: int) -> Any:
    return mavlink.MAVLink_autopilot_version_message(
        CAPABILITIES, PX4_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x0C0E7000 + vehicle_id
    )


def adsb_vehicle(e: TrafficEntry, now_s: float) -> Any:
    """Echo a held traffic report, as PX4's ADSB_VEHICLE stream does (tslc = its age)."""
    flags = ADSB_FLAGS_VALID_COORDS | ADSB_FLAGS_VALID_CALLSIGN | ADSB_FLAGS_SIMULATED
    flags |= 0 if math.isnan(e.alt_m) else ADSB_FLAGS_VALID_ALTITUDE
    flags |= 0 if math.isnan(e.heading_rad) else ADSB_FLAGS_VALID_HEADING
    flags |= ADSB_FLAGS_VALID_VELOCITY | ADSB_FLAGS_VERTICAL_VELOCITY_VALID
    heading_cdeg = (
        0 if math.isnan(e.heading_rad) else int(round(math.degrees(e.heading_rad) * 100)) % 36000
    )
    return mavlink.MAVLink_adsb_vehicle_message(
        e.icao_address,
        int(round(e.lat_deg * 1e7)),
        int(round(e.lon_deg * 1e7)),
        mavlink.ADSB_ALTITUDE_TYPE_GEOMETRIC,
        0 if math.isnan(e.alt_m) else int(round(e.alt_m * 1000)),
        heading_cdeg,
        int(min(65535, round(e.hor_speed_m_s * 100))),
        int(max(-32767, min(32767, round(e.ver_speed_m_s * 100)))),
        e.callsign.encode()[:9],
        e.emitter_type,
        int(min(255, max(0, now_s - e.received_s))),
        flags,
        0,
    )


def statustext(text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> Any:
    return mavlink.MAVLink_statustext_message(severity, text.encode("ascii", "replace")[:50])


class Scheduler:
    """Which periodic streams are due: each named stream fires at its own rate."""

    def __init__(self, rates_hz: dict[str, float]) -> None:
        self.period_s = {name: 1.0 / hz for name, hz in rates_hz.items()}
        self.next_s = dict.fromkeys(rates_hz, -math.inf)

    def due(self, now_s: float) -> list[str]:
        out = []
        for name, t in self.next_s.items():
            if now_s >= t:
                out.append(name)
                # Keep the phase, but never try to catch up a backlog.
                nxt = t + self.period_s[name]
                self.next_s[name] = nxt if nxt > now_s else now_s + self.period_s[name]
        return out
