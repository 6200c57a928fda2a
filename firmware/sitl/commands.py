"""PX4's MAVLink command, parameter and setpoint handling, mapped onto the pure vehicle.

`Autopilot.handle(msg, now_s)` takes one received message and returns the replies (COMMAND_ACK,
PARAM_VALUE, requested messages). Invalid input is refused with a reason, never raised.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from comms.geo import GeoOrigin
from firmware.sitl import px4, streams
from firmware.sitl.fence import MISSION_MESSAGES, FenceStore
from firmware.sitl.px4 import OK, Px4Mode, Px4Result
from firmware.sitl.traffic import TrafficStore, entry_from_adsb
from firmware.sitl.vehicle import Vehicle

log = logging.getLogger(__name__)

INT32_MAX = 2**31 - 1
"""COMMAND_INT x/y value that means "unset": keep the current position."""

PARAMS: dict[str, tuple[str, float, float]] = {
    "MIS_TAKEOFF_ALT": ("takeoff_alt_m", 0.5, 120.0),
    "MPC_XY_CRUISE": ("cruise_speed_m_s", 0.5, 20.0),
    "MPC_TKO_SPEED": ("takeoff_speed_m_s", 0.3, 10.0),
    "MPC_LAND_SPEED": ("land_speed_m_s", 0.3, 5.0),
    "RTL_RETURN_ALT": ("rtl_alt_m", 2.0, 120.0),
    "COM_OF_LOSS_T": ("offboard_loss_s", 0.1, 60.0),
    "NAV_ACC_RAD": ("arrive_radius_m", 0.05, 20.0),
}
"""PX4 parameter -> (VehicleParams field, min, max). All REAL32, like PX4's."""

# Position targets: bits set in type_mask mean "ignore this field".
POS_IGNORE = 0b111
VEL_IGNORE = 0b111 << 3
YAW_IGNORE = 1 << 10


class Autopilot:
    """The MAVLink face of one vehicle: commands, parameters, setpoints, traffic."""

    def __init__(
        self,
        vehicle: Vehicle,
        home: GeoOrigin,
        system_id: int,
        traffic: TrafficStore,
        onboard_params: dict[str, float] | None = None,
    ) -> None:
        self.vehicle, self.home, self.system_id, self.traffic = vehicle, home, system_id, traffic
        self.onboard_params = dict(onboard_params or {})
        """The covey PX4 module's parameters when the policy runs onboard (CVY_SEP_M: the
        separation its filter keeps), read-only here: `covey sitl --separation-m` sets them."""
        self.boot_ms = 0
        self.fence = FenceStore(system_id)
        """The geofence uploaded over the mission protocol (firmware/sitl/fence.py)."""

    def _for_us(self, msg: Any) -> bool:
        return msg.target_system in (0, self.system_id) and msg.target_component in (0, 1)

    def handle(self, msg: Any, now_s: float) -> list[Any]:
        kind = msg.get_type()
        if kind == "COMMAND_LONG" and self._for_us(msg):
            params = [
                msg.param1,
                msg.param2,
                msg.param3,
                msg.param4,
                msg.param5,
                msg.param6,
                msg.param7,
            ]
            return self._command(msg, msg.command, params, None, now_s)
        if kind == "COMMAND_INT" and self._for_us(msg):
            params = [
                msg.param1,
                msg.param2,
                msg.param3,
                msg.param4,
                float(msg.x),
                float(msg.y),
                msg.z,
            ]
            return self._command(msg, msg.command, params, msg.frame, now_s)
        if kind == "SET_POSITION_TARGET_LOCAL_NED" and self._for_us(msg):
            self._setpoint(msg, now_s)
        elif kind in MISSION_MESSAGES and self._for_us(msg):
            return self.fence.handle(msg, now_s, (msg.get_srcSystem(), msg.get_srcComponent()))
        elif kind == "ADSB_VEHICLE":
            entry = entry_from_adsb(msg, now_s)
            if entry is not None:
                self.traffic.add(entry)
        elif kind in ("PARAM_REQUEST_READ", "PARAM_SET", "PARAM_REQUEST_LIST") and self._for_us(
            msg
        ):
            return self._param(msg)
        elif kind == "TIMESYNC" and msg.tc1 == 0:
            return [mavlink.MAVLink_timesync_message(int(now_s * 1e9), msg.ts1)]
        return []

    # ---- commands ------------------------------------------------------------------------------

    def _command(
        self, msg: Any, command: int, p: list[float], frame: int | None, now_s: float
    ) -> list[Any]:
        extra: list[Any] = []
        try:
            outcome = self._dispatch(command, p, frame, now_s, extra)
        except (ValueError, OverflowError) as exc:  # e.g. int(nan): a malformed parameter
            outcome = Px4Result(px4.DENIED, f"Command {command} denied: {exc}")
            self.vehicle.events.append(outcome.reason)
        log.debug("command %d %s -> result %d %s", command, p, outcome.result, outcome.reason)
        ack = mavlink.MAVLink_command_ack_message(
            command, outcome.result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        return [*extra, ack]

    def _dispatch(
        self, command: int, p: list[float], frame: int | None, now_s: float, extra: list[Any]
    ) -> Px4Result:
        v = self.vehicle
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                return v.arm(now_s)
            if p[0] == 0.0:
                return v.disarm(now_s, force=p[1] == px4.KILL_MAGIC)
            raise ValueError(f"param1 must be 0 or 1, got {p[0]}")
        if command == mavlink.MAV_CMD_DO_FLIGHTTERMINATION:
            return v.kill(now_s) if p[0] > 0.5 else Px4Result(px4.ACCEPTED)
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            if not int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                raise ValueError("only custom (PX4) modes are supported")
            mode = Px4Mode.from_main_sub(int(p[1]), int(p[2]))
            if mode is None:
                raise ValueError(f"no PX4 mode main={p[1]} sub={p[2]}")
            return v.set_mode(mode, now_s)
        if command == mavlink.MAV_CMD_NAV_TAKEOFF:
            # param7 is AMSL; NaN means MIS_TAKEOFF_ALT (what MAVSDK sends).
            return v.takeoff(p[6] - self.home.alt_m if not math.isnan(p[6]) else math.nan, now_s)
        if command == mavlink.MAV_CMD_NAV_LAND:
            return v.land(now_s)
        if command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return v.set_mode(Px4Mode.RTL, now_s)
        if command == mavlink.MAV_CMD_DO_REPOSITION:
            return self._reposition(p, frame, now_s)
        if command in (
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
            mavlink.MAV_CMD_GET_HOME_POSITION,
        ):
            msg_id = {
                mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                mavlink.MAV_CMD_GET_HOME_POSITION: mavlink.MAVLINK_MSG_ID_HOME_POSITION,
            }.get(command, int(p[0]))
            reply = self._requested(msg_id, now_s)
            if reply is None:
                return Px4Result(px4.UNSUPPORTED, f"message {msg_id} not available")
            extra.append(reply)
            return OK
        if command == mavlink.MAV_CMD_DO_CHANGE_SPEED:
            return self._change_speed(p[1])
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return Px4Result(
                px4.ACCEPTED
            )  # streams run at fixed rates; accepted like PX4 so MAVSDK is happy
        return Px4Result(px4.UNSUPPORTED)

    def _reposition(self, p: list[float], frame: int | None, now_s: float) -> Px4Result:
        lat, lon, alt = p[4], p[5], p[6]
        v = self.vehicle
        if frame is not None:  # COMMAND_INT: degE7 integers; INT32_MAX is "unset"
            if lat == INT32_MAX or lon == INT32_MAX:
                cur = self.home.to_global(*map(float, v.pos_ned_m))
                lat, lon = cur[0] * 1e7, cur[1] * 1e7
            lat, lon = lat * 1e-7, lon * 1e-7
            if frame in (
                mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            ):
                alt += self.home.alt_m
            elif frame not in (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT):
                return self._refused(
                    px4.UNSUPPORTED, f"Reposition denied: frame {frame} not supported"
                )
        if not (math.isfinite(lat) and math.isfinite(lon)):
            return self._refused(px4.DENIED, "Reposition denied: latitude/longitude not finite")
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return self._refused(px4.DENIED, f"Reposition denied: lat {lat} lon {lon} out of range")
        breach = self.fence.refusal(lat, lon, self.home.lat_deg)
        if breach:
            return self._refused(px4.DENIED, f"Reposition denied: target {breach}")
        n, e, d = self.home.to_local(lat, lon, alt if math.isfinite(alt) else self.home.alt_m)
        return v.reposition(np.array([n, e, d if math.isfinite(alt) else math.nan]), now_s)

    def _change_speed(self, speed_m_s: float) -> Px4Result:
        """DO_CHANGE_SPEED param2: the cruise speed of goto flight; -1 keeps it (PX4)."""
        if speed_m_s == -1.0:
            return OK
        lo, hi = 0.5, self.vehicle.params.max_speed_m_s
        if not (math.isfinite(speed_m_s) and lo <= speed_m_s <= hi):
            return self._refused(
                px4.DENIED, f"Speed change denied: {speed_m_s} m/s outside [{lo}, {hi}]"
            )
        self.vehicle.params = dataclasses.replace(self.vehicle.params, cruise_speed_m_s=speed_m_s)
        return OK

    def _refused(self, result: int, reason: str) -> Px4Result:
        self.vehicle.events.append(reason)
        return Px4Result(result, reason)

    def _requested(self, msg_id: int, now_s: float) -> Any | None:
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return streams.autopilot_version(self.system_id)
        if msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            return streams.home_position(self.home, self.boot_ms)
        if msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return streams.extended_sys_state(self.vehicle)
        return None

    # ---- offboard setpoints --------------------------------------------------------------------

    def _setpoint(self, msg: Any, now_s: float) -> None:
        mask, v = msg.type_mask, self.vehicle
        pos = None if mask & POS_IGNORE else np.array([msg.x, msg.y, msg.z])
        vel = None if mask & VEL_IGNORE else np.array([msg.vx, msg.vy, msg.vz])
        if msg.coordinate_frame == mavlink.MAV_FRAME_BODY_NED and vel is not None:
            c, s = math.cos(v.heading_rad), math.sin(v.heading_rad)
            vel = np.array([c * vel[0] - s * vel[1], s * vel[0] + c * vel[1], vel[2]])
            pos = None
        elif msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
            return
        yaw = None if mask & YAW_IGNORE else float(msg.yaw)
        v.offboard_setpoint(now_s, vel_ned_m_s=vel, pos_ned_m=pos, yaw_rad=yaw)

    # ---- parameters ----------------------------------------------------------------------------

    def _param_value(self, name: str) -> Any:
        names = [*PARAMS, *self.onboard_params]
        if name in PARAMS:
            value = float(getattr(self.vehicle.params, PARAMS[name][0]))
        else:
            value = float(self.onboard_params[name])
        return mavlink.MAVLink_param_value_message(
            name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, len(names), names.index(name)
        )

    def _param(self, msg: Any) -> list[Any]:
        kind, names = msg.get_type(), [*PARAMS, *self.onboard_params]
        if kind == "PARAM_REQUEST_LIST":
            return [self._param_value(n) for n in names]
        name = (
            msg.param_id
            if isinstance(msg.param_id, str)
            else msg.param_id.decode("ascii", "replace")
        )
        name = name.rstrip("\x00")
        if (
            kind == "PARAM_REQUEST_READ"
            and name not in PARAMS
            and 0 <= msg.param_index < len(names)
        ):
            name = names[msg.param_index]
        if name in self.onboard_params:
            if kind == "PARAM_SET":  # echo the value kept: the setter sees it was not taken
                self.vehicle.events.append(
                    f"Parameter {name} is read-only in the emulator (covey sitl --separation-m)"
                )
            return [self._param_value(name)]
        if name not in PARAMS:
            return []  # PX4 stays silent about unknown parameters
        if kind == "PARAM_SET":
            field, lo, hi = PARAMS[name]
            value = float(msg.param_value)
            if math.isfinite(value) and lo <= value <= hi:
                self.vehicle.params = dataclasses.replace(self.vehicle.params, **{field: value})
            else:  # echo the old value: the setter sees it was not taken
                self.vehicle.events.append(
                    f"Parameter {name} = {value} rejected: outside [{lo}, {hi}]"
                )
        return [self._param_value(name)]
