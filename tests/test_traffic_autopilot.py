"""Traffic from the autopilot's own receiver, against the PX4 emulator in its own process over UDP.

An ADS-B receiver (a pymavlink socket on a link of the emulator, as a PingRX on TELEM2) sends
ADSB_VEHICLE reports; the emulator holds them and streams them out, as PX4 does. MAVSDK's
transponder plugin (companion mode) and the relay (onboard mode) must turn real traffic into
tracks in the fleet frame, and never take covey's own reports for traffic nor echo one as the other.
"""

from __future__ import annotations

import contextlib
import math
import socket
import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from agent.backends.base import Capability, Traffic
from agent.backends.mavsdk_backend import MavsdkBackend, MavsdkConfig
from agent.backends.relay import RelayBackend, RelayConfig
from comms import adsb
from comms.geo import GeoOrigin
from comms.schema import TrafficSource
from comms.traffic import TRAFFIC_ID_BASE
from firmware.sitl.process import SitlProcess, free_udp_port

pytestmark = pytest.mark.e2e

HOME = GeoOrigin(48.7490, 9.1050, 450.0)
ORIGIN = GeoOrigin(48.7489, 9.1049, 450.0)
CESSNA = 0x3C6444
"""A real (24-bit) ICAO address."""
DRONE = 0x3C0001


class Receiver:
    """An ADS-B receiver wired to the autopilot: sends ADSB_VEHICLE to one of its links."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.addr = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(None, srcSystem=200, srcComponent=156)

    def send(self, icao: int, ned_m, vel_ne_m_s, callsign: str, emitter: int) -> None:
        lat, lon, alt = ORIGIN.to_global(*ned_m)
        course_cdeg = round(math.degrees(math.atan2(vel_ne_m_s[1], vel_ne_m_s[0])) * 100) % 36000
        msg = mavlink.MAVLink_adsb_vehicle_message(
            icao,
            round(lat * 1e7),
            round(lon * 1e7),
            mavlink.ADSB_ALTITUDE_TYPE_GEOMETRIC,
            round(alt * 1000),
            course_cdeg,
            round(math.hypot(*vel_ne_m_s) * 100),
            0,
            callsign.encode(),
            emitter,
            0,
            mavlink.ADSB_FLAGS_VALID_COORDS
            | mavlink.ADSB_FLAGS_VALID_ALTITUDE
            | mavlink.ADSB_FLAGS_VALID_HEADING
            | mavlink.ADSB_FLAGS_VALID_VELOCITY
            | mavlink.ADSB_FLAGS_VALID_CALLSIGN,
            0,
        )
        self.sock.sendto(msg.pack(self.mav), self.addr)

    def close(self) -> None:
        self.sock.close()


def sitl_args(link: str, rx_port: int) -> list[str]:
    home = f"{HOME.lat_deg},{HOME.lon_deg},{HOME.alt_m}"
    return ["--id", "2", "--connect", link, "--listen", f"udpin:127.0.0.1:{rx_port}"] + [
        "--home",
        home,
    ]


def collect(backend, until, timeout_s: float = 10.0, feed=None) -> dict:
    """Tracks by id, gathered until `until(tracks)` holds (bounded wait)."""
    tracks: dict = {}
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if feed is not None:
            feed()
        for t in backend.traffic_tracks(time.monotonic()):
            tracks[t.track_id] = t
        if until(tracks):
            return tracks
        time.sleep(0.1)
    raise AssertionError(f"tracks after {timeout_s} s: {sorted(tracks)}")


def test_mavsdk_transponder_reads_real_traffic_not_covey_reports() -> None:
    port, rx_port = free_udp_port(), free_udp_port()
    rx = Receiver(rx_port)
    cfg = MavsdkConfig(connection=f"udpin://127.0.0.1:{port}")
    with (
        SitlProcess(sitl_args(f"udpout:127.0.0.1:{port}", rx_port)) as proc,
        MavsdkBackend(cfg, ORIGIN) as be,
    ):
        assert be.wait_connected(), proc.output()
        assert Capability.TRAFFIC_RECEIVER in be.capabilities

        def feed() -> None:
            rx.send(CESSNA, (40.0, -10.0, -60.0), (-30.0, 40.0), "DEGAB", 1)  # light aircraft
            rx.send(DRONE, (5.0, 6.0, -10.0), (0.0, 2.0), "DRONE1", 14)  # someone else's UAV
            # covey's own report of vehicle 9, as a relay would have sent it
            rx.send(adsb.covey_icao(9), (1.0, 1.0, -10.0), (1.0, 0.0), "CVY9", 14)

        tracks = collect(be, lambda t: {CESSNA, DRONE} <= t.keys(), feed=feed)
        assert adsb.covey_icao(9) not in tracks and be.traffic_reports >= 3
        cessna, drone = tracks[CESSNA], tracks[DRONE]
        assert cessna.manned and not drone.manned and cessna.source is TrafficSource.ADSB
        assert cessna.pos_ned_m == pytest.approx((40.0, -10.0, -60.0), abs=0.1)
        assert cessna.vel_ned_m_s[:2] == pytest.approx((-30.0, 40.0), abs=0.2)
        assert drone.pos_ned_m == pytest.approx((5.0, 6.0, -10.0), abs=0.1)
        assert cessna.callsign == "DEGAB"
    rx.close()


def test_relay_forwards_real_traffic_and_never_echoes_one_as_the_other() -> None:
    port, rx_port = free_udp_port(), free_udp_port()
    rx = Receiver(rx_port)
    cfg = RelayConfig(connection=f"udpin:127.0.0.1:{port}")
    with (
        SitlProcess(sitl_args(f"udpout:127.0.0.1:{port}", rx_port)) as proc,
        RelayBackend(cfg, ORIGIN) as relay,
    ):
        assert relay.wait_connected(), proc.output()
        intruder = TRAFFIC_ID_BASE + 0x0200_0001  # a station's simulated intruder, from the mesh
        sent = [
            Traffic(4, (10.0, 0.0, -5.0), (1.0, 0.0, 0.0), 0.0, 0.1),  # a covey neighbour
            Traffic(intruder, (-20.0, 0.0, -5.0), (2.0, 0.0, 0.0), 0.0, 0.1, cooperative=False),
        ]

        def feed() -> None:
            rx.send(CESSNA, (40.0, -10.0, -60.0), (-30.0, 40.0), "DEGAB", 1)
            relay.send_traffic(sent)

        tracks = collect(relay, lambda t: CESSNA in t and relay.own_echoes >= 4, feed=feed)
        # the real aircraft came through as traffic, manned, in the fleet frame ...
        assert tracks[CESSNA].manned
        assert tracks[CESSNA].pos_ned_m == pytest.approx((40.0, -10.0, -60.0), abs=0.1)
        # ... while neither covey's neighbour report nor the mesh intruder we forwarded came
        # back as traffic (both were streamed back by the autopilot: own_echoes counts them)
        assert set(tracks) == {CESSNA}
        # and traffic the autopilot heard itself is never sent back to it
        echo_back = Traffic(TRAFFIC_ID_BASE + CESSNA, (0.0, 0.0, -5.0), (0.0,) * 3, 0.0, 0.0)
        relay.send_traffic([Traffic(**{**echo_back.__dict__, "cooperative": False})])
        assert CESSNA not in relay._sent_traffic_s
    rx.close()


def test_a_relay_agent_reports_what_its_autopilot_hears_and_forwards_the_mesh_intruder(
    procs,
) -> None:
    """Real processes: the emulator (an ADS-B receiver on one link, an observer on another)
    behind `covey agent --vehicle relay:...` on a Zenoh mesh. The Cessna its receiver hears
    reaches the mesh as vehicle 2's signed-in-keyed-mode report; a station's intruder reaches
    the autopilot as traffic (callsign TRF), and its echo never comes back as vehicle 2's report."""
    import dataclasses

    from test_backend_relay import Observer

    from comms.mesh import Mesh
    from comms.schema import Role, TrafficFlag, TrafficReport
    from comms.session import embedded_router, free_tcp_port
    from comms.traffic import TrafficListener, TrafficTable, publish_report

    port, relay_port, rx_port = free_tcp_port(), free_udp_port(), free_udp_port()
    rx, obs = Receiver(rx_port), Observer()
    home = f"{HOME.lat_deg},{HOME.lon_deg},{HOME.alt_m}"
    origin = f"{ORIGIN.lat_deg},{ORIGIN.lon_deg},{ORIGIN.alt_m}"
    got: list[TrafficReport] = []
    with Mesh(embedded_router(port)) as mesh:
        mesh.declare_gcs(1)
        listener = TrafficListener(
            mesh, TrafficTable(), time.monotonic, lambda _t, r: got.append(r)
        )
        procs.start(
            "-m",
            "firmware.sitl",
            "--id",
            "2",
            "--connect",
            f"udpout:127.0.0.1:{relay_port}",
            "--connect",
            f"udpout:127.0.0.1:{obs.port}",
            "--listen",
            f"udpin:127.0.0.1:{rx_port}",
            "--home",
            home,
        )
        procs.start(
            "-m",
            "covey_cli",
            "agent",
            "--id",
            "2",
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--vehicle",
            f"relay:udpin:127.0.0.1:{relay_port}",
            "--origin",
            origin,
            "--no-gcs-failsafe",
        )
        assert mesh.presence().wait_for(lambda v, _g: 2 in v, timeout_s=60)
        intruder = TrafficReport(
            Role.STATION, 1, 0x2000001, TrafficSource.SIM, 0, (0.0, 8.0, -5.0), (0.0, -2.0, 0.0)
        )
        end = time.monotonic() + 30
        forwarded = None
        while time.monotonic() < end and not (forwarded and any(r.track_id == CESSNA for r in got)):
            rx.send(CESSNA, (40.0, -10.0, -60.0), (-30.0, 40.0), "DEGAB", 1)
            publish_report(mesh, dataclasses.replace(intruder, stamp_ns=time.time_ns()))
            if forwarded is None:
                with contextlib.suppress(AssertionError):
                    forwarded = obs.adsb(lambda m: m.ICAO_address == 0x2000001, timeout_s=0.3)
            time.sleep(0.2)
        time.sleep(2.0)  # time for an echo to come back, were it going to
        listener.close()
    rx.close()
    obs.close()
    mine = [r for r in got if r.reporter_role is Role.VEHICLE]
    cessna = [r for r in mine if r.track_id == CESSNA]
    assert cessna and cessna[-1].reporter_id == 2 and cessna[-1].flags & TrafficFlag.MANNED
    assert cessna[-1].pos_ned_m == pytest.approx((40.0, -10.0, -60.0), abs=0.5)
    assert forwarded is not None and forwarded.callsign.startswith("TRF")
    assert forwarded.emitter_type == 0  # unmanned intruder: no emitter information
    assert {r.track_id for r in mine} == {CESSNA}, "the forwarded intruder came back as traffic"
