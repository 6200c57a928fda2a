"""Bounded presence (issue 34, finding 4): liveliness tokens are not signed, so in keyed mode the
station lists only vehicles that something signed proved, and a command to all waits only for
those (and, from `covey cmd`, for the roster's vehicles).

- the fleet model: a token alone takes no row; kept apart in a bounded set, counted beyond it;
  a verified state (or clock report) lists the vehicle and moves its token over; open mode as
  before;
- end to end: a keyless process declares 2,100 fake vehicle tokens, then a real keyed vehicle
  starts: the real keyed station lists it, and `covey cmd hold --to all` and the station's own
  command to all get its answer without a row of timeouts.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest

from comms.schema import ClockReport, Mode, Role, VehicleState
from groundstation.fleet import FleetConfig, FleetModel
from groundstation.tables import fleet_table
from tests.conftest import REPO, views_by_id, wait_until

FLEET = "covey"
FAKE_TOKENS = 2100


def state(vid: int, seq: int = 1) -> VehicleState:
    return VehicleState(vid, seq, 10**18, (1.0, 2.0, -3.0), (0.0, 0.0, 0.0), 0.0, Mode.HOLDING)


def test_tokens_alone_take_no_row_and_never_displace_a_verified_vehicle() -> None:
    model = FleetModel(FleetConfig(verified_only=True, max_vehicles=5, max_unverified=4))
    for vid in range(100, 110):
        model.on_presence(vid, True, 0)
    assert model.ids() == [] and model.unverified_present == 10  # 4 kept apart, 6 counted
    model.on_presence(101, False, 1)
    assert model.unverified_present == 9
    model.on_presence(110, True, 2)  # room again after 101 left: kept
    model.on_presence(1, True, 2)  # the set is full: only counted
    model.on_state(state(100), 10)  # a verified state of a kept token: listed, present
    model.on_state(state(1), 11)  # a verified state of a token only counted: listed, present
    assert model.ids() == [1, 100] and model.present_ids() == {1, 100}
    snap = model.snapshot(20)
    assert snap.unverified_present == 10 and all(v.alive for v in snap.vehicles)
    assert "10 presence tokens of unverified vehicles" in fleet_table(snap)
    model.on_presence(1, False, 21)  # a listed vehicle's token goes: LOST, as before
    assert model.present_ids() == {100}
    model.on_presence(555, False, 21)  # a counted token goes
    assert model.unverified_present == 9
    model.on_clock(ClockReport(7, 10.0, 1), 22)  # a verified clock report proves vehicle 7
    snap = model.snapshot(22)
    assert views_by_id(snap)[7].clock_offset_s == 10.0 and "CLOCK +10.0 s" in fleet_table(snap)
    model.on_clock(ClockReport(7, 0.1, 1, ok=True), 23)
    assert views_by_id(model.snapshot(24))[7].clock_offset_s is None


def test_open_mode_still_lists_present_vehicles() -> None:
    model = FleetModel()
    model.on_presence(3, True, 0)
    assert model.ids() == [3] and model.unverified_present == 0


@pytest.mark.e2e
@pytest.mark.slow
def test_2100_fake_tokens_then_a_real_vehicle_is_listed_and_answers_a_command_to_all(
    tmp_path, procs
) -> None:
    from comms.mesh import Mesh
    from comms.schema import CommandKind
    from comms.session import MeshConfig, embedded_peer, embedded_router, free_tcp_port
    from groundstation.inputs import CommandRequest
    from groundstation.station import GcsConfig, GroundStation
    from trust.authority import throwaway_fleet

    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1, 2], stations=[1, 2])
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    peer = MeshConfig(fleet=FLEET, mode="peer", connect=(endpoint,))
    with (
        Mesh(embedded_router(port, fleet=FLEET)) as _router,
        Mesh(embedded_peer(port, fleet=FLEET)) as keyless,  # an outsider: no key
        GroundStation(
            GcsConfig(mesh=peer, port=0, key_file=str(authority.member_path(Role.STATION, 1)))
        ) as gcs,
    ):
        for vid in range(100, 100 + FAKE_TOKENS):
            keyless.declare_vehicle(vid)
        assert wait_until(lambda: gcs.fleet.unverified_present >= FAKE_TOKENS, 30), (
            gcs.fleet.unverified_present
        )
        procs.start(
            "-m",
            "covey_cli",
            "agent",
            "--id",
            "1",
            "--key-file",
            str(authority.member_path(Role.VEHICLE, 1)),
            "--fleet",
            FLEET,
            "--connect",
            endpoint,
        )
        assert wait_until(lambda: gcs.fleet.present_ids() == {1}, 60), gcs.fleet.ids()
        snap = gcs.fleet.snapshot(time.time_ns(), trails=False)
        assert [v.vehicle_id for v in snap.vehicles] == [1]
        # The real vehicle's own token arrived beyond the bound, so it may be counted too.
        assert snap.unverified_present in (FAKE_TOKENS, FAKE_TOKENS + 1)
        assert f"{snap.unverified_present:,} presence tokens of unverified" in fleet_table(snap)

        t0 = time.monotonic()
        cli = subprocess.run(
            [sys.executable, "-m", "covey_cli", "cmd", "hold", "--to", "all", "--fleet", FLEET]
            + ["--connect", endpoint, "--timeout-s", "5"]
            + ["--key-file", str(authority.member_path(Role.STATION, 2))],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
        )
        cli_s = time.monotonic() - t0
        lines = cli.stdout.splitlines()
        assert [line for line in lines if line.startswith("vehicle")] == [
            line for line in lines if line.startswith("vehicle     1:")
        ], cli.stdout
        assert len([line for line in lines if line.startswith("vehicle")]) == 1, cli.stdout
        assert "timeout" not in cli.stdout and "no answer" not in cli.stdout, cli.stdout
        assert f"ignored {FAKE_TOKENS:,} presence tokens" in cli.stdout, cli.stdout

        done, got = threading.Event(), []
        t0 = time.monotonic()
        gcs.dispatch(
            "hold all",
            [(CommandRequest(CommandKind.HOLD, (0.0, 0.0, 0.0)), ())],
            lambda d: (got.append(d), done.set()),
        )
        assert done.wait(30)
        station_s = time.monotonic() - t0
        (result,) = got[0].results
        assert set(result.outcomes) == {1}, result.summary()
        assert result.outcomes[1].status.value != "timeout", result.summary()
        print(
            f"covey cmd hold --to all: {cli_s:.2f} s (process included); station: {station_s:.2f} s"
        )
