"""`covey status` shows a landed vehicle's real state rate (issue 39 #13).

A landed, disarmed vehicle publishes once a second (comms/state_rate.py). Before, a listen
shorter than two of its states showed `Hz 0.0`; now status listens on (two idle periods at
most) until it has two, and shows about 1 Hz; a rate it could not measure shows as "-".
"""

from __future__ import annotations

import pytest

from comms.mesh import Mesh
from comms.session import embedded_peer, embedded_router, free_tcp_port
from groundstation.fleet import FleetModel
from groundstation.ops import StatusConfig, format_status, status_main

pytestmark = [pytest.mark.e2e]


def _hz_column(lines: list[str], vid: int) -> str:
    """The Hz cell of vehicle `vid`'s row (id alive mode arm N E alt m/s bat% Hz ...)."""
    assert lines[0].split()[12] == "Hz", lines[0]
    row = next(line.split() for line in lines[1:] if line.split()[0] == str(vid))
    return row[9]


def test_status_shows_a_landed_vehicles_one_hertz(procs) -> None:
    port = free_tcp_port()
    with Mesh(embedded_router(port)) as mesh:
        presence = mesh.presence()
        procs.start("-m", "covey_cli", "agent", "--id", "4", "--connect", f"tcp/127.0.0.1:{port}")
        assert presence.wait_for(lambda v, _g: 4 in v, timeout_s=60)
        lines: list[str] = []
        cfg = StatusConfig(mesh=embedded_peer(port), listen_s=0.4)  # under one idle period
        assert status_main(cfg, out=lambda text: lines.extend(text.splitlines())) == 0
    hz = _hz_column(lines, 4)
    assert hz != "-" and 0.5 <= float(hz) <= 2.0, lines


def test_an_unmeasured_rate_is_a_dash_not_zero() -> None:
    from comms.schema import Mode, VehicleState

    fleet = FleetModel()
    fleet.on_state(
        VehicleState(4, 1, 1_000, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, Mode.LANDED, False, 90.0),
        1_000,
    )
    lines = format_status(fleet.snapshot(2_000)).splitlines()
    assert _hz_column(lines, 4) == "-"
