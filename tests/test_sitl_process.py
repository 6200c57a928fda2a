"""A real emulator process over UDP on 127.0.0.1: PX4's refusals on the wire, garbage input, and
both link modes. A raw pymavlink ground station stands in for MAVSDK, so the emulator's own
answers are what is checked (MAVSDK refuses some things on its own side first).
"""

from __future__ import annotations

import math
import random
import socket
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware.sitl import px4
from firmware.sitl.process import SitlProcess, free_udp_port

GCS = mavlink.MAVLink(None, srcSystem=245, srcComponent=190)


class RawGcs:
    """A pymavlink ground station on a UDP socket that the emulator sends to."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.peer = None
        self.mav = mavlink.MAVLink(None, srcSystem=245, srcComponent=190)

    def recv(self, kind: str, timeout_s: float = 5.0, pred=lambda m: True):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                data, self.peer = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            for m in mavlink.MAVLink(None).parse_buffer(data) or []:
                if m.get_type() == kind and pred(m):
                    return m
        raise AssertionError(f"no {kind} within {timeout_s} s")

    def send(self, msg) -> None:
        self.sock.sendto(msg.pack(self.mav), self.peer)

    def command(self, command: int, *p: float, attempts: int = 3) -> int:
        """MAVLink's command protocol: resend (confirmation + 1) until an ack comes."""
        p = [*map(float, p), *[math.nan] * (7 - len(p))]
        for confirmation in range(attempts):
            self.send(mavlink.MAVLink_command_long_message(1, 1, command, confirmation, *p))
            try:
                return self.recv(
                    "COMMAND_ACK", timeout_s=1.5, pred=lambda m: m.command == command
                ).result
            except AssertionError:
                continue
        raise AssertionError(f"no COMMAND_ACK for command {command} after {attempts} tries")

    def close(self) -> None:
        self.sock.close()


FAST_ARGS = [
    "--takeoff-speed-m-s",
    "5",
    "--pos-gain-1-s",
    "3",
    "--accel-m-s2",
    "15",
    "--land-speed-m-s",
    "4",
    "--disarm-after-land-s",
    "0.3",
]


@pytest.fixture
def raw_sitl():
    gcs = RawGcs()
    with SitlProcess(
        ["--id", "1", "--connect", f"udpout:127.0.0.1:{gcs.port}", *FAST_ARGS]
    ) as proc:
        gcs.recv("HEARTBEAT", timeout_s=60.0)  # the process's start-up: slow on a busy machine
        yield gcs, proc
    gcs.close()


@pytest.mark.e2e
def test_refusals_over_the_wire(raw_sitl) -> None:
    gcs, proc = raw_sitl
    # Offboard with no setpoint streaming: PX4 refuses the mode switch.
    assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == px4.TEMPORARILY_REJECTED
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == px4.ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF) == px4.ACCEPTED
    gcs.recv("EXTENDED_SYS_STATE", pred=lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR)
    # Disarm in the air without the kill magic: refused, still armed.
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == px4.TEMPORARILY_REJECTED
    gcs.recv("HEARTBEAT", pred=lambda m: m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
    # A NaN goto: denied, with PX4-style words in a STATUSTEXT.
    assert (
        gcs.command(mavlink.MAV_CMD_DO_REPOSITION, -1, 1, 0, math.nan, math.nan, math.nan, 500)
        == px4.DENIED
    )
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 6, math.inf) == px4.DENIED
    assert proc.alive()


@pytest.mark.e2e
def test_garbage_on_the_udp_port_does_not_kill_the_emulator(raw_sitl) -> None:
    gcs, proc = raw_sitl
    rng = random.Random(3)
    payloads = [
        b"",
        b"\xfd",
        b"\xfe\xff" + bytes(255),
        b"\xfd\x09\x00\x00\x00\x01\x01\x4c\x00\x00" + bytes(40),
    ]
    payloads += [
        bytes(rng.randrange(256) for _ in range(rng.randrange(1, 600))) for _ in range(300)
    ]
    # Valid frames with corrupted bytes, too: they get past the magic byte and the header.
    good = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs.mav)
    for _ in range(200):
        bad = bytearray(good)
        bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
        payloads.append(bytes(bad))
    for p in payloads:
        gcs.sock.sendto(p, gcs.peer)
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == px4.ACCEPTED
    assert proc.alive(), proc.output()
    assert gcs.recv("HEARTBEAT").autopilot == mavlink.MAV_AUTOPILOT_PX4


@pytest.mark.e2e
def test_listen_mode_answers_whoever_speaks() -> None:
    port = free_udp_port()
    with (
        SitlProcess(["--id", "6", "--listen", f"127.0.0.1:{port}"]) as proc,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
    ):
        sock.settimeout(0.2)
        hb = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(GCS)
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            sock.sendto(hb, ("127.0.0.1", port))
            try:
                msgs = mavlink.MAVLink(None).parse_buffer(sock.recv(65535)) or []
            except TimeoutError:
                continue
            if any(m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 6 for m in msgs):
                break
        else:
            raise AssertionError(f"no heartbeat from a listening emulator: {proc.output()}")
