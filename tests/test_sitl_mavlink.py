"""The emulator's MAVLink face: commands, parameters, setpoints, traffic, streams and the link.

All of them drive `Autopilot.handle` or `Emulator.tick` on injected time (the e2e tests against a
real emulator process are in test_sitl_process.py).
"""

from __future__ import annotations

import math
import random
import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from comms.geo import GeoOrigin
from comms.mavlink_udp import LinkUrl
from firmware.sitl import px4, streams
from firmware.sitl.commands import Autopilot
from firmware.sitl.config import SitlConfig
from firmware.sitl.emulator import Emulator
from firmware.sitl.px4 import Px4Mode
from firmware.sitl.traffic import TrafficStore
from firmware.sitl.vehicle import Vehicle, VehicleParams

HOME = GeoOrigin(47.3977, 8.5456, 488.0)
GCS = mavlink.MAVLink(None, srcSystem=245, srcComponent=190)


def wire(msg):
    """Round-trip a message through the wire format, as the emulator receives it."""
    buf = msg.pack(GCS)
    return mavlink.MAVLink(None).parse_buffer(buf)[0]


def long(command, *p, target=1):
    p = [*map(float, p), *[math.nan] * (7 - len(p))]
    return wire(mavlink.MAVLink_command_long_message(target, 1, command, 0, *p))


def autopilot(**kw) -> Autopilot:
    vehicle = Vehicle(params=VehicleParams(pos_gain_1_s=2.0), **kw)
    return Autopilot(vehicle, HOME, 1, TrafficStore(5.0, own_icao=1))


def ack_of(replies):
    acks = [r for r in replies if r.get_type() == "COMMAND_ACK"]
    assert len(acks) == 1, replies
    assert acks[0].target_system == 245 and acks[0].target_component == 190
    return acks[0].result


def fly(ap: Autopilot, alt_m: float = 5.0) -> float:
    assert ack_of(ap.handle(long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 0.0)) == px4.ACCEPTED
    assert (
        ack_of(
            ap.handle(long(mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 6, HOME.alt_m + alt_m), 0.0)
        )
        == px4.ACCEPTED
    )
    t = 0.0
    while ap.vehicle.mode is not Px4Mode.HOLD and t < 30.0:
        t += 0.05
        ap.vehicle.step(t)
    assert abs(ap.vehicle.alt_m - alt_m) < 0.3
    return t


@pytest.mark.parametrize(
    ("msg", "result"),
    [
        (long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), px4.ACCEPTED),
        (long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, math.nan), px4.DENIED),
        (long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 7), px4.DENIED),
        (
            long(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0),
            px4.TEMPORARILY_REJECTED,
        ),  # offboard, no setpoints
        (long(mavlink.MAV_CMD_DO_SET_MODE, 1, 42, 0), px4.DENIED),  # no such PX4 mode
        (long(mavlink.MAV_CMD_DO_SET_MODE, 0, 4, 3), px4.DENIED),  # not a custom mode
        (long(mavlink.MAV_CMD_DO_SET_MODE, math.nan, 4, 3), px4.DENIED),
        (long(mavlink.MAV_CMD_DO_SET_MODE, 1, 4, 3), px4.ACCEPTED),
        (long(mavlink.MAV_CMD_NAV_TAKEOFF), px4.TEMPORARILY_REJECTED),  # disarmed
        (
            long(mavlink.MAV_CMD_DO_REPOSITION, -1, 1, 0, math.nan, math.nan, math.nan, 500.0),
            px4.DENIED,
        ),
        (long(mavlink.MAV_CMD_DO_REPOSITION, -1, 1, 0, math.nan, 95.0, 8.0, 500.0), px4.DENIED),
        (long(mavlink.MAV_CMD_DO_MOTOR_TEST, 1, 0, 0), px4.UNSUPPORTED),
        (long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 33, 50000), px4.ACCEPTED),
        (long(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 7.5), px4.ACCEPTED),
        (long(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, -1), px4.ACCEPTED),
        (long(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, math.nan), px4.DENIED),
        (long(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 99.0), px4.DENIED),
    ],
)
def test_command_results(msg, result) -> None:
    assert ack_of(autopilot().handle(msg, 0.0)) == result


def test_commands_for_another_system_are_ignored() -> None:
    assert autopilot().handle(long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=9), 0.0) == []
    assert (
        ack_of(autopilot().handle(long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=0), 0.0))
        == px4.ACCEPTED
    )


def test_arm_with_bad_health_is_refused_with_a_reason() -> None:
    ap = autopilot(healthy=False)
    assert (
        ack_of(ap.handle(long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 0.0))
        == px4.TEMPORARILY_REJECTED
    )
    assert "Arming denied" in ap.vehicle.events[-1]
    status = streams.sys_status(ap.vehicle, healthy=False)
    assert not status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    assert not status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK


def test_disarm_in_the_air_needs_the_kill_magic() -> None:
    ap = autopilot()
    fly(ap)
    assert (
        ack_of(ap.handle(long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0), 0.0))
        == px4.TEMPORARILY_REJECTED
    )
    assert ap.vehicle.armed
    assert (
        ack_of(ap.handle(long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, px4.KILL_MAGIC), 0.0))
        == px4.ACCEPTED
    )
    assert not ap.vehicle.armed and ap.vehicle.falling


def test_reposition_command_int_global_and_relative_frames() -> None:
    ap = autopilot()
    t = fly(ap)
    lat, lon, alt = HOME.to_global(12.0, -7.0, -6.0)
    msg = wire(
        mavlink.MAVLink_command_int_message(
            1,
            1,
            mavlink.MAV_FRAME_GLOBAL,
            mavlink.MAV_CMD_DO_REPOSITION,
            0,
            0,
            -1,
            1,
            0,
            math.nan,
            round(lat * 1e7),
            round(lon * 1e7),
            alt,
        )
    )
    assert ack_of(ap.handle(msg, t)) == px4.ACCEPTED
    assert np.allclose(ap.vehicle.target_ned_m, [12.0, -7.0, -6.0], atol=0.02)
    msg = wire(
        mavlink.MAVLink_command_int_message(
            1,
            1,
            mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            mavlink.MAV_CMD_DO_REPOSITION,
            0,
            0,
            -1,
            1,
            0,
            math.nan,
            round(lat * 1e7),
            round(lon * 1e7),
            9.0,
        )
    )
    assert ack_of(ap.handle(msg, t)) == px4.ACCEPTED
    assert ap.vehicle.target_ned_m[2] == pytest.approx(-9.0, abs=0.01)
    msg = wire(
        mavlink.MAVLink_command_int_message(
            1,
            1,
            mavlink.MAV_FRAME_GLOBAL,
            mavlink.MAV_CMD_DO_REPOSITION,
            0,
            0,
            -1,
            1,
            0,
            math.nan,
            1_000_000_000,
            0,
            alt,
        )
    )
    assert ack_of(ap.handle(msg, t)) == px4.DENIED  # latitude 100 degrees
    msg = wire(
        mavlink.MAVLink_command_int_message(
            1,
            1,
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_CMD_DO_REPOSITION,
            0,
            0,
            -1,
            1,
            0,
            math.nan,
            0,
            0,
            alt,
        )
    )
    assert ack_of(ap.handle(msg, t)) == px4.UNSUPPORTED


def test_params_read_set_and_refuse() -> None:
    ap = autopilot()
    read = wire(mavlink.MAVLink_param_request_read_message(1, 1, b"MIS_TAKEOFF_ALT", -1))
    (value,) = ap.handle(read, 0.0)
    assert value.param_id == "MIS_TAKEOFF_ALT" and value.param_value == pytest.approx(2.5)
    (value,) = ap.handle(
        wire(mavlink.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", 7.5, 9)), 0.0
    )
    assert value.param_value == pytest.approx(7.5) and ap.vehicle.params.takeoff_alt_m == 7.5
    for bad in (math.nan, math.inf, -3.0, 1e6):
        (value,) = ap.handle(
            wire(mavlink.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", bad, 9)), 0.0
        )
        assert value.param_value == pytest.approx(7.5)  # the old value comes back: refused
    assert (
        ap.handle(wire(mavlink.MAVLink_param_set_message(1, 1, b"NO_SUCH_PARAM", 1.0, 9)), 0.0)
        == []
    )
    listed = ap.handle(wire(mavlink.MAVLink_param_request_list_message(1, 1)), 0.0)
    assert {p.param_id for p in listed} >= {"MIS_TAKEOFF_ALT", "COM_OF_LOSS_T"}
    assert sorted(p.param_index for p in listed) == list(range(len(listed)))


def test_the_onboard_modules_separation_is_read_only_and_only_with_the_module() -> None:
    """CVY_SEP_M (the covey PX4 module's separation) is answered when the policy runs onboard,
    so a relay can read it; setting it is refused (the old value comes back, with a reason);
    an autopilot without the module stays silent about it, as PX4 does."""
    plain = autopilot()
    read = wire(mavlink.MAVLink_param_request_read_message(1, 1, b"CVY_SEP_M", -1))
    assert plain.handle(read, 0.0) == []
    vehicle = Vehicle(params=VehicleParams(pos_gain_1_s=2.0))
    ap = Autopilot(vehicle, HOME, 1, TrafficStore(5.0, own_icao=1), {"CVY_SEP_M": 4.0})
    (value,) = ap.handle(read, 0.0)
    assert value.param_id == "CVY_SEP_M" and value.param_value == pytest.approx(4.0)
    (value,) = ap.handle(wire(mavlink.MAVLink_param_set_message(1, 1, b"CVY_SEP_M", 9.0, 9)), 0.0)
    assert value.param_value == pytest.approx(4.0)
    assert any("CVY_SEP_M is read-only" in e for e in vehicle.events)
    listed = ap.handle(wire(mavlink.MAVLink_param_request_list_message(1, 1)), 0.0)
    assert "CVY_SEP_M" in {p.param_id for p in listed}
    assert sorted(p.param_index for p in listed) == list(range(len(listed)))
    assert {p.param_count for p in listed} == {len(listed)}


def test_request_message_answers_autopilot_version_and_home() -> None:
    ap = autopilot()
    replies = ap.handle(
        long(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION), 0.0
    )
    assert replies[0].get_type() == "AUTOPILOT_VERSION" and ack_of(replies) == px4.ACCEPTED
    assert replies[0].capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    replies = ap.handle(
        long(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION), 0.0
    )
    assert replies[0].get_type() == "HOME_POSITION" and replies[0].latitude == round(
        HOME.lat_deg * 1e7
    )
    assert ack_of(ap.handle(long(mavlink.MAV_CMD_REQUEST_MESSAGE, 12345), 0.0)) == px4.UNSUPPORTED


def setpoint(frame=mavlink.MAV_FRAME_LOCAL_NED, vel=(1.0, 0.0, 0.0), mask=0b1001_1100_0111):
    return wire(
        mavlink.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, frame, mask, 0, 0, 0, *vel, 0, 0, 0, 0.5, 0
        )
    )


def test_offboard_setpoints_local_and_body_frames() -> None:
    ap = autopilot()
    t = fly(ap)
    ap.vehicle.heading_rad = math.pi / 2
    ap.handle(setpoint(frame=mavlink.MAV_FRAME_BODY_NED, vel=(2.0, 0.0, 0.0)), t)
    assert np.allclose(ap.vehicle.sp_vel_ned_m_s, [0.0, 2.0, 0.0], atol=1e-9)  # body forward = east
    ap.handle(setpoint(vel=(math.nan, 0.0, 0.0)), t)
    assert np.allclose(ap.vehicle.sp_vel_ned_m_s, [0.0, 2.0, 0.0], atol=1e-9)  # NaN ignored
    ap.handle(setpoint(vel=(1.0, -1.0, 0.0)), t)
    assert ap.vehicle.sp_yaw_rad == pytest.approx(0.5)
    assert ack_of(ap.handle(long(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0), t)) == px4.ACCEPTED


def adsb(
    icao=7, lat=None, lon=None, flags=0b1_1101_1111, alt_mm=493_000, heading_cdeg=9000, hor_cm_s=150
):
    lat = HOME.lat_deg + 1e-4 if lat is None else lat
    lon = HOME.lon_deg if lon is None else lon
    return wire(
        mavlink.MAVLink_adsb_vehicle_message(
            icao,
            round(lat * 1e7),
            round(lon * 1e7),
            1,
            alt_mm,
            heading_cdeg,
            hor_cm_s,
            -20,
            b"COVEY7",
            14,
            0,
            flags,
            0,
        )
    )


def test_traffic_is_stored_per_icao_and_ages_out() -> None:
    ap = autopilot()
    ap.handle(adsb(icao=7), 0.0)
    ap.handle(adsb(icao=7, heading_cdeg=18000), 0.5)  # newer report replaces the older one
    ap.handle(adsb(icao=8), 1.0)
    ap.handle(adsb(icao=9, flags=0), 1.0)  # no valid coordinates: dropped
    ap.handle(adsb(icao=1), 1.0)  # our own id: not a neighbour
    ap.handle(adsb(icao=10, lat=95.0), 1.0)
    held = ap.traffic.fresh(2.0)
    assert [e.icao_address for e in held] == [7, 8]
    assert held[0].heading_rad == pytest.approx(math.pi) and held[0].received_s == 0.5
    assert held[0].hor_speed_m_s == pytest.approx(1.5) and held[0].alt_m == pytest.approx(493.0)
    assert [e.icao_address for e in ap.traffic.fresh(5.8)] == [8]
    echo = streams.adsb_vehicle(held[0], now_s=3.0)
    assert echo.ICAO_address == 7 and echo.tslc == 2 and echo.heading == 18000


def test_streams_look_like_px4() -> None:
    v = Vehicle()
    v.pos_ned_m[:] = [10.0, -5.0, -3.0]
    v.vel_ned_m_s[:] = [1.0, 2.0, -0.5]
    v.heading_rad = -math.pi / 2
    hb = streams.heartbeat(v)
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.custom_mode == Px4Mode.HOLD.custom_mode
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    gpi = streams.global_position_int(v, HOME, 1234)
    assert HOME.to_local(gpi.lat * 1e-7, gpi.lon * 1e-7, gpi.alt * 1e-3) == pytest.approx(
        (10.0, -5.0, -3.0), abs=0.02
    )
    assert (gpi.relative_alt, gpi.vx, gpi.vy, gpi.vz, gpi.hdg) == (3000, 100, 200, -50, 27000)
    st = streams.sys_status(v, healthy=True)
    assert st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    assert st.onboard_control_sensors_present & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    assert streams.extended_sys_state(v).landed_state == mavlink.MAV_LANDED_STATE_IN_AIR


def test_scheduler_fires_at_each_rate_without_backlog() -> None:
    s = streams.Scheduler({"fast": 4.0, "slow": 1.0})
    fired = {"fast": 0, "slow": 0}
    for k in range(193):  # 3 s at 64 Hz (binary fractions: exact)
        for name in s.due(k / 64):
            fired[name] += 1
    assert fired == {"fast": 13, "slow": 4}
    assert s.due(100.0) == ["fast", "slow"] and s.due(100.0) == []


def test_handle_never_raises_on_random_input() -> None:
    rng = random.Random(7)
    ap = autopilot()
    fly(ap)
    for _ in range(2000):
        params = [
            rng.choice(
                [math.nan, math.inf, -math.inf, 0.0, 1.0, 21196.0, 1e30, rng.uniform(-1e3, 1e3)]
            )
            for _ in range(7)
        ]
        cmd = rng.choice([400, 176, 22, 21, 20, 192, 185, 511, 512, 520, 410, rng.randrange(65536)])
        if rng.random() < 0.5:
            msg = wire(mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *params))
        else:
            msg = wire(
                mavlink.MAVLink_command_int_message(
                    1,
                    1,
                    rng.randrange(20),
                    cmd,
                    0,
                    0,
                    *params[:4],
                    rng.randrange(-(2**31), 2**31),
                    rng.randrange(-(2**31), 2**31),
                    params[6],
                )
            )
        ap.handle(msg, ap.vehicle.now_s)
        ap.vehicle.step(ap.vehicle.now_s + 0.01)
        assert np.all(np.isfinite(ap.vehicle.pos_ned_m)) and np.all(
            np.isfinite(ap.vehicle.vel_ned_m_s)
        )


@pytest.mark.parametrize(
    "url", ["udp:1.2.3.4:5", "udpout:host", "udpin::14540", "udpout:127.0.0.1:0", "tcp:x:1"]
)
def test_bad_link_urls_are_refused(url) -> None:
    with pytest.raises(ValueError, match="udp"):
        LinkUrl.parse(url)


def test_emulator_tick_on_a_fake_clock_over_real_udp() -> None:
    """The whole stack in-process: garbage and commands in on a real socket, time injected."""
    cfg = SitlConfig(vehicle_id=4, links=("udpin:127.0.0.1:0",), home=HOME)
    with Emulator(cfg, now_s=100.0) as emu, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        addr = ("127.0.0.1", emu.links[0].local_port)
        gcs.sendto(b"\xfd\xff" + bytes(300), addr)  # a header that claims more than is there
        gcs.sendto(bytes(range(256)), addr)
        arm = mavlink.MAVLink_command_long_message(
            4, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
        )
        gcs.sendto(arm.pack(GCS), addr)
        gcs.settimeout(0.05)
        got: list = []
        deadline = time.monotonic() + 10.0  # wall time only bounds the wait for the datagrams
        while not any(m.get_type() == "COMMAND_ACK" for m in got):
            assert time.monotonic() < deadline, "no COMMAND_ACK from the emulator"
            emu.tick(100.0)  # the emulator's clock stands still: it is the injected one
            try:
                got += mavlink.MAVLink(None).parse_buffer(gcs.recv(65535)) or []
            except TimeoutError:
                continue
        ack = next(m for m in got if m.get_type() == "COMMAND_ACK")
        assert ack.result == px4.ACCEPTED and emu.vehicle.armed
        assert emu.links[0].bad_packets >= 2
        emu.tick(101.0)
        assert emu.vehicle.now_s == 101.0
