"""Signed commands (comms/auth.py): the checks in isolation, key handling, and across real
agent processes started with a key file.

Run as a script, this file is an agent launcher with `--key-file` (what `covey agent
--key-file` does once agent/cli.py wires it): `python tests/test_trust_auth.py --key-file K --id 1 ...`
"""

from __future__ import annotations

import dataclasses
import os
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from comms.auth import (
    CommandAuth,
    FleetKeyError,
    keygen_cli,
    load_auth,
    load_key,
    parse_key,
    read_key_file,
    write_new_key,
)
from comms.schema import AckResult, Command, CommandAck, CommandKind, Event, EventKind, Mode

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
T0_NS = 1_700_000_000_000_000_000


class Clock:
    def __init__(self, t_ns: int = T0_NS) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns


def takeoff(nonce: int = 7, targets=(1,)) -> Command:
    return Command.takeoff(10.0, nonce=nonce, stamp_ns=0, targets=targets, source_id=1)


# -- the checks ------------------------------------------------------------------------------
def test_signed_command_passes_once_and_everything_else_fails_with_its_reason() -> None:
    clock = Clock()
    sender, vehicle = CommandAuth(KEY, clock_ns=clock), CommandAuth(KEY, clock_ns=clock)
    cmd = sender.sign_command(takeoff())
    assert cmd.stamp_ns == T0_NS and cmd.tag != bytes(32)
    assert Command.decode(cmd.encode()) == cmd  # the tag survives the wire
    assert vehicle.check_command(cmd, 1) is None
    assert "replayed" in vehicle.check_command(cmd, 1)
    assert "unsigned" in vehicle.check_command(takeoff(nonce=8), 1)
    assert "bad signature" in vehicle.check_command(
        CommandAuth(OTHER_KEY, clock_ns=clock).sign_command(takeoff(9)), 1
    )
    signed = sender.sign_command(takeoff(10, targets=(1, 2)))
    for tampered in (
        dataclasses.replace(signed, params=(50.0, 0.0, 0.0)),
        dataclasses.replace(signed, targets=(1, 3)),
        dataclasses.replace(signed, kind=CommandKind.KILL, params=(0.0, 0.0, 0.0)),
        dataclasses.replace(signed, source_id=2),
        dataclasses.replace(signed, seq=1),
        dataclasses.replace(signed, stamp_ns=signed.stamp_ns + 1),
        dataclasses.replace(signed, tag=bytes([signed.tag[0] ^ 1]) + signed.tag[1:]),
    ):
        assert "bad signature" in vehicle.check_command(tampered, 1)
    clock.t_ns += 6 * 10**9
    assert "stale" in vehicle.check_command(signed, 1)
    clock.t_ns -= 12 * 10**9
    assert "stale" in vehicle.check_command(signed, 1)  # from the future too
    assert vehicle.rejected == 12


def test_a_broadcast_is_fresh_for_each_vehicle_of_one_process() -> None:
    auth = CommandAuth(KEY, clock_ns=Clock())
    cmd = auth.sign_command(takeoff(targets=()))
    assert [auth.check_command(cmd, v) for v in (1, 2, 3)] == [None, None, None]
    assert "replayed" in auth.check_command(cmd, 2)


def test_nonce_cache_is_bounded_and_forgets_only_what_is_stale_anyway() -> None:
    clock = Clock()
    auth = CommandAuth(KEY, clock_ns=clock, max_skew_s=5.0, replay_window=100)
    first = [auth.sign_command(takeoff(nonce=n)) for n in range(1, 101)]
    assert all(auth.check_command(c, 1) is None for c in first)
    clock.t_ns += 1
    newer = auth.sign_command(takeoff(nonce=1000))
    assert auth.check_command(newer, 1) is None  # evicts one; older stamps now below the floor
    assert len(auth._seen) == 100
    assert all(auth.check_command(c, 1) is not None for c in first)  # replays still refused
    clock.t_ns += 6 * 10**9
    late = auth.sign_command(takeoff(nonce=2000))
    assert auth.check_command(late, 1) is None
    assert len(auth._seen) == 1  # the stale ones expired


def test_zero_nonce_gets_a_fresh_one_and_acks_are_signed_apart_from_commands() -> None:
    auth = CommandAuth(KEY, clock_ns=Clock(), rng=lambda _bits, it=iter([0, 0, 42]): next(it))
    cmd = auth.sign_command(takeoff(nonce=0))
    assert cmd.nonce == 42
    ack = auth.sign_ack(CommandAck(1, cmd.nonce, T0_NS, AckResult.ACCEPTED, "", Mode.TAKING_OFF))
    assert auth.check_ack(ack, cmd) is None
    assert "another fleet key" in CommandAuth(OTHER_KEY).check_ack(ack, cmd)
    assert "open mode" in auth.check_ack(dataclasses.replace(ack, tag=bytes(32)), cmd)
    forged = dataclasses.replace(ack, result=AckResult.REJECTED, reason="no")
    assert "bad signature" in auth.check_ack(
        forged, cmd
    ) and "it said: rejected: no" in auth.check_ack(forged, cmd)
    assert "does not answer" in auth.check_ack(
        auth.sign_ack(dataclasses.replace(ack, nonce=43)), cmd
    )
    # A command tag is not an ack tag even over identical bytes.
    assert auth._tag(b"covey-cmd-v1\0", b"x") != auth._tag(b"covey-ack-v1\0", b"x")


def test_check_command_is_thread_safe() -> None:
    auth = CommandAuth(KEY)
    cmds = [auth.sign_command(takeoff(nonce=n)) for n in range(1, 401)]
    accepted: list[int] = []
    lock = threading.Lock()

    def worker() -> None:
        for c in cmds:
            if auth.check_command(c, 1) is None:
                with lock:
                    accepted.append(c.nonce)

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(accepted) == list(range(1, 401))  # each exactly once


def test_on_reject_listener_sees_every_refusal_and_cannot_break_the_check() -> None:
    auth = CommandAuth(KEY)
    seen: list[str] = []
    auth.on_reject = lambda cmd, vid, reason: seen.append(reason)
    assert "unsigned" in auth.check_command(takeoff(), 1)
    auth.on_reject = lambda *_: 1 / 0
    assert "unsigned" in auth.check_command(takeoff(), 1)
    assert len(seen) == 1


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(FleetKeyError):
        CommandAuth(b"short")
    with pytest.raises(ValueError):
        CommandAuth(KEY, max_skew_s=0)
    with pytest.raises(ValueError):
        CommandAuth(KEY, replay_window=0)


# -- keys ------------------------------------------------------------------------------------
def test_keygen_writes_0600_refuses_to_overwrite_and_the_key_loads(tmp_path, capsys) -> None:
    path = tmp_path / "sub" / "fleet.key"
    assert keygen_cli(["-o", str(path)]) == 0
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert "wrote fleet key" in capsys.readouterr().out
    before = path.read_bytes()
    assert keygen_cli(["-o", str(path)]) == 1
    assert "already exists" in capsys.readouterr().err and path.read_bytes() == before
    assert len(read_key_file(path)) == 32
    assert load_auth(str(path), env={}) is not None


def test_key_sources_and_their_errors(tmp_path, caplog) -> None:
    path = write_new_key(tmp_path / "k")
    key = read_key_file(path)
    import base64

    assert load_key(None, {"COVEY_FLEET_KEY": key.hex()}) == key
    assert load_key(None, {"COVEY_FLEET_KEY": base64.b64encode(key).decode()}) == key
    assert load_key(None, {"COVEY_FLEET_KEY_FILE": str(path)}) == key
    assert load_key(str(path), {"COVEY_FLEET_KEY": "00" * 32}) == key  # the explicit file wins
    raw = tmp_path / "raw"
    raw.write_bytes(key)
    raw.chmod(0o600)
    assert read_key_file(raw) == key
    with caplog.at_level("WARNING", logger="comms.auth"):
        assert load_auth(None, env={}) is None
    assert "OPEN MODE" in caplog.text
    path.chmod(0o644)
    with pytest.raises(FleetKeyError, match="chmod 600"):
        load_auth(str(path), env={})
    with pytest.raises(FleetKeyError, match="does not exist"):
        read_key_file(tmp_path / "missing")
    with pytest.raises(FleetKeyError, match="not a key"):
        parse_key("not hex, not base64!", "$COVEY_FLEET_KEY")
    with pytest.raises(FleetKeyError, match="at least 16"):
        parse_key("00" * 8, "$COVEY_FLEET_KEY")
    with pytest.raises(FleetKeyError):
        load_auth(None, env={"COVEY_FLEET_KEY": "zz"})  # a typo never falls back to open mode


# -- across real processes -------------------------------------------------------------------
@pytest.mark.e2e
def test_agents_with_a_key_file_accept_only_fresh_correctly_signed_commands(
    procs, tmp_path
) -> None:
    from comms.commands import OutcomeStatus, new_nonce
    from comms.mesh import Mesh
    from comms.session import embedded_peer, embedded_router, free_tcp_port

    key_file = write_new_key(tmp_path / "fleet.key")
    key = read_key_file(key_file)
    port = free_tcp_port()
    events: list[Event] = []
    with Mesh(embedded_router(port), auth=CommandAuth(key)) as gcs:
        gcs.subscribe_events(lambda e, _t: events.append(e))
        presence = gcs.presence()
        launcher = ["-m", "covey_cli", "agent"]  # the real `covey agent --key-file`
        for vid in (1, 2):
            procs.start(*launcher, "--key-file", str(key_file), "--id", str(vid), "--connect", f"tcp/127.0.0.1:{port}",
                        f"--start={3 * vid},0", "--no-gcs-failsafe")  # fmt: skip
        assert presence.wait_for(lambda v, _g: v >= {1, 2}, timeout_s=60), "agents did not come up"
        with Mesh(embedded_peer(port)) as raw:  # sends exactly what it is given
            time.sleep(0.5)

            def raw_send(cmd: Command, vid: int):
                return raw.send_command(cmd, expect=(vid,), timeout_s=5).outcomes[vid]

            now = time.time_ns
            outcomes = {
                "unsigned": raw_send(Command.takeoff(5.0, nonce=new_nonce(), stamp_ns=now(), targets=(1,)), 1),
                "wrong key": raw_send(CommandAuth(OTHER_KEY).sign_command(Command.takeoff(5.0, nonce=0, stamp_ns=0, targets=(1,))), 1),
                "tampered params": raw_send(dataclasses.replace(CommandAuth(key).sign_command(Command.takeoff(5.0, nonce=0, stamp_ns=0, targets=(1,))), params=(100.0, 0.0, 0.0)), 1),
                "tampered targets": raw_send(dataclasses.replace(CommandAuth(key).sign_command(Command.takeoff(5.0, nonce=0, stamp_ns=0, targets=(1,))), targets=(2,)), 2),
                "stale": raw_send(CommandAuth(key, clock_ns=lambda: time.time_ns() - 60 * 10**9).sign_command(Command.takeoff(5.0, nonce=0, stamp_ns=0, targets=(1,))), 1),
            }  # fmt: skip
            expected = {"unsigned": "unsigned", "wrong key": "bad signature", "tampered params": "bad signature",
                        "tampered targets": "bad signature", "stale": "stale"}  # fmt: skip
            for name, outcome in outcomes.items():
                assert outcome.status is OutcomeStatus.REJECTED, (name, outcome)
                assert expected[name] in outcome.reason, (name, outcome.reason)
                assert outcome.ack is not None and outcome.ack.tag != bytes(
                    32
                )  # the refusal is signed
            # Signed by the station's own mesh: accepted, ack verified.
            ok = gcs.send_command(
                Command.takeoff(5.0, nonce=new_nonce(), stamp_ns=0, targets=(1,)), timeout_s=5
            )
            assert ok.ok, ok.summary()
            # The exact bytes again (a recorded command played back): refused as a replay.
            replayed = raw_send(ok.command, 1)
            assert replayed.status is OutcomeStatus.REJECTED and "replayed" in replayed.reason
            # A fleet-wide signed command reaches both.
            both = gcs.send_command(
                Command(CommandKind.HOLD, new_nonce(), 0), expect=(1, 2), timeout_s=5
            )
            assert set(both.outcomes) == {1, 2} and all(
                o.ack is not None for o in both.outcomes.values()
            ), both.summary()
            # The real `covey cmd --key-file`, and without a key (open mode: refused as unsigned).
            run = [sys.executable, "-m", "covey_cli", "cmd", "land", "--to", "all",
                   "--connect", f"tcp/127.0.0.1:{port}"]  # fmt: skip
            env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent))
            env.pop("COVEY_FLEET_KEY", None)
            env.pop("COVEY_FLEET_KEY_FILE", None)
            signed = subprocess.run(
                [*run, "--key-file", str(key_file)],
                capture_output=True,
                text=True,
                timeout=60,
                env=env,
            )
            unsigned = subprocess.run(run, capture_output=True, text=True, timeout=60, env=env)
            print(
                "covey cmd --key-file:",
                signed.stdout.strip(),
                "| without:",
                unsigned.stdout.strip(),
            )
            assert "accepted" in signed.stdout and "unsigned" not in signed.stdout, (
                signed.stdout + signed.stderr
            )
            assert "unsigned" in unsigned.stdout and "OPEN MODE" in unsigned.stderr, (
                unsigned.stdout + unsigned.stderr
            )
            # The browser station's own mesh signs with --key-file (GcsConfig.key_file).
            from comms.schema import CommandKind as Kind
            from comms.session import MeshConfig
            from groundstation import dispatch, inputs
            from groundstation.app import GcsConfig, GroundStation

            station = GcsConfig(mesh=MeshConfig(mode="peer", connect=(f"tcp/127.0.0.1:{port}",)), port=0,
                                gcs_id=5, key_file=str(key_file))  # fmt: skip
            with GroundStation(station) as gs:
                res = dispatch.send(gs.mesh, inputs.takeoff(4.0), (1, 2), source_id=5, timeout_s=10)
                assert res.ok, res.summary()
            with GroundStation(dataclasses.replace(station, key_file=None, gcs_id=6)) as gs:
                res = dispatch.send(gs.mesh, inputs.simple(Kind.LAND), (1,), source_id=6, timeout_s=10)
                assert "unsigned" in res.outcomes[1].reason, res.summary()
        deadline = time.monotonic() + 5
        while (
            time.monotonic() < deadline
            and len([e for e in events if e.kind is EventKind.SECURITY]) < 6
        ):
            time.sleep(0.05)
        security = [e for e in events if e.kind is EventKind.SECURITY]
        assert len(security) >= 6, [e.text for e in events]
        for name in ("unsigned", "bad signature", "stale", "replayed"):
            assert any(name in e.text for e in security), name
        print(f"{len(security)} SECURITY events, e.g. {security[0].text!r}")
