"""Fuzz the MAVLink inputs: a running `python -m firmware.sitl` and the relay backend.

Three kinds of datagrams, seeded:
- garbage: random bytes, MAVLink magic bytes followed by junk, truncated headers;
- mutated frames: valid frames with flipped/overwritten bytes (the CRC then fails, mostly);
- well-formed hostile frames: every message the receiver handles, with random field values
  (NaN, inf, extremes, random command ids) and a CORRECT checksum, so they reach the handlers.
The emulator must stay up and still answer a command; the relay's receive thread must stay up
and its telemetry must stay finite.
"""

from __future__ import annotations

import math
import random
import socket
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

pytestmark = [pytest.mark.e2e]

SEED = 77
FLOATS = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1e38, -1e38, 3.4e38, 1e-45, 1.0, -1.0]
COMMAND_IDS = [400, 22, 21, 20, 176, 192, 511, 512, 246, 183, 178, 300, 0, 65535]
INT_RANGES = {
    "int8_t": (-128, 127),
    "uint8_t": (0, 255),
    "int16_t": (-32768, 32767),
    "uint16_t": (0, 65535),
    "int32_t": (-(2**31), 2**31 - 1),
    "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1),
    "uint64_t": (0, 2**64 - 1),
}

SITL_INPUTS = [
    mavlink.MAVLink_command_long_message,
    mavlink.MAVLink_command_int_message,
    mavlink.MAVLink_set_position_target_local_ned_message,
    mavlink.MAVLink_adsb_vehicle_message,
    mavlink.MAVLink_timesync_message,
    mavlink.MAVLink_param_request_list_message,
    mavlink.MAVLink_param_request_read_message,
    mavlink.MAVLink_param_set_message,
    mavlink.MAVLink_set_mode_message,
    mavlink.MAVLink_heartbeat_message,
]
RELAY_INPUTS = [
    mavlink.MAVLink_global_position_int_message,
    mavlink.MAVLink_local_position_ned_message,
    mavlink.MAVLink_attitude_message,
    mavlink.MAVLink_extended_sys_state_message,
    mavlink.MAVLink_sys_status_message,
    mavlink.MAVLink_command_ack_message,
    mavlink.MAVLink_statustext_message,
    mavlink.MAVLink_param_value_message,
    mavlink.MAVLink_heartbeat_message,
]


def random_value(ftype: str, length: int, name: str, rng: random.Random, target_id: int):
    if length and ftype != "char":
        return [random_value(ftype, 0, name, rng, target_id) for _ in range(length)]
    if ftype == "char":
        return rng.randbytes(rng.randrange(0, (length or 1) + 1))
    if ftype in ("float", "double"):
        return rng.choice(FLOATS) if rng.random() < 0.5 else rng.uniform(-1e7, 1e7)
    lo, hi = INT_RANGES[ftype]
    if name == "target_system" and rng.random() < 0.8:
        return target_id
    if name == "command" and rng.random() < 0.8:
        return rng.choice(COMMAND_IDS)
    return rng.choice([lo, hi, 0, 1]) if rng.random() < 0.4 else rng.randint(lo, hi)


def hostile_frame(cls, mav: mavlink.MAVLink, rng: random.Random, target_id: int) -> bytes:
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    args = [
        random_value(t, lengths[n], n, rng, target_id)
        for n, t in zip(cls.fieldnames, cls.fieldtypes, strict=True)
    ]
    return cls(*args).pack(mav)


def garbage(rng: random.Random) -> bytes:
    kind = rng.randrange(3)
    if kind == 0:
        return rng.randbytes(rng.randrange(0, 400))
    if kind == 1:
        return bytes([rng.choice([0xFD, 0xFE])]) + rng.randbytes(rng.randrange(0, 300))
    return b"\xfd" + bytes([rng.randrange(256)]) + rng.randbytes(rng.randrange(0, 9))


def mutated(frame: bytes, rng: random.Random) -> bytes:
    b = bytearray(frame)
    for _ in range(rng.randint(1, 3)):
        i = rng.randrange(len(b))
        b[i] = rng.randrange(256) if rng.random() < 0.5 else b[i] ^ (1 << rng.randrange(8))
    return bytes(b[: rng.randrange(1, len(b) + 1)] if rng.random() < 0.2 else b)


def datagrams(rng: random.Random, inputs, n: int, mav: mavlink.MAVLink, target_id: int):
    counts = {"garbage": 0, "mutated": 0, "hostile": 0}
    for i in range(n):
        r = i % 4
        if r == 0:
            counts["garbage"] += 1
            yield garbage(rng)
        elif r == 1:
            counts["mutated"] += 1
            yield mutated(hostile_frame(rng.choice(inputs), mav, rng, target_id), rng)
        else:
            counts["hostile"] += 1
            yield hostile_frame(rng.choice(inputs), mav, rng, target_id)
    print(f"sent {n} datagrams: {counts}")


def blast(sock: socket.socket, addr, frames, per_burst: int = 200, pause_s: float = 0.01) -> int:
    """Send in bursts so that the receiver's socket buffer, not the sender, decides the pace."""
    sent = 0
    for i, f in enumerate(frames):
        sock.sendto(f, addr)
        sent += 1
        if i % per_burst == per_burst - 1:
            time.sleep(pause_s)
    return sent


N_SITL = 8000
N_RELAY = 8000


def test_emulator_survives_hostile_mavlink_and_still_answers() -> None:
    from firmware.sitl import px4
    from firmware.sitl.process import SitlProcess, free_udp_port

    port = free_udp_port()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.2)
    mav = mavlink.MAVLink(None, srcSystem=245, srcComponent=190)
    addr = ("127.0.0.1", port)

    def ask_arm_disarm() -> int | None:
        """Send DISARM until its COMMAND_ACK comes; the result code, or None."""
        end = time.monotonic() + 10
        while time.monotonic() < end:
            sock.sendto(
                mavlink.MAVLink_command_long_message(1, 1, 400, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav),
                addr,
            )
            t = time.monotonic() + 0.5
            while time.monotonic() < t:
                try:
                    data = sock.recv(65535)
                except TimeoutError:
                    continue
                for m in mavlink.MAVLink(None).parse_buffer(data) or []:
                    if m.get_type() == "COMMAND_ACK" and m.command == 400:
                        return m.result
        return None

    with SitlProcess(["--id", "1", "--listen", f"127.0.0.1:{port}"]) as proc:
        assert ask_arm_disarm() is not None, (
            "the emulator does not answer before fuzzing: " + proc.output()[-2000:]
        )
        rng = random.Random(SEED)
        blast(sock, addr, datagrams(rng, SITL_INPUTS, N_SITL, mav, 1))
        assert proc.alive(), proc.output()[-3000:]
        result = ask_arm_disarm()
        assert result in (px4.ACCEPTED, px4.TEMPORARILY_REJECTED, px4.DENIED), proc.output()[-3000:]
        assert proc.alive()
        tail = proc.output()
    sock.close()
    assert "Traceback" not in tail, tail[-3000:]


@pytest.fixture(scope="module")
def relay_fuzz() -> dict:
    """Blast the relay backend once; both relay tests read the outcome."""
    from agent.backends.relay import RelayBackend
    from comms.geo import GeoOrigin
    from firmware.sitl.process import free_udp_port

    port = free_udp_port()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    px4_mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    addr = ("127.0.0.1", port)
    hb = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3, 3
    )
    origin = GeoOrigin()
    # A sane position fix near the origin before each block, so the hostile frames that follow
    # (velocity, attitude, far-away fixes) are what the snapshot can show.
    fix = mavlink.MAVLink_global_position_int_message(
        0,
        round(origin.lat_deg * 1e7),
        round(origin.lon_deg * 1e7),
        round(origin.alt_m * 1e3),
        0,
        0,
        0,
        0,
        65535,
    )
    out = {"bad_telemetry": [], "snapshots": 0}
    with RelayBackend(f"udpin:127.0.0.1:{port}", origin=origin) as relay:
        sock.sendto(hb.pack(px4_mav), addr)
        sock.sendto(fix.pack(px4_mav), addr)
        out["connected"] = relay.wait_connected(5.0)
        rng = random.Random(SEED + 1)
        for i, frame in enumerate(datagrams(rng, RELAY_INPUTS, N_RELAY, px4_mav, 245)):
            sock.sendto(frame, addr)
            if i % 200 == 199:
                sock.sendto(hb.pack(px4_mav), addr)
                sock.sendto(fix.pack(px4_mav), addr)
                time.sleep(0.01)
                tel = relay.telemetry()
                if tel is not None:
                    out["snapshots"] += 1
                    values = [*tel.pos_ned_m, *tel.vel_ned_m_s, tel.heading_rad]
                    battery_ok = (
                        math.isnan(tel.battery_pct) or 0 <= tel.battery_pct <= 100
                    )  # NaN: unknown
                    if not (all(math.isfinite(v) for v in values) and battery_ok):
                        out["bad_telemetry"].append(values)
        time.sleep(0.2)
        out["thread_alive"] = relay._thread.is_alive()
        out["link_ok"] = relay.link_ok
        out["rejected"] = relay.rejected_messages
    sock.close()
    print(
        f"relay: non-finite telemetry in {len(out['bad_telemetry'])} of {out['snapshots']} snapshots"
    )
    return out


def test_relay_backend_survives_hostile_mavlink(relay_fuzz) -> None:
    assert relay_fuzz["connected"]
    assert relay_fuzz["thread_alive"], "the relay's receive thread died"
    assert relay_fuzz["link_ok"]


def test_relay_backend_keeps_telemetry_finite(relay_fuzz) -> None:
    assert relay_fuzz["snapshots"] > 0
    assert relay_fuzz["rejected"] > 0, "the fuzzer never reached the plausibility check"
    assert not relay_fuzz["bad_telemetry"], f"e.g. {relay_fuzz['bad_telemetry'][0]}"
