"""The onboard-mode relay (pymavlink) against the PX4 emulator in its own process, over real UDP.

The emulator has a second link, like PX4's GCS instance; an observer socket there sees the
ADSB_VEHICLE reports the emulator holds (PX4 streams its transponder reports back out), which is
how the test checks that the neighbours arrived.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from agent.backends.base import BackendError, Capability, NotSupported, Traffic
from agent.backends.relay import RelayBackend, RelayConfig, adsb_vehicle
from comms.adsb import covey_icao
from comms.geo import GeoOrigin
from firmware.sitl.process import SitlProcess, free_udp_port

HOME = GeoOrigin(48.7490, 9.1050, 450.0)
ORIGIN = GeoOrigin(48.7489, 9.1049, 450.0)
HOME_NED_M = ORIGIN.to_local(HOME.lat_deg, HOME.lon_deg, HOME.alt_m)
FAST = [
    "--takeoff-speed-m-s",
    "5",
    "--pos-gain-1-s",
    "3",
    "--accel-m-s2",
    "15",
    "--land-speed-m-s",
    "4",
    "--cruise-speed-m-s",
    "8",
    "--disarm-after-land-s",
    "0.3",
]


class Observer:
    """A second MAVLink link of the emulator (PX4's GCS instance): collects ADSB_VEHICLE echoes."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]

    def adsb(self, pred, timeout_s: float = 5.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            for m in mavlink.MAVLink(None).parse_buffer(data) or []:
                if m.get_type() == "ADSB_VEHICLE" and pred(m):
                    return m
        raise AssertionError(f"the emulator reported no matching ADSB_VEHICLE within {timeout_s} s")

    def close(self) -> None:
        self.sock.close()


def wait_for(backend, pred, timeout_s: float = 15.0, what: str = "condition"):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        t = backend.telemetry()
        if t is not None and pred(t):
            return t
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}; last telemetry {backend.telemetry()}")


@pytest.fixture
def relay_and_sitl():
    port, obs = free_udp_port(), Observer()
    home = f"{HOME.lat_deg},{HOME.lon_deg},{HOME.alt_m}"
    args = [
        "--id",
        "3",
        "--connect",
        f"udpout:127.0.0.1:{port}",
        "--connect",
        f"udpout:127.0.0.1:{obs.port}",
        "--home",
        home,
        *FAST,
    ]
    cfg = RelayConfig(connection=f"udpin:127.0.0.1:{port}", link_timeout_s=1.0)
    with SitlProcess(args) as proc, RelayBackend(cfg, ORIGIN) as relay:
        assert relay.wait_connected(), proc.output()
        yield relay, proc, obs
    obs.close()


@pytest.mark.e2e
def test_relay_flies_the_emulator_and_forwards_traffic(relay_and_sitl) -> None:
    relay, proc, obs = relay_and_sitl
    assert relay.capabilities == {
        Capability.ONBOARD_GUIDANCE,
        Capability.TRAFFIC_INPUT,
        Capability.TRAFFIC_RECEIVER,
    }
    with pytest.raises(NotSupported):
        relay.set_velocity_ned((1.0, 0.0, 0.0), 0.0)
    t = wait_for(relay, lambda t: True, what="first telemetry")
    assert t.pos_ned_m == pytest.approx(HOME_NED_M, abs=0.05) and t.link_ok and not t.armed

    # Refused on the ground: the reason is PX4's own STATUSTEXT.
    with pytest.raises(BackendError, match="TEMPORARILY_REJECTED.*not flying"):
        relay.goto_local((0.0, 0.0, -5.0))

    relay.takeoff(4.0)
    t = wait_for(relay, lambda t: t.pos_ned_m[2] < -3.7, what="takeoff altitude")
    assert t.armed and t.in_air and t.battery_pct <= 100.0

    neighbours = [
        Traffic(7, (30.0, 5.0, -4.0), (1.0, 1.0, 0.0), math.pi / 4, 0.2),
        Traffic(8, (-3.0, 20.0, -6.0), (0.0, -2.0, -0.5), 3 * math.pi / 2, 0.0),
    ]
    relay.send_traffic(neighbours)
    for n in neighbours:
        echo = obs.adsb(lambda m, n=n: m.ICAO_address == covey_icao(n.vehicle_id))
        back = ORIGIN.to_local(echo.lat * 1e-7, echo.lon * 1e-7, echo.altitude * 1e-3)
        assert back == pytest.approx(n.pos_ned_m, abs=0.05)
        assert echo.heading == round(math.degrees(n.heading_rad) * 100) % 36000
        assert echo.hor_velocity == round(math.hypot(*n.vel_ned_m_s[:2]) * 100)
        assert echo.ver_velocity == round(-n.vel_ned_m_s[2] * 100)
        assert (
            echo.flags & mavlink.ADSB_FLAGS_VALID_COORDS and echo.callsign == f"CVY{n.vehicle_id}"
        )

    target = (HOME_NED_M[0] + 12.0, HOME_NED_M[1] - 6.0, -6.0)
    relay.goto_local(target)
    t = wait_for(relay, lambda t: math.dist(t.pos_ned_m, target) < 0.5, what="goto target")
    relay.hold()
    wait_for(relay, lambda t: math.hypot(*t.vel_ned_m_s[:2]) < 0.05, what="hold")

    relay.land()
    wait_for(relay, lambda t: not t.armed and not t.in_air, what="landed and disarmed")

    relay.takeoff(3.0)
    wait_for(relay, lambda t: t.pos_ned_m[2] < -2.0, what="second takeoff")
    relay.kill()
    t = wait_for(relay, lambda t: t.pos_ned_m[2] > -0.05, what="drop")
    assert not t.armed

    proc.stop()
    wait_for(relay, lambda t: not t.link_ok, what="link loss")


@pytest.mark.e2e
def test_relay_refuses_bad_input_without_sending_it(relay_and_sitl) -> None:
    relay, proc, obs = relay_and_sitl
    for bad in ((math.nan, 0.0, -5.0), (0.0, math.inf, -5.0), (1.0, 2.0)):
        with pytest.raises(BackendError, match="finite"):
            relay.goto_local(bad)
    with pytest.raises(BackendError, match="takeoff altitude"):
        relay.takeoff(-1.0)
    good, bad = (
        Traffic(11, (5.0, 5.0, -4.0), (0.0, 0.0, 0.0), 0.0, 0.1),
        Traffic(12, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, 0.0),
    )
    with pytest.raises(BackendError, match=r"\[12\]"):
        relay.send_traffic([bad, good])
    assert obs.adsb(lambda m: m.ICAO_address == covey_icao(11))  # the good one still went out
    assert proc.alive()


@pytest.mark.e2e
def test_relay_connects_out_to_a_listening_emulator() -> None:
    port = free_udp_port()
    with (
        SitlProcess(["--id", "5", "--listen", f"udpin:127.0.0.1:{port}"]) as proc,
        # A bare URL, as `covey agent --vehicle relay:<url>` passes it.
        RelayBackend(f"udpout:127.0.0.1:{port}", origin=GeoOrigin()) as relay,
    ):
        assert relay.wait_connected(), proc.output()
        t = wait_for(relay, lambda t: True, what="telemetry")
        assert t.pos_ned_m == pytest.approx((0.0, 0.0, 0.0), abs=0.05)
        relay.hold()


class FakeAutopilot:
    """A PX4 stand-in on a socket: heartbeats, and a fixed answer (or silence) to every command."""

    def __init__(self, relay_port: int, result: int | None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.relay = ("127.0.0.1", relay_port)
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.result, self.commands = result, []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        next_hb = 0.0
        while not self.stop.is_set():
            if time.monotonic() > next_hb:
                next_hb = time.monotonic() + 0.2
                hb = mavlink.MAVLink_heartbeat_message(2, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3, 3)
                self.sock.sendto(hb.pack(self.mav), self.relay)
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            for m in mavlink.MAVLink(None).parse_buffer(data) or []:
                if m.get_type() == "COMMAND_LONG":
                    self.commands.append((m.command, m.confirmation))
                    if self.result is not None:
                        why = mavlink.MAVLink_statustext_message(6, b"Denied: a test")
                        self.sock.sendto(why.pack(self.mav), self.relay)
                        ack = mavlink.MAVLink_command_ack_message(
                            m.command, self.result, 0, 0, 245, 191
                        )
                        self.sock.sendto(ack.pack(self.mav), self.relay)

    def __enter__(self) -> FakeAutopilot:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.sock.close()


@pytest.mark.parametrize(
    ("result", "match"),
    [
        (None, "no COMMAND_ACK after 2 tries"),
        (mavlink.MAV_RESULT_DENIED, "refused: MAV_RESULT_DENIED.*Denied: a test"),
        (mavlink.MAV_RESULT_FAILED, "refused: MAV_RESULT_FAILED"),
    ],
)
def test_relay_maps_missing_and_negative_acks_to_backend_errors(result, match) -> None:
    port = free_udp_port()
    cfg = RelayConfig(connection=f"udpin:127.0.0.1:{port}", ack_timeout_s=0.3, attempts=2)
    with RelayBackend(cfg, ORIGIN) as relay, FakeAutopilot(port, result) as ap:
        assert relay.wait_connected(5.0)
        with pytest.raises(BackendError, match=match):
            relay.land()
        # The command protocol: a retry carries confirmation + 1; a refusal is not retried.
        expected = (
            [(mavlink.MAV_CMD_NAV_LAND, 0), (mavlink.MAV_CMD_NAV_LAND, 1)]
            if result is None
            else [(mavlink.MAV_CMD_NAV_LAND, 0)]
        )
        assert ap.commands == expected


def test_relay_without_an_autopilot_fails_with_a_reason() -> None:
    cfg = RelayConfig(connection=f"udpin:127.0.0.1:{free_udp_port()}", connect_timeout_s=0.3)
    with RelayBackend(cfg, ORIGIN) as relay:
        assert relay.telemetry() is None
        with pytest.raises(BackendError, match="no autopilot heartbeat"):
            relay.kill()
    with pytest.raises(BackendError, match="closed"):
        relay.land()


def test_relay_config_and_adsb_encoding_validate() -> None:
    for bad in ("14550", "udp:1.2.3.4:1", "udpin:host"):
        with pytest.raises(ValueError, match="udpin"):
            RelayConfig(connection=bad)
    with pytest.raises(ValueError, match="attempts"):
        RelayConfig(attempts=0)
    msg = adsb_vehicle(
        Traffic(0xABCD, (0.0, 0.0, -10.0), (3.0, 4.0, 1.0), -math.pi / 2, 300.0), ORIGIN
    )
    assert (msg.ICAO_address, msg.heading, msg.hor_velocity, msg.ver_velocity, msg.tslc) == (
        covey_icao(0xABCD),
        27000,
        500,
        -100,
        255,
    )
    assert msg.altitude == round((ORIGIN.alt_m + 10.0) * 1000)
