"""Revocation that always arrives: the roster follower (trust/roster_sync.py) on its own and
through the shipped mTLS + access-control configs (made by `covey tls init`).

Unit level (one real Zenoh session each): a roster's size and header are read before anything
else, what is not newer is dropped undecoded and unverified, the signature is checked before the
members are decoded, a flood of forged rosters becomes one summary line a second, an authentic
older roster is answered by one re-publish.

End to end: a `covey router` with the generated router config, two keyed `covey agent`
processes and a keyed station as TLS clients, the authority's pusher with a station
certificate. A revocation reaches every member within 1 s, also at the end of a 10 s keyless
flood (60/s) of forged rosters of the largest size the routers pass; `covey keygen push` works
with only `--connect tls/...` and `--zenoh-config` and says who confirmed; a vehicle rebooted
from an old key file while the rest of the fleet is down catches up within about a second of
the fleet's return and refuses the revoked station.
"""

from __future__ import annotations

import os
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from comms.commands import OutcomeStatus, new_nonce
from comms.doc_sync import Offer, RosterSyncConfig, confirmations
from comms.mesh import Mesh
from comms.schema import (
    MAX_ROSTER_BYTES,
    Command,
    CommandKind,
    DecodeError,
    EventKind,
    Member,
    Role,
    Roster,
)
from comms.session import MeshConfig, free_tcp_port
from trust.auth import FleetAuth, load_auth
from trust.authority import Authority, throwaway_fleet
from trust.identity import member_doc, read_member_key, write_private_file
from trust.roster_sync import RosterSync
from trust.tls_setup import TlsConfig, init

FLEET = "revoke"
REPO = Path(__file__).resolve().parent.parent


def forged_roster(version: int, n_members: int = 4096, fleet: str = FLEET) -> bytes:
    """A well-formed roster with random keys and a random signature (no authority's)."""
    rng = random.Random(version)
    members = tuple(
        Member(Role.VEHICLE if i >= 8 else Role.STATION, i + 1, rng.randbytes(32))
        for i in range(n_members)
    )
    members = tuple(sorted(members, key=lambda m: (int(m.role), m.member_id)))
    return Roster(fleet, version, time.time_ns(), members, rng.randbytes(64)).encode()


def lone_member(tmp_path: Path, port: int = 0) -> tuple[Authority, FleetAuth, Mesh]:
    """A keyed vehicle alone on a peer mesh listening on `port` (0: any)."""
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1])
    auth = load_auth(str(authority.member_path(Role.VEHICLE, 1)))
    cfg = MeshConfig(fleet=FLEET, mode="peer", connect=(), listen=(f"tcp/127.0.0.1:{port}",))
    return authority, auth, Mesh(cfg, auth=auth)


class Counting:
    """Counts calls of a function it wraps (monkeypatched in place)."""

    def __init__(self, fn) -> None:
        self.fn, self.calls = fn, 0

    def __call__(self, *a, **kw):
        self.calls += 1
        return self.fn(*a, **kw)


# -- the wire --------------------------------------------------------------------------------------
def test_peek_reads_the_header_and_refuses_an_oversized_roster_first(tmp_path) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1, 2], stations=[1])
    data = authority.roster.encode()
    head = Roster.peek(data)
    assert (head.fleet, head.version, head.n_members) == (FLEET, authority.roster.version, 3)
    assert head.signed == authority.roster.signed_bytes() and head.sig == authority.roster.sig
    assert len(forged_roster(5)) == MAX_ROSTER_BYTES  # the largest roster is exactly the limit
    for bad, why in (
        (b"\x00" * (MAX_ROSTER_BYTES + 1), "at most"),  # size first: not even the type is read
        (data + b"\x00", "must be"),
        (data[:-1], "must be"),
        (data[:20], "too short"),
        (b"\x01" + data[1:], "expected message type"),
        (data[:1] + b"\x09" + data[2:], "unsupported ROSTER version"),
        (data[:2] + b"bad fleet!" + data[12:], "fleet"),
    ):
        with pytest.raises(DecodeError, match=why):
            Roster.peek(bad)
    assert Roster.decode(data) == authority.roster


# -- the follower ----------------------------------------------------------------------------------
def test_offer_checks_cheapest_first_and_applies_only_the_authoritys_newer_roster(
    tmp_path, monkeypatch
) -> None:
    authority, auth, mesh = lone_member(tmp_path)
    with mesh:
        sync = mesh.roster_sync
        assert sync is not None
        held = auth.roster.version
        authority.revoke(Role.STATION, 1)  # the authority's next roster, not yet offered
        newer = authority.roster.encode()
        decodes = Counting(Roster.decode)
        verifies = Counting(__import__("trust.roster_sync").roster_sync.verify)
        monkeypatch.setattr(Roster, "decode", decodes)
        monkeypatch.setattr("trust.roster_sync.verify", verifies)
        # Not newer: dropped on the header, neither verified nor decoded.
        assert sync.offer(forged_roster(held)) is Offer.SAME
        assert (decodes.calls, verifies.calls) == (0, 0)
        # Newer but forged: verified (refused), never decoded.
        for k in range(5):
            assert sync.offer(forged_roster(held + 1 + k)) is Offer.REFUSED
        assert (decodes.calls, verifies.calls) == (0, 5)
        assert auth.roster.version == held
        # Malformed and another fleet's: refused on the header.
        assert sync.offer(b"\x05\x01junk") is Offer.REFUSED
        assert sync.offer(forged_roster(held + 9, 8, fleet="other")) is Offer.REFUSED
        assert (decodes.calls, verifies.calls) == (0, 5)
        # The authority's newer roster: verified, decoded, applied.
        assert sync.offer(newer) is Offer.APPLIED
        assert (decodes.calls, verifies.calls) == (1, 6)
        assert auth.roster.version == held + 1 and not auth.is_member(Role.STATION, 1)
        assert mesh.stats.rosters_applied == 1
        counts = sync.counts()
        assert counts["refused: forged"] == 5 and counts["refused: malformed"] == 1
        assert counts["refused: other fleet"] == 1 and counts["applied"] == 1


def test_a_flood_of_forged_rosters_is_one_summary_line_a_second(tmp_path) -> None:
    _, auth, mesh = lone_member(tmp_path)
    now = [0]
    lines: list[str] = []
    with mesh:
        sync = RosterSync(
            mesh.session,
            FLEET,
            auth,
            RosterSyncConfig(pull_every_s=60.0),
            on_summary=lines.append,
            mono_ns=lambda: now[0],
        )
        try:
            payloads = [forged_roster(auth.roster.version + 1 + k, 64) for k in range(50)]
            for second in range(3):
                now[0] = second * 1_000_000_000
                for data in payloads:
                    sync.offer(data)
        finally:
            sync.undeclare()
    # 150 forged rosters over three seconds: three lines, the later ones with the count.
    assert len(lines) == 3, lines
    assert "refused a roster (forged)" in lines[0]
    assert lines[1].startswith("refused 50 rosters (forged)"), lines


def test_an_authentic_older_roster_is_answered_once_and_a_forged_one_never(tmp_path) -> None:
    port = free_tcp_port()
    authority, auth, mesh = lone_member(tmp_path, port)
    old = authority.roster.encode()
    authority.add(Role.VEHICLE, 2)
    with mesh:
        assert mesh.roster_sync.offer(authority.roster.encode()) is Offer.APPLIED
        heard: list[int] = []
        with Mesh(
            MeshConfig(
                fleet=FLEET,
                mode="peer",
                connect=(f"tcp/127.0.0.1:{port}",),
                listen=("tcp/127.0.0.1:0",),
            )
        ) as other:
            other.session.declare_subscriber(
                f"covey/{FLEET}/roster",
                lambda s: heard.append(Roster.peek(s.payload.to_bytes()).version),
            )
            time.sleep(0.5)
            # A forged older roster: no answer (it would make the fleet an amplifier).
            forged_old = forged_roster(1, 8)
            for _ in range(3):
                other.session.put(f"covey/{FLEET}/roster", forged_old)
            time.sleep(1.0)
            assert auth.roster.version not in heard
            # An authentic older roster: one re-publish of the newer one, after a short delay.
            time.sleep(1.0)  # past the re-publish interval
            for _ in range(5):
                other.session.put(f"covey/{FLEET}/roster", old)
            deadline = time.monotonic() + 3
            while time.monotonic() < deadline and auth.roster.version not in heard:
                time.sleep(0.05)
            time.sleep(0.3)
    assert heard.count(auth.roster.version) == 1, heard
    assert mesh.roster_sync.counts()["republished"] == 1


def test_a_member_pulls_when_its_router_comes_back(tmp_path) -> None:
    """A client that was cut off while the roster changed catches up on the new link, not at its
    next periodic pull (set to a minute here)."""
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1, 2])
    member = load_auth(str(authority.member_path(Role.VEHICLE, 1)))
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    router_cfg = MeshConfig(fleet=FLEET, mode="router", connect=(), listen=(ep,))
    slow = RosterSyncConfig(pull_every_s=60.0)
    with (
        Mesh(router_cfg) as router,
        Mesh(
            MeshConfig(fleet=FLEET, mode="client", connect=(ep,)), auth=member, roster_sync=slow
        ) as client,
    ):
        assert wait_for(lambda: client.roster_sync.counts().get("pulls", 0) >= 1, 5)
        router.close()  # the router goes; the roster changes while it is away
        authority.revoke(Role.STATION, 2)
        held = load_auth(str(authority.member_path(Role.STATION, 1)))
        time.sleep(1.0)
        assert client.auth.roster.version < held.roster.version
        # The router comes back as a keyed station that holds the new roster (its own start
        # pull found nobody: the client has not linked yet).
        with Mesh(router_cfg, auth=held, roster_sync=slow):
            took = wait_for(lambda: client.auth.roster.version == held.roster.version, 10)
        assert took is not None, client.roster_sync.counts()
        assert not client.auth.is_member(Role.STATION, 2)
        assert client.roster_sync.counts()["pulls"] >= 2  # the start and the new link
    print(f"caught up {took:.2f} s after the router came back")


# -- end to end through the shipped configs --------------------------------------------------------
FLOOD = r"""
import struct, sys, time
from comms import keys
from comms.mesh import Mesh
from comms.session import MeshConfig
fleet, ep, conf, rate, dur, base, path = sys.argv[1:8]
data = bytearray(open(path, "rb").read())
with Mesh(MeshConfig(fleet=fleet, mode="client", connect=(ep,), config_file=conf)) as m:
    print("READY", flush=True)
    t0, n = time.monotonic(), 0
    while time.monotonic() - t0 < float(dur):
        struct.pack_into("<I", data, 34, int(base) + n)  # a new forged version each time
        m.session.put(keys.roster(fleet), bytes(data))
        n += 1
        time.sleep(max(0.0, t0 + n / float(rate) - time.monotonic()))
    print(f"SENT {n} in {time.monotonic() - t0:.1f} s", flush=True)
"""


class Fleet:
    """Certificates, configs and the fleet authority of one secured test fleet."""

    def __init__(self, tmp: Path) -> None:
        self.tls = tmp / "tls"
        init(
            TlsConfig(
                directory=self.tls,
                names=("router", "gcs-1", "gcs-2", "vehicle-1", "vehicle-2", "vehicle-3"),
            )
        )
        self.authority = throwaway_fleet(tmp / "keys", FLEET, vehicles=[1, 2, 3], stations=[1, 2])
        self.first_roster = self.authority.roster
        self.port = free_tcp_port()
        self.connect = f"tls/localhost:{self.port}"
        self.tmp = tmp

    def client(self, name: str) -> MeshConfig:
        return MeshConfig(
            fleet=FLEET,
            mode="client",
            connect=(self.connect,),
            config_file=str(self.tls / f"{name}.json5"),
        )

    def agent(self, procs, vid: int, key_file: Path | None = None):
        return procs.start(
            "-m",
            "covey_cli",
            "agent",
            "--id",
            str(vid),
            "--fleet",
            FLEET,
            "--key-file",
            str(key_file or self.authority.member_path(Role.VEHICLE, vid)),
            "--mesh-mode",
            "client",
            "--connect",
            self.connect,
            "--zenoh-config",
            str(self.tls / f"vehicle-{vid}.json5"),
            "--no-gcs-failsafe",
        )

    def holders(self, session, version: int, exclude: set[str] = frozenset()) -> set[str]:
        return {
            c.replier
            for c in confirmations(session, FLEET, version, timeout_s=0.3)
            if c.replier not in exclude
        }


def wait_for(pred, timeout_s: float, period_s: float = 0.02) -> float | None:
    """Seconds until `pred()` held, or None."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if pred():
            return time.monotonic() - t0
        time.sleep(period_s)
    return None


def hold_from(mesh: Mesh, vid: int):
    return mesh.send_command(
        Command(CommandKind.HOLD, new_nonce(), 0, targets=(vid,)), timeout_s=3.0
    ).outcomes[vid]


def signer_accepted(outcome) -> bool:
    """The vehicle answered and took the station's signature (a landed vehicle may still refuse a
    hold for its own reasons, with its signed ack)."""
    auth_refusals = ("unsigned", "unknown signer", "bad signature", "stale", "replayed")
    return outcome.status is OutcomeStatus.ACCEPTED or (
        outcome.status is OutcomeStatus.REJECTED and not outcome.reason.startswith(auth_refusals)
    )


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.skipif(sys.platform != "linux", reason="loopback TLS fleet")
def test_revocation_through_the_shipped_mtls_acl_configs_within_a_second(tmp_path, procs) -> None:
    f = Fleet(tmp_path)
    router = procs.start(
        "-m",
        "covey_cli",
        "router",
        "--listen",
        f"tls/127.0.0.1:{f.port}",
        "--zenoh-config",
        str(f.tls / "router.json5"),
    )
    router.wait_for("READY", 30)
    s1 = load_auth(str(f.authority.member_path(Role.STATION, 1)))
    s2 = load_auth(str(f.authority.member_path(Role.STATION, 2)))
    agents = {vid: f.agent(procs, vid) for vid in (1, 2)}
    numbers: dict[str, float] = {}
    with (
        Mesh(f.client("gcs-1"), auth=s1) as station,
        Mesh(f.client("gcs-2"), auth=s2) as station2,
        Mesh(f.client("gcs-1")) as pusher,  # the authority's tool: a station's certificate, no key
    ):
        presence = station.presence()
        assert presence.wait_for(lambda v, _g: {1, 2} <= set(v), timeout_s=60), (
            "the agents did not join through the TLS router"
        )
        assert signer_accepted(hold_from(station2, 1))  # control: enrolled
        members = 4  # two agents, two stations

        # 1. A revocation (vehicle 3) through the router: every member within 1 s.
        f.authority.revoke(Role.VEHICLE, 3)
        v = f.authority.roster.version
        t0 = time.monotonic()
        pusher.publish_roster(f.authority.roster)
        took = wait_for(lambda: len(f.holders(pusher.session, v)) >= members, 5)
        assert took is not None, f"members holding v{v}: {f.holders(pusher.session, v)}"
        numbers["quiet"] = time.monotonic() - t0
        assert numbers["quiet"] < 1.0, numbers

        # 2. The same at the end of a 10 s keyless flood of forged rosters of the largest size
        # the router passes (an insider's certificate, vehicle 3's, and no fleet key).
        forged = tmp_path / "forged.bin"
        forged.write_bytes(forged_roster(1_000_000))
        assert len(forged.read_bytes()) == MAX_ROSTER_BYTES
        security: list[str] = []
        station.subscribe_events(
            lambda e, _t: security.append(e.text) if e.kind == EventKind.SECURITY else None
        )
        flood = procs.start(
            "-c",
            FLOOD,
            FLEET,
            f.connect,
            str(f.tls / "vehicle-3.json5"),
            "60",
            "10",
            "1000000",
            str(forged),
        )
        flood.wait_for("READY", 30)
        time.sleep(8.0)
        f.authority.revoke(Role.STATION, 2)
        v = f.authority.roster.version
        t0 = time.monotonic()
        pusher.publish_roster(f.authority.roster)
        took = wait_for(lambda: len(f.holders(pusher.session, v)) >= members, 20)
        numbers["flood"] = time.monotonic() - t0
        sent = flood.wait_for("SENT", 30)
        assert took is not None, f"members holding v{v}: {f.holders(pusher.session, v)}"
        n_sent = int(sent.split()[1])
        assert n_sent >= 400, sent  # the flood really ran (60/s for 10 s, less on a loaded box)
        time.sleep(1.2)  # the last summaries
        roster_lines = [t for t in security if "roster" in t]
        numbers["security_events"] = len(roster_lines)
        numbers["forged_sent"] = n_sent
        print(
            f"revocation latency: quiet {numbers['quiet']:.3f} s, during the flood "
            f"{numbers['flood']:.3f} s; {n_sent} forged rosters of {MAX_ROSTER_BYTES} bytes -> "
            f"{len(roster_lines)} SECURITY events from 2 agents"
        )
        assert numbers["flood"] < 1.0, numbers
        assert roster_lines, "the agents did not report the forged rosters"
        assert len(roster_lines) <= 2 * 14, roster_lines  # at most ~1 a second per agent
        for vid in (1, 2):  # station 2 is refused by every vehicle; station 1 still commands
            refused = hold_from(station2, vid)
            assert refused.status is OutcomeStatus.REJECTED and "unknown signer" in refused.reason
            assert signer_accepted(hold_from(station, vid))

        # 3. The CLI pusher: only --connect tls/... and --zenoh-config; it says who confirmed.
        f.authority.add(Role.STATION, 3)
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "covey_cli",
                "keygen",
                "push",
                "--dir",
                str(f.authority.dir),
                "--connect",
                f.connect,
                "--zenoh-config",
                str(f.tls / "gcs-1.json5"),
            ],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
        assert out.returncode == 0, out.stdout + out.stderr
        assert f"roster v{f.authority.roster.version}" in out.stdout and "confirmed" in out.stdout

    # 4. The whole fleet down; vehicle 2 reboots from an old key file (the first roster, which
    # still lists station 2) before anyone else is back, then the station returns.
    for child in agents.values():
        child.kill()
    old = read_member_key(f.authority.member_path(Role.VEHICLE, 2))
    stale_file = tmp_path / "onboard" / "vehicle-2.key"
    write_private_file(
        stale_file,
        member_doc(
            FLEET, Role.VEHICLE, 2, old.private_key, old.authority_public_key, f.first_roster
        ),
    )
    assert read_member_key(stale_file).roster.version < f.authority.roster.version
    f.agent(procs, 2, stale_file)
    v = f.authority.roster.version
    with Mesh(f.client("gcs-1")) as observer:
        assert observer.presence().wait_for(lambda vs, _g: 2 in vs, timeout_s=60)
        time.sleep(5.5)  # its start-up pull found nobody newer, and has ended (5 s before)
        assert not f.holders(observer.session, v), "it caught up before anyone had the roster"
        s1_now = load_auth(str(f.authority.member_path(Role.STATION, 1)))
        t0 = time.monotonic()
        with Mesh(f.client("gcs-1"), auth=s1_now) as station:
            me = str(station.session.info.zid())
            took = wait_for(lambda: bool(f.holders(observer.session, v, exclude={me})), 10)
            numbers["reboot"] = time.monotonic() - t0
            assert took is not None, "the rebooted vehicle stayed on its old roster"
            with Mesh(f.client("gcs-2"), auth=s2) as revoked:
                refused = hold_from(revoked, 2)
            assert refused.status is OutcomeStatus.REJECTED and "unknown signer" in refused.reason
            assert signer_accepted(hold_from(station, 2))
    print(f"rebooted vehicle caught up {numbers['reboot']:.3f} s after the station returned")
    assert numbers["reboot"] < 1.5, numbers


def test_tls_init_writes_keys_private_and_refuses_the_repo(tmp_path) -> None:
    d = tmp_path / "tls"
    written = init(TlsConfig(directory=d, names=("router", "gcs-1", "vehicle-4")))
    assert sorted(p.name for p in written) == ["gcs-1.json5", "router.json5", "vehicle-4.json5"]
    for key in d.glob("*.key"):
        assert key.stat().st_mode & 0o777 == 0o600, key
    assert d.stat().st_mode & 0o777 == 0o700
    router = (d / "router.json5").read_text()
    assert '"covey/*/v/4/**"' in router and "vehicle-1" not in router and '["gcs-1"]' in router
    assert "/etc/covey" not in router and str(d / "router.pem") in router
    vehicle = (d / "vehicle-4.json5").read_text()
    assert str(d / "vehicle-4.key") in vehicle and str(d / "ca.pem") in vehicle
    ca = (d / "ca.pem").read_bytes()
    init(TlsConfig(directory=d, names=("router", "gcs-1", "vehicle-5")))  # the CA is reused
    assert (d / "ca.pem").read_bytes() == ca
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "covey_cli",
            "tls",
            "init",
            "--dir",
            str(REPO / "tls"),
            "--names",
            "router",
            "gcs-1",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    assert out.returncode == 2 and "inside covey's source tree" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and not (REPO / "tls").exists()
    for ok in ("--names", "router"), ("--names", "gcs-1"):
        bad = subprocess.run(
            [sys.executable, "-m", "covey_cli", "tls", "init", "--dir", str(tmp_path / "x"), *ok],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO,
        )
        assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) <= 3, bad.stderr
    assert shutil.which("sh")
