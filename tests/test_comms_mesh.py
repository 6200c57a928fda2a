"""The mesh across real processes on loopback: states, presence, broadcast commands with acks."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from comms import keys
from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import COMMAND_RING, Mesh
from comms.schema import AckResult, Command, CommandAck, CommandKind, Mode, VehicleState
from comms.session import embedded_peer, embedded_router, free_tcp_port

pytestmark = pytest.mark.e2e


@pytest.fixture
def hub():
    port = free_tcp_port()
    with Mesh(embedded_router(port)) as mesh:
        mesh.declare_gcs(1)
        yield port, mesh


def test_two_processes_exchange_states(hub, procs) -> None:
    port, _ = hub
    talker = procs.start("tests/mesh_node.py", str(port), "1", "accept")
    listener = procs.start("tests/mesh_node.py", str(port), "2", "echo-states")
    talker.wait_for("READY")
    listener.wait_for("READY")
    seqs = []
    while len(seqs) < 5:
        line = listener.wait_for("STATE 1 ", timeout_s=20)
        seqs.append(int(line.split()[2]))
    assert seqs == sorted(seqs) and len(set(seqs)) == 5


def test_killed_process_is_reported_gone_within_1s(hub, procs) -> None:
    port, mesh = hub
    left = threading.Event()
    gone_at: list[float] = []

    def on_change(kind: str, ident: int, alive: bool) -> None:
        if kind == "vehicle" and ident == 7 and not alive:
            gone_at.append(time.monotonic())
            left.set()

    presence = mesh.presence(on_change)
    node = procs.start("tests/mesh_node.py", str(port), "7", "accept")
    node.wait_for("READY")
    assert presence.wait_for(lambda v, g: 7 in v, timeout_s=20)
    killed_at = time.monotonic()
    os.kill(node.pid, signal.SIGKILL)
    assert left.wait(5.0), "presence never reported the killed vehicle"
    delay_s = gone_at[0] - killed_at
    print(f"presence loss reported {delay_s * 1000:.1f} ms after kill -9")
    assert delay_s < 1.0
    assert 7 not in presence.vehicles


def test_one_broadcast_reaches_ten_vehicles(hub, procs) -> None:
    port, mesh = hub
    presence = mesh.presence()
    behaviours = {vid: "accept" for vid in range(1, 11)}
    behaviours[4] = "reject"
    behaviours[9] = "hang"
    nodes = [procs.start("tests/mesh_node.py", str(port), str(v), b) for v, b in behaviours.items()]
    for node in nodes:
        node.wait_for("READY", timeout_s=60)
    assert presence.wait_for(lambda v, g: v >= set(behaviours), timeout_s=30)
    cmd = Command(CommandKind.HOLD, new_nonce(), time.time_ns())
    result = mesh.send_command(cmd, expect=presence.vehicles, timeout_s=3.0)
    assert set(result.outcomes) == set(behaviours)
    assert result.by_status(OutcomeStatus.ACCEPTED) == [
        v for v, b in behaviours.items() if b == "accept"
    ]
    assert result.outcomes[4].status is OutcomeStatus.REJECTED
    assert result.outcomes[4].reason == "vehicle 4 says no"
    assert result.outcomes[9].status is OutcomeStatus.TIMEOUT
    assert not result.ok


def test_command_to_a_list_reaches_only_that_list(hub, procs) -> None:
    port, mesh = hub
    presence = mesh.presence()
    nodes = [procs.start("tests/mesh_node.py", str(port), str(v), "accept") for v in (1, 2, 3)]
    for node in nodes:
        node.wait_for("READY", timeout_s=60)
    assert presence.wait_for(lambda v, g: v >= {1, 2, 3}, timeout_s=30)
    result = mesh.send_command(
        Command(CommandKind.LAND, new_nonce(), 0, targets=(1, 3)), timeout_s=3.0
    )
    assert sorted(result.outcomes) == [1, 3]
    assert result.ok
    missing = mesh.send_command(
        Command(CommandKind.LAND, new_nonce(), 0, targets=(5,)), timeout_s=1.0
    )
    assert missing.outcomes[5].status is OutcomeStatus.TIMEOUT


def test_malformed_payloads_do_not_kill_a_subscriber(hub, procs) -> None:
    port, mesh = hub
    listener = procs.start("tests/mesh_node.py", str(port), "2", "echo-states")
    listener.wait_for("READY")
    time.sleep(0.5)
    for junk in (b"", b"\x01", b"\x01\x01" + b"\xff" * 62, b"garbage" * 10):
        mesh.session.put("covey/covey/v/5/state", junk)
    mesh.publish_state(VehicleState(5, 1, 0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0))
    line = listener.wait_for("STATE 5 ", timeout_s=10)
    assert line.split()[2] == "1"
    reply = mesh.session.get("covey/covey/v/2/cmd", payload=b"\x02\x01nonsense", timeout=3.0)
    answers = [r for r in reply]
    assert len(answers) == 1 and answers[0].ok is not None
    assert listener.poll() is None


def test_a_polled_command_queryable_answers_when_polled_and_keeps_the_newest_of_a_flood(
    hub,
) -> None:
    """A host's vehicles answer from its tick (`serve_commands(polled=True)`): nothing before a
    poll, every query after it in order, and a flood between two polls keeps the newest."""
    port, station = hub
    calls: list[int] = []

    def handler(cmd: Command) -> CommandAck:
        calls.append(cmd.nonce)
        return CommandAck(7, cmd.nonce, 0, AckResult.ACCEPTED, "", Mode.LANDED)

    with Mesh(embedded_peer(port)) as vehicle:
        inbox = vehicle.serve_commands(7, handler, polled=True)
        time.sleep(0.5)  # the queryable reaches the station
        hold = Command(CommandKind.HOLD, new_nonce(), time.time_ns())
        out: list = []
        sender = threading.Thread(
            target=lambda: out.append(station.send_command(hold, expect=(7,), timeout_s=5))
        )
        sender.start()
        time.sleep(0.5)
        assert sender.is_alive() and calls == []  # waits for the poll
        deadline = time.monotonic() + 5
        while inbox.poll() == 0:
            assert time.monotonic() < deadline, "the query never reached the ring"
            time.sleep(0.01)
        sender.join(5)
        assert calls == [hold.nonce] and out[0].ok, out[0].summary()

        calls.clear()
        flood = [Command(CommandKind.HOLD, new_nonce(), time.time_ns()) for _ in range(100)]
        for cmd in flood:
            station.session.get(keys.cmd("covey", 7), lambda _r: None, payload=cmd.encode())
        time.sleep(1.0)
        assert inbox.poll() == COMMAND_RING
        assert calls == [c.nonce for c in flood[-COMMAND_RING:]]
        assert inbox.poll() == 0
