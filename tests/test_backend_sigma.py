"""Both autopilot backends report the position uncertainty the autopilot gives (GPS_RAW_INT
h_acc, PX4's eph): the emulator flying realistic vehicles (--vehicle-model realistic, 0.5 m
GNSS drift) in its own process, over real UDP."""

from __future__ import annotations

import time

import pytest

from agent.backends.base import pos_sigma_of
from comms.geo import GeoOrigin
from firmware.sitl.process import SitlProcess, free_udp_port

pytestmark = pytest.mark.e2e
HOME = GeoOrigin(48.7490, 9.1050, 450.0)


def _sitl(port: int, *extra: str) -> SitlProcess:
    home = f"{HOME.lat_deg},{HOME.lon_deg},{HOME.alt_m}"
    return SitlProcess(
        ["--id", "2", "--connect", f"udpout:127.0.0.1:{port}", "--home", home, *extra]
    )


def _sigma(backend, timeout_s: float = 10.0) -> float:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        t = backend.telemetry()
        if t is not None and t.pos_sigma_m > 0:
            return t.pos_sigma_m
        time.sleep(0.05)
    raise AssertionError(f"no position uncertainty within {timeout_s} s: {backend.telemetry()}")


def test_accuracy_is_sanitised():
    assert [pos_sigma_of(x) for x in (0.5, 0.0, -1.0, float("nan"), float("inf"), 5e3)] == [
        0.5,
        0.0,
        0.0,
        0.0,
        0.0,
        1000.0,
    ]


def test_relay_reports_the_emulators_sigma():
    from agent.backends.relay import RelayBackend, RelayConfig

    port = free_udp_port()
    cfg = RelayConfig(connection=f"udpin:127.0.0.1:{port}", link_timeout_s=1.0)
    with _sitl(port, "--vehicle-model", "realistic") as proc, RelayBackend(cfg, HOME) as relay:
        assert relay.wait_connected(), proc.output()
        assert _sigma(relay) == pytest.approx(0.5)


def test_mavsdk_reports_the_emulators_sigma():
    from agent.backends.mavsdk_backend import MavsdkBackend, MavsdkConfig

    port = free_udp_port()
    cfg = MavsdkConfig(connection=f"udpin://127.0.0.1:{port}", link_timeout_s=1.0)
    with _sitl(port, "--vehicle-model", "realistic") as proc, MavsdkBackend(cfg, HOME) as vb:
        assert vb.wait_connected(), proc.output()
        assert _sigma(vb, 20.0) == pytest.approx(0.5)
