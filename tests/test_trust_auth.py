"""Per-member signatures (trust/auth.py, trust/identity.py, comms/gate.py): the checks in
isolation, key files and `covey keygen`, then across real agent processes with key files."""

from __future__ import annotations

import dataclasses
import json
import os
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from comms.gate import SKIPPED, Gate, GateConfig, Refusal
from comms.schema import (
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    Event,
    EventKind,
    Mode,
    Role,
    VehicleState,
)
from trust.auth import FleetAuth, FleetKeyError, command_digest, load_auth
from trust.authority import Authority, throwaway_fleet
from trust.identity import read_member_key

T0_NS = 1_700_000_000_000_000_000


class Clock:
    def __init__(self, t_ns: int = T0_NS) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns


@pytest.fixture
def fleet(tmp_path) -> Authority:
    return throwaway_fleet(tmp_path / "keys", "covey", vehicles=range(1, 4), stations=[1, 2])


def member(fleet: Authority, role: Role, mid: int, **kw) -> FleetAuth:
    return load_auth(str(fleet.member_path(role, mid)), **kw)


def takeoff(nonce: int = 7, targets=(1,)) -> Command:
    return Command.takeoff(10.0, nonce=nonce, stamp_ns=0, targets=targets, source_id=1)


def state(vid: int = 1, seq: int = 1, stamp_ns: int = T0_NS) -> VehicleState:
    return VehicleState(
        vid, seq, stamp_ns, (1.0, 2.0, -10.0), (0.0, 0.0, 0.0), 0.0, Mode.HOLDING, True
    )


# -- commands --------------------------------------------------------------------------------
def test_station_signed_command_passes_once_and_everything_else_fails_with_its_reason(
    fleet,
) -> None:
    clock = Clock()
    station, vehicle = (
        member(fleet, Role.STATION, 1, clock_ns=clock),
        member(fleet, Role.VEHICLE, 1, clock_ns=clock),
    )
    cmd = station.sign_command(takeoff())
    assert cmd.stamp_ns == T0_NS and cmd.source_id == 1 and len(cmd.tag) == 64
    assert Command.decode(cmd.encode()) == cmd  # the signature survives the wire
    assert vehicle.check_command(cmd, 1) is None
    assert "replayed" in vehicle.check_command(cmd, 1)
    assert "unsigned" in vehicle.check_command(takeoff(nonce=8), 1)
    signed = station.sign_command(takeoff(10, targets=(1, 2)))
    for tampered in (
        dataclasses.replace(signed, params=(50.0, 0.0, 0.0)),
        dataclasses.replace(signed, targets=(1, 3)),
        dataclasses.replace(signed, kind=CommandKind.KILL, params=(0.0, 0.0, 0.0)),
        dataclasses.replace(signed, seq=1),
        dataclasses.replace(signed, stamp_ns=signed.stamp_ns + 1),
        dataclasses.replace(signed, tag=bytes([signed.tag[0] ^ 1]) + signed.tag[1:]),
        dataclasses.replace(signed, source_id=2),  # station 2 exists, but did not sign it
    ):
        assert "bad signature" in vehicle.check_command(tampered, 1)
    clock.t_ns += 6 * 10**9
    assert "stale" in vehicle.check_command(signed, 1)
    clock.t_ns -= 12 * 10**9
    assert "stale" in vehicle.check_command(signed, 1)  # from the future too
    assert vehicle.rejected == 11


def test_a_captured_vehicle_key_cannot_command_anyone_not_even_itself(fleet) -> None:
    clock = Clock()
    captured = member(fleet, Role.VEHICLE, 2, clock_ns=clock)
    with pytest.raises(FleetKeyError, match="only a station key"):
        captured.sign_command(takeoff())
    victim, itself = (
        member(fleet, Role.VEHICLE, 1, clock_ns=clock),
        member(fleet, Role.VEHICLE, 2, clock_ns=clock),
    )
    for source_id in (2, 1, 9):  # as "station 2" (its vehicle id), as station 1, as an unknown one
        forged = dataclasses.replace(
            takeoff(nonce=source_id, targets=()), stamp_ns=T0_NS, source_id=source_id
        )
        forged = dataclasses.replace(forged, tag=captured._sign("cmd", forged.signed_bytes()))
        for vid, auth in ((1, victim), (2, itself)):
            reason = auth.check_command(forged, vid)
            assert reason is not None and (
                "bad signature" in reason or "unknown signer" in reason
            ), reason


def test_a_signature_for_one_fleet_is_refused_in_another(tmp_path) -> None:
    """Fleet beta shares every key with fleet covey (one operator, two rosters); a command
    signed for covey and replayed into beta still fails: the fleet name is in what is signed."""
    covey = throwaway_fleet(tmp_path / "covey", "covey", vehicles=[1], stations=[1])
    beta_dir = tmp_path / "beta"
    beta_dir.mkdir()
    (beta_dir / "authority.key").write_text(
        json.dumps(
            {**json.loads((tmp_path / "covey" / "authority.key").read_text()), "fleet": "beta"}
        )
    )
    (beta_dir / "authority.key").chmod(0o600)
    from trust.identity import sign_roster

    beta_roster = sign_roster(covey.key, dataclasses.replace(covey.roster, fleet="beta"))
    key = read_member_key(covey.member_path(Role.VEHICLE, 1))
    beta_vehicle = FleetAuth(
        dataclasses.replace(key, fleet="beta", roster=beta_roster), clock_ns=Clock()
    )
    covey_station = member(covey, Role.STATION, 1, clock_ns=Clock())
    cmd = covey_station.sign_command(takeoff())
    assert member(covey, Role.VEHICLE, 1, clock_ns=Clock()).check_command(cmd, 1) is None  # control
    assert "bad signature" in beta_vehicle.check_command(cmd, 1)
    signed_state = member(covey, Role.VEHICLE, 1).sign_state(state())
    assert member(covey, Role.STATION, 1).check_state(signed_state) is None  # control
    assert "bad signature" in beta_vehicle.check_state(signed_state)
    # And a covey member refuses to join beta outright.
    with pytest.raises(FleetKeyError, match="fleet 'covey'"):
        load_auth(str(covey.member_path(Role.VEHICLE, 1)), fleet="beta")


def test_acks_are_bound_to_the_exact_command_they_answer(fleet) -> None:
    clock = Clock()
    station, v1 = (
        member(fleet, Role.STATION, 1, clock_ns=clock),
        member(fleet, Role.VEHICLE, 1, clock_ns=clock),
    )
    a = station.sign_command(takeoff(nonce=1))
    b = station.sign_command(takeoff(nonce=2))
    da, db = command_digest(a.encode()), command_digest(b.encode())
    ack_a = v1.sign_ack(CommandAck(1, a.nonce, T0_NS, AckResult.ACCEPTED, "", Mode.TAKING_OFF), da)
    assert station.check_ack(ack_a, a, da) is None
    # Replayed as the answer to b, even with b's nonce swapped in: forged.
    assert "forged ack" in station.check_ack(ack_a, b, db)
    assert "forged ack" in station.check_ack(dataclasses.replace(ack_a, nonce=b.nonce), b, db)
    # An ack to an undecodable command (nonce 0) cannot be replayed for any real command either.
    ack0 = v1.sign_ack(
        CommandAck(1, 0, T0_NS, AckResult.REJECTED, "malformed"), command_digest(b"junk")
    )
    assert "forged ack" in station.check_ack(ack0, a, da)
    # Vehicle 2 cannot sign for vehicle 1; unsigned acks are reported too.
    v2 = member(fleet, Role.VEHICLE, 2, clock_ns=clock)
    assert "forged ack" in station.check_ack(
        v2.sign_ack(dataclasses.replace(ack_a, tag=bytes(64)), da), a, da
    )
    assert "unsigned" in station.check_ack(dataclasses.replace(ack_a, tag=bytes(64)), a, da)
    lie = dataclasses.replace(ack_a, result=AckResult.REJECTED, reason="no")
    assert "it said: rejected: no" in station.check_ack(lie, a, da)


def test_nonce_cache_is_bounded_and_thread_safe(fleet) -> None:
    clock = Clock()
    station = member(fleet, Role.STATION, 1, clock_ns=clock)
    auth = member(fleet, Role.VEHICLE, 1, clock_ns=clock, replay_window=100)
    first = [station.sign_command(takeoff(nonce=n)) for n in range(1, 101)]
    assert all(auth.check_command(c, 1) is None for c in first)
    clock.t_ns += 1
    assert auth.check_command(station.sign_command(takeoff(nonce=1000)), 1) is None
    assert len(auth._seen) == 100
    assert all(auth.check_command(c, 1) is not None for c in first)  # replays still refused
    fresh = member(fleet, Role.VEHICLE, 1, clock_ns=clock)
    cmds = [station.sign_command(takeoff(nonce=n)) for n in range(2000, 2200)]
    accepted: list[int] = []
    lock = threading.Lock()

    def worker() -> None:
        for c in cmds:
            if fresh.check_command(c, 1) is None:
                with lock:
                    accepted.append(c.nonce)

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(accepted) == list(range(2000, 2200))  # each exactly once


# -- rosters ---------------------------------------------------------------------------------
def test_a_newer_roster_revokes_and_an_old_or_foreign_one_is_refused(fleet, tmp_path) -> None:
    clock = Clock()
    vehicle = member(fleet, Role.VEHICLE, 1, clock_ns=clock)
    s1, s2 = (
        member(fleet, Role.STATION, 1, clock_ns=clock),
        member(fleet, Role.STATION, 2, clock_ns=clock),
    )
    old = fleet.roster
    assert vehicle.check_command(s2.sign_command(takeoff(nonce=1)), 1) is None
    fleet.revoke(Role.STATION, 2)
    assert not fleet.member_path(Role.STATION, 2).exists()
    assert vehicle.apply_roster(fleet.roster) is None
    assert "unknown signer" in vehicle.check_command(s2.sign_command(takeoff(nonce=2)), 1)
    assert vehicle.check_command(s1.sign_command(takeoff(nonce=3)), 1) is None
    assert "not newer" in vehicle.apply_roster(old)  # no rollback to a roster that lists station 2
    other = throwaway_fleet(tmp_path / "other", "covey", vehicles=[1], stations=[2])
    for _ in range(5):
        other.add(Role.VEHICLE, 10 + _)
    assert "authority" in vehicle.apply_roster(other.roster)  # another authority's roster
    tampered = dataclasses.replace(fleet.roster, version=fleet.roster.version + 1)
    assert "authority" in vehicle.apply_roster(tampered)
    # A member whose file's roster no longer lists it refuses to start.
    fleet.revoke(Role.VEHICLE, 3)
    with pytest.raises(FleetKeyError, match="does not exist"):
        read_member_key(fleet.member_path(Role.VEHICLE, 3))


# -- states and the gate -----------------------------------------------------------------------
def test_gate_drops_unsigned_forged_stale_replayed_out_of_order_and_phantom_states(fleet) -> None:
    clock = Clock()
    v1, v2 = (
        member(fleet, Role.VEHICLE, 1, clock_ns=clock),
        member(fleet, Role.VEHICLE, 2, clock_ns=clock),
    )
    lines: list[str] = []
    gate = Gate(member(fleet, Role.STATION, 1), GateConfig(), on_summary=lines.append)
    t = T0_NS
    assert gate.admit_state(v1.sign_state(state(1, 1, t)), t) is None
    assert gate.admit_state(state(1, 2, t + 1), t + 1) is Refusal.UNSIGNED
    assert (
        gate.admit_state(dataclasses.replace(v2.sign_state(state(1, 2, t + 1))), t + 1)
        is Refusal.FORGED
    )
    assert gate.admit_state(v2.sign_state(state(2, 2, t + 1)), t + 1) is None  # its own: fine
    assert gate.admit_state(v1.sign_state(state(9, 1, t)), t) is Refusal.UNKNOWN  # a phantom id
    assert gate.admit_state(v1.sign_state(state(1, 1, t)), t + 2) is Refusal.REPLAYED
    assert gate.admit_state(v1.sign_state(state(1, 0, t - 1)), t + 2) is Refusal.OUT_OF_ORDER
    recorded = v1.sign_state(state(1, 5, t + 10))
    later = t + 60 * 10**9
    assert gate.admit_state(recorded, later) is Refusal.STALE  # a recording re-sent a minute later
    tampered = dataclasses.replace(v1.sign_state(state(1, 6, later)), pos_ned_m=(50.0, 0.0, -10.0))
    assert gate.admit_state(tampered, later) is Refusal.FORGED
    assert gate.admit_state(v1.sign_state(state(1, 7, later)), later) is None
    assert gate.refused[Refusal.FORGED] == 2 and gate.accepted == 3
    assert {m for m in gate._last} == {1, 2}  # phantoms never enter the table
    # One summary per cause per second, however many refusals.
    lines.clear()
    for i in range(500):
        gate.admit_state(state(1, 100 + i, later + i * 1000), later + i * 1000)
    assert len(lines) == 1 and "refused 1 unsigned state " in lines[0], lines  # the first at once
    gate.admit_state(state(1, 1000, later + 2 * 10**9), later + 2 * 10**9)
    assert len(lines) == 2 and "refused 500 unsigned states" in lines[1], lines  # then a summary


def test_thinning_skips_only_genuine_extras_and_a_forger_cannot_use_it(fleet) -> None:
    v1 = member(fleet, Role.VEHICLE, 1)
    v2 = member(fleet, Role.VEHICLE, 2)
    gate = Gate(member(fleet, Role.VEHICLE, 3), GateConfig(min_interval_s=0.15))
    t = T0_NS
    ms = 10**6
    assert gate.admit_state(v1.sign_state(state(1, 1, t)), t) is None
    assert gate.admit_state(v1.sign_state(state(1, 2, t + 100 * ms)), t + 100 * ms) is SKIPPED
    # Forged states right before each real one: refused, and they do not move "last accepted".
    assert (
        gate.admit_state(v2.sign_state(state(1, 3, t + 190 * ms)), t + 190 * ms) is Refusal.FORGED
    )
    assert gate.admit_state(v1.sign_state(state(1, 3, t + 200 * ms)), t + 200 * ms) is None


def test_events_are_signed_by_their_vehicle(fleet) -> None:
    v1, v2 = member(fleet, Role.VEHICLE, 1), member(fleet, Role.VEHICLE, 2)
    gate = Gate(member(fleet, Role.STATION, 1), what="event")
    now = time.time_ns()
    ev = Event(1, now, "battery low", kind=EventKind.FAILSAFE)
    assert gate.admit_event(v1.sign_event(ev), now) is None
    assert gate.admit_event(v2.sign_event(ev), now) is Refusal.FORGED
    assert gate.admit_event(ev, now) is Refusal.UNSIGNED
    assert Event.decode(v1.sign_event(ev).encode()).sig  # the signature survives the wire


def test_guidance_traces_are_signed_by_their_vehicle(fleet) -> None:
    from comms.schema import GuidanceTrace

    v1, v2 = member(fleet, Role.VEHICLE, 1), member(fleet, Role.VEHICLE, 2)
    station = member(fleet, Role.STATION, 1)
    tr = GuidanceTrace(1, 5, time.time_ns(), 0.5, (1.0, 0.0, 0.0), ((2, 3, 0.1),))
    signed = GuidanceTrace.decode(v1.sign_trace(tr).encode())  # the signature survives the wire
    assert signed.sig and station.check_trace(signed) is None
    assert "bad signature" in station.check_trace(v2.sign_trace(tr))
    assert station.check_trace(tr) is not None  # unsigned
    assert station.check_trace(dataclasses.replace(signed, state_seq=6)) is not None


# -- key files and keygen ----------------------------------------------------------------------
def test_keygen_init_add_revoke_list_and_file_modes(tmp_path, capsys) -> None:
    from groundstation.keygen_cli import keygen_cli

    d = str(tmp_path / "fleet")
    assert keygen_cli(["init", "--dir", d, "--fleet", "alpha"]) == 0
    assert keygen_cli(["init", "--dir", d]) == 1  # never overwrites an authority
    for who in (["vehicle", "1"], ["vehicle", "2"], ["station", "1"]):
        assert keygen_cli(["add", "--dir", d, *who]) == 0
    assert keygen_cli(["add", "--dir", d, "vehicle", "1"]) == 1  # already enrolled
    for name in ("authority.key", "vehicle-1.key", "station-1.key"):
        assert stat.S_IMODE((tmp_path / "fleet" / name).stat().st_mode) == 0o600
    doc = json.loads((tmp_path / "fleet" / "vehicle-1.key").read_text())
    assert sorted(doc) == [
        "authority_public_key",
        "covey",
        "fleet",
        "id",
        "private_key",
        "role",
        "roster",
        "version",
    ]
    key = read_member_key(tmp_path / "fleet" / "vehicle-1.key")  # refreshed with the latest roster
    assert key.roster.version == 4 and len(key.roster.members) == 3
    assert keygen_cli(["revoke", "--dir", d, "vehicle", "2"]) == 0
    assert keygen_cli(["revoke", "--dir", d, "vehicle", "2"]) == 1
    capsys.readouterr()
    assert keygen_cli(["list", "--dir", d]) == 0
    out = capsys.readouterr().out
    assert "roster v5, 2 members" in out and "vehicle      1" in out and "vehicle      2" not in out
    with pytest.raises(SystemExit) as exc:
        keygen_cli(["add", "--dir", d, "vehicle", "70000"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        keygen_cli(["list", "--dir", str(tmp_path / "nothing")])
    assert exc.value.code == 2


def test_key_files_that_cannot_be_used_refuse_to_start(fleet, tmp_path, caplog) -> None:
    good = fleet.member_path(Role.VEHICLE, 1)

    def bad(name: str, content: bytes | str, mode: int = 0o600) -> str:
        p = tmp_path / name
        p.write_bytes(content if isinstance(content, bytes) else content.encode())
        p.chmod(mode)
        return str(p)

    doc = json.loads(good.read_text())
    cases = {
        "": "path is empty",
        str(tmp_path / "missing.key"): "does not exist",
        str(tmp_path): "not a regular file",
        bad("loose.key", good.read_text(), 0o644): "chmod 600",
        bad("old.key", "ab" * 32 + "\n"): "shared fleet key from an older covey",
        bad("binary.key", b"\xff\xfe\x00garbage"): "not UTF-8 text",
        bad("list.key", "[1, 2]"): "not a JSON object",
        bad("other.key", '{"covey": "something"}'): "not a covey member key file",
        bad("noid.key", json.dumps({**doc, "id": "one"})): "'id' is missing or not a int",
        bad("badhex.key", json.dumps({**doc, "private_key": "zz"})): "not hex",
        bad("short.key", json.dumps({**doc, "private_key": "00" * 31})): "must be 32 bytes",
        bad(
            "badroster.key", json.dumps({**doc, "roster": doc["roster"][:-2]})
        ): "roster is malformed",
        bad("swapped.key", json.dumps({**doc, "id": 2})): "not in its roster",
        bad("foreign.key", json.dumps({**doc, "authority_public_key": "11" * 32})): "authority",
        str(fleet.dir / "authority.key"): "AUTHORITY key",
    }
    for path, why in cases.items():
        with pytest.raises(FleetKeyError, match=why):
            load_auth(path, env={})
    with pytest.raises(FleetKeyError, match="no longer supported"):
        load_auth(None, env={"COVEY_FLEET_KEY": "ab" * 32})
    with pytest.raises(FleetKeyError, match="path is empty"):
        load_auth(None, env={"COVEY_FLEET_KEY_FILE": ""})  # an empty variable is not open mode
    assert load_auth(None, env={"COVEY_FLEET_KEY_FILE": str(good)}).member_id == 1
    with caplog.at_level("WARNING"):
        assert load_auth(None, env={}) is None
    assert "OPEN MODE" in caplog.text


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_an_unreadable_key_file_is_one_line(fleet) -> None:
    p = fleet.member_path(Role.VEHICLE, 1)
    p.chmod(0o000)
    with pytest.raises(FleetKeyError, match="cannot read"):
        load_auth(str(p))


# -- across real processes -------------------------------------------------------------------
@pytest.mark.e2e
def test_agents_with_key_files_accept_only_station_signed_fresh_commands(procs, fleet) -> None:
    from comms.commands import OutcomeStatus, new_nonce
    from comms.mesh import Mesh
    from comms.session import embedded_peer, embedded_router, free_tcp_port

    port = free_tcp_port()
    events: list[Event] = []
    station = member(fleet, Role.STATION, 1)
    with Mesh(embedded_router(port), auth=station) as gcs:
        gcs.subscribe_events(lambda e, _t: events.append(e))
        presence = gcs.presence()
        for vid in (1, 2):
            procs.start(
                "-m",
                "covey_cli",
                "agent",
                "--key-file",
                str(fleet.member_path(Role.VEHICLE, vid)),
                "--id",
                str(vid),
                "--connect",
                f"tcp/127.0.0.1:{port}",
                f"--start-ne-m={3 * vid},0",
                "--no-gcs-failsafe",
            )
        assert presence.wait_for(lambda v, _g: v >= {1, 2}, timeout_s=60), "agents did not come up"
        with Mesh(embedded_peer(port)) as raw:  # open mode: sends exactly what it is given
            time.sleep(0.5)

            def raw_send(cmd: Command, vid: int):
                return raw.send_command(cmd, expect=(vid,), timeout_s=5).outcomes[vid]

            captured = member(fleet, Role.VEHICLE, 2)
            as_station = dataclasses.replace(
                takeoff(nonce=new_nonce(), targets=(1,)), stamp_ns=time.time_ns(), source_id=2
            )
            as_station = dataclasses.replace(
                as_station, tag=captured._sign("cmd", as_station.signed_bytes())
            )
            self_cmd = dataclasses.replace(as_station, targets=(2,), nonce=new_nonce())
            self_cmd = dataclasses.replace(
                self_cmd, tag=captured._sign("cmd", self_cmd.signed_bytes())
            )
            retargeted = station.sign_command(takeoff(nonce=0, targets=(1,)))
            outcomes = {
                "unsigned": raw_send(
                    Command.takeoff(5.0, nonce=new_nonce(), stamp_ns=time.time_ns(), targets=(1,)),
                    1,
                ),
                "captured vehicle key": raw_send(as_station, 1),
                "captured key, itself": raw_send(self_cmd, 2),
                "tampered params": raw_send(
                    dataclasses.replace(station.sign_command(takeoff(0)), params=(100.0, 0.0, 0.0)),
                    1,
                ),
                "stale": raw_send(
                    member(
                        fleet, Role.STATION, 1, clock_ns=lambda: time.time_ns() - 60 * 10**9
                    ).sign_command(takeoff(0)),
                    1,
                ),
                "for 1, sent to 2": _send_to(raw, retargeted, 2),
            }
            expected = {
                "unsigned": "unsigned",
                "captured vehicle key": "bad signature",
                "captured key, itself": "bad signature",
                "tampered params": "bad signature",
                "stale": "stale",
                "for 1, sent to 2": "not for this vehicle",
            }
            for name, outcome in outcomes.items():
                assert outcome.status is OutcomeStatus.REJECTED, (name, outcome)
                assert expected[name] in outcome.reason, (name, outcome.reason)
                assert outcome.ack is not None and outcome.ack.tag != bytes(
                    64
                )  # the refusal is signed
            ok = gcs.send_command(
                Command.takeoff(5.0, nonce=new_nonce(), stamp_ns=0, targets=(1,)), timeout_s=5
            )
            assert ok.ok, ok.summary()
            replayed = raw_send(ok.command, 1)  # the exact bytes again: a replay
            assert replayed.status is OutcomeStatus.REJECTED and "replayed" in replayed.reason
            both = gcs.send_command(
                Command(CommandKind.HOLD, new_nonce(), 0), expect=(1, 2), timeout_s=5
            )
            assert set(both.outcomes) == {1, 2} and all(
                o.ack is not None for o in both.outcomes.values()
            )
            # The real `covey cmd`: with a station key accepted; with a vehicle key or none refused.
            run = [
                sys.executable,
                "-m",
                "covey_cli",
                "cmd",
                "land",
                "--to",
                "all",
                "--connect",
                f"tcp/127.0.0.1:{port}",
            ]
            env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parent.parent))
            env.pop("COVEY_FLEET_KEY_FILE", None)
            signed = subprocess.run(
                [*run, "--key-file", str(fleet.member_path(Role.STATION, 2))],
                capture_output=True,
                text=True,
                timeout=60,
                env=env,
            )
            vehicle_key = subprocess.run(
                [*run, "--key-file", str(fleet.member_path(Role.VEHICLE, 1))],
                capture_output=True,
                text=True,
                timeout=60,
                env=env,
            )
            unsigned = subprocess.run(run, capture_output=True, text=True, timeout=60, env=env)
            assert "accepted" in signed.stdout and "unsigned" not in signed.stdout, (
                signed.stdout + signed.stderr
            )
            assert vehicle_key.returncode == 2 and "only a station key" in vehicle_key.stderr, (
                vehicle_key.stderr
            )
            assert (
                "Traceback" not in vehicle_key.stderr
                and len(vehicle_key.stderr.strip().splitlines()) == 1
            )
            assert "unsigned" in unsigned.stdout and "OPEN MODE" in unsigned.stderr, (
                unsigned.stdout + unsigned.stderr
            )
        deadline = time.monotonic() + 5
        while (
            time.monotonic() < deadline
            and len([e for e in events if e.kind is EventKind.SECURITY]) < 6
        ):
            time.sleep(0.05)
        security = [e for e in events if e.kind is EventKind.SECURITY]
        for name in ("unsigned", "bad signature", "stale", "replayed", "not for this vehicle"):
            assert any(name in e.text for e in security), (name, [e.text for e in security])
        assert all(e.sig for e in events)  # every event the station let in was signed
        print(f"{len(security)} SECURITY events, e.g. {security[0].text!r}")


def _send_to(mesh, cmd: Command, vid: int):
    """Send `cmd` (addressed to others) on vehicle `vid`'s own command key, as a retargeting
    attacker would; the vehicle must answer, signed, instead of staying silent."""
    import zenoh

    from comms import keys
    from comms.commands import Outcome

    replies = mesh.session.get(
        keys.cmd(mesh.fleet, vid), payload=cmd.encode(), timeout=5.0, target=zenoh.QueryTarget.ALL
    )
    for reply in replies:
        if reply.ok is not None:
            ack = CommandAck.decode(reply.ok.payload.to_bytes())
            return Outcome.from_ack(ack, 0.0)
    raise AssertionError(f"vehicle {vid} did not answer a command sent to it for others")
