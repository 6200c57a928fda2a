"""Mission uploads in a keyed station's command log, on a real Zenoh mesh with a real keyed
`covey agent`: a genuine upload by another station is listed as "mission N (k items) → ids"
with the vehicle's own ack (loaded, or rejected with the item and the reason); unsigned
uploads and one signed with a captured vehicle key are only counted in the summary line, like
forged commands (before: no mission upload was listed, and forged ones were not counted)."""

from __future__ import annotations

import dataclasses
import time

import pytest
from conftest import keyed_agent_argv, wait_until

from comms import keys
from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.schema import Mission, MissionItem, MissionItemKind, Role
from comms.session import embedded_peer, embedded_router, free_tcp_port, open_session
from groundstation.command_log import Progress, Status
from groundstation.station import GcsConfig, GroundStation
from trust.auth import load_auth
from trust.authority import throwaway_fleet
from trust.identity import signed_message

pytestmark = pytest.mark.e2e
FLEET = "ml"


def _mission(mission_id: int, n: int, alt_m: float = 6.0) -> Mission:
    items = tuple(
        MissionItem(MissionItemKind.WAYPOINT, x=5.0 * k, y=0.0, alt_m=alt_m) for k in range(n)
    )
    return Mission(new_nonce(), time.time_ns(), items, mission_id=mission_id, targets=(1,))


def test_a_keyed_station_lists_genuine_uploads_and_counts_forged_ones(procs, tmp_path) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1, 2], stations=[1, 2])
    key = {sid: str(authority.member_path(Role.STATION, sid)) for sid in (1, 2)}
    captured = load_auth(str(authority.member_path(Role.VEHICLE, 2)))  # a stolen vehicle key
    port = free_tcp_port()
    with (
        Mesh(embedded_router(port, fleet=FLEET)),
        GroundStation(
            GcsConfig(mesh=embedded_peer(port, fleet=FLEET), port=0, key_file=key[1])
        ) as gcs,
        Mesh(embedded_peer(port, fleet=FLEET), auth=load_auth(key[2])) as other,
        open_session(embedded_peer(port, fleet=FLEET)) as attacker,
    ):
        procs.start(
            *keyed_agent_argv(authority, 1), "--fleet", FLEET, "--connect", f"tcp/127.0.0.1:{port}"
        )
        assert other.presence().wait_for(lambda v, _g: 1 in v, timeout_s=90), "no vehicle 1"

        good = other.send_command(_mission(3, 6), timeout_s=5)
        assert good.by_status(OutcomeStatus.ACCEPTED) == [1], good.summary()
        high = other.send_command(_mission(4, 2, alt_m=150.0), timeout_s=5)
        assert high.by_status(OutcomeStatus.REJECTED) == [1], high.summary()

        forged = 20
        for k in range(forged):
            m = _mission(100 + k, 1)
            if k == 0:  # signed, but with a vehicle's key: not a station's signature
                stamped = dataclasses.replace(m, source_id=2)
                tag = captured.key.private_key.sign(
                    signed_message("mission", FLEET, stamped.signed_bytes())
                )
                m = dataclasses.replace(stamped, tag=tag)
            for _ in attacker.get(keys.all_cmds(FLEET), payload=m.encode(), timeout=0.5):
                pass

        def listed() -> dict[str, object]:
            return {e.describe(): e for e in gcs.commands.entries()}

        assert wait_until(lambda: gcs.commands.refused_commands == forged, 10), (
            gcs.commands.refused_last_minute(time.time_ns())
        )
        assert wait_until(lambda: len(listed()) == 2, 10), list(listed())
        entries = listed()
        up = entries["mission 3 (6 items) → 1"]
        assert up.sender() == "station 2" and up.signed
        assert wait_until(
            lambda: (
                gcs.commands.entries()[1].progress(1, time.time_ns(), 5.0, None)
                == Progress(Status.DONE, "loaded")
            ),
            10,
        )
        bad = gcs.commands.entries()[0]
        assert bad.describe() == "mission 4 (2 items) → 1"
        pr = bad.progress(1, time.time_ns(), 5.0, None)
        assert pr.status is Status.REJECTED and "item 1" in pr.detail, pr
        assert wait_until(
            lambda: f"data-refused-commands='{forged}'" in gcs.command_log_html.content, 10
        )
        html = gcs.command_log_html.content
        assert "mission 3 (6 items) → 1" in html and "mission 100" not in html
        print(f"mission log: 2 genuine uploads listed, {forged} forged counted: {html[:300]}")
