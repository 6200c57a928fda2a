"""Encrypted, authenticated mesh: the shipped Zenoh configs (comms/zenoh_configs/) on loopback.

A router in this process, the ground station as a client in this process, a real agent process
as a client. Two setups share the same access-control shape: mutual TLS with identities from
certificate common names, and user/password with identities from user names. Checked:
- the fleet works through them (states flow, commands are acked);
- a peer without credentials cannot join: its put never arrives, its query gets no ack;
- a peer WITH credentials but the wrong identity cannot impersonate: another vehicle's state
  never arrives, and a vehicle cannot command a vehicle.
"""

from __future__ import annotations

import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh

from comms import keys
from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.schema import ActionOutcome, Command, CommandKind, RelayBatch, VehicleState
from comms.session import MeshConfig, free_tcp_port

pytestmark = [pytest.mark.e2e]

CONFIGS = Path(__file__).resolve().parent.parent / "comms" / "zenoh_configs"
FLEET = "trust"
PLACEHOLDER_DIR = "/etc/covey/tls/"
PLACEHOLDER_USERS = "/etc/covey/users.txt"
# Give up quickly on a link that will never be accepted, instead of retrying forever.
QUICK = (
    ("connect/timeout_ms", "1500"),
    ("connect/exit_on_failure", "false"),
    ("listen/endpoints", "[]"),
)

needs_openssl = pytest.mark.skipif(
    shutil.which("openssl") is None, reason="openssl CLI not installed"
)


def make_certs(out: Path, *names: str) -> Path:
    subprocess.run(["sh", str(CONFIGS / "make_certs.sh"), str(out), *names], check=True, timeout=60)
    return out


def identity_config(
    template: str,
    tmp: Path,
    name: str,
    certs: Path | None = None,
    user: str | None = None,
    password: str | None = None,
) -> str:
    """Write a copy of a shipped config with its placeholders pointing at `name`'s files."""
    text = (CONFIGS / template).read_text()
    if certs is not None:
        for leaf in ("client", "router"):
            text = text.replace(f"{PLACEHOLDER_DIR}{leaf}.pem", str(certs / f"{name}.pem"))
            text = text.replace(f"{PLACEHOLDER_DIR}{leaf}.key", str(certs / f"{name}.key"))
        text = text.replace(f"{PLACEHOLDER_DIR}ca.pem", str(certs / "ca.pem"))
    text = text.replace(PLACEHOLDER_USERS, str(tmp / "users.txt"))
    if user is not None:
        text = text.replace('user: "vehicle-1"', f'user: "{user}"').replace(
            '"CHANGE-ME"', f'"{password}"'
        )
    path = tmp / f"{name}-{template}"
    path.write_text(text)
    path.chmod(0o600)
    return str(path)


class Setup:
    """Endpoints and per-identity config files of one secured fleet."""

    def __init__(self, kind: str, tmp: Path) -> None:
        self.kind = kind
        self.port = free_tcp_port()
        self.tmp = tmp
        if kind == "mtls":
            self.certs = make_certs(tmp / "certs", "router", "gcs-1", "vehicle-1", "vehicle-2")
            self.rogue_certs = make_certs(tmp / "rogue", "gcs-1")  # right name, wrong CA
            self.listen = f"tls/127.0.0.1:{self.port}"
            self.connect = f"tls/localhost:{self.port}"
        else:
            self.certs = None
            (tmp / "users.txt").write_text(
                "gcs-1:pw-gcs-1\nvehicle-1:pw-vehicle-1\nvehicle-2:pw-vehicle-2\n"
            )
            (tmp / "users.txt").chmod(0o600)
            self.listen = f"tcp/127.0.0.1:{self.port}"
            self.connect = f"tcp/127.0.0.1:{self.port}"

    def router(self) -> MeshConfig:
        template = "router_mtls_acl.json5" if self.kind == "mtls" else "router_usrpwd_acl.json5"
        path = identity_config(template, self.tmp, "router", self.certs)
        return MeshConfig(
            fleet=FLEET, mode="router", connect=(), listen=(self.listen,), config_file=path
        )

    def client_file(self, name: str, password: str | None = None) -> str:
        if self.kind == "mtls":
            return identity_config("client_mtls.json5", self.tmp, name, self.certs)
        return identity_config(
            "client_usrpwd.json5", self.tmp, name, user=name, password=password or f"pw-{name}"
        )

    def client(self, name: str, password: str | None = None, extra=()) -> MeshConfig:
        return MeshConfig(
            fleet=FLEET,
            mode="client",
            connect=(self.connect,),
            config_file=self.client_file(name, password),
            extra=extra,
        )

    def peer(self, name: str) -> MeshConfig:
        """`name`'s credentials in a peer session that gives up quickly (same path as intruders)."""
        return MeshConfig(
            fleet=FLEET,
            mode="peer",
            connect=(self.connect,),
            extra=QUICK,
            config_file=self.client_file(name),
        )

    def intruders(self) -> list[tuple[str, MeshConfig]]:
        """Configs that must not get in at all."""
        # Peers: a peer's session opens even when nobody lets it in, so it can try to send.
        bare = MeshConfig(fleet=FLEET, mode="peer", connect=(self.connect,), extra=QUICK)
        if self.kind == "mtls":
            wrong_ca = identity_config("client_mtls.json5", self.tmp, "gcs-1", self.rogue_certs)
            no_cert = MeshConfig(
                fleet=FLEET,
                mode="peer",
                connect=(self.connect,),
                extra=(
                    *QUICK,
                    ("transport/link/tls/root_ca_certificate", f'"{self.certs / "ca.pem"}"'),
                ),
            )
            return [
                ("plain", bare),
                ("tls-without-certificate", no_cert),
                (
                    "certificate-from-another-ca",
                    MeshConfig(
                        fleet=FLEET,
                        mode="peer",
                        connect=(self.connect,),
                        config_file=wrong_ca,
                        extra=QUICK,
                    ),
                ),
            ]
        wrong = MeshConfig(
            fleet=FLEET,
            mode="peer",
            connect=(self.connect,),
            extra=QUICK,
            config_file=self.client_file("gcs-1", password="guess"),
        )
        return [("no-password", bare), ("wrong-password", wrong)]


@pytest.fixture(params=["mtls", "usrpwd"])
def secured(request, tmp_path, procs):
    if request.param == "mtls" and shutil.which("openssl") is None:
        pytest.skip("openssl CLI not installed")
    setup = Setup(request.param, tmp_path)
    with Mesh(setup.router()) as router, Mesh(setup.client("gcs-1")) as gcs:
        received: list[VehicleState] = []
        gcs.subscribe_states(lambda s, _t: received.append(s))
        gcs.subscribe_events(lambda e, _t: None)
        presence = gcs.presence()
        gcs.declare_gcs(1)
        agent = procs.start(
            "-m",
            "covey_cli",
            "agent",
            "--id",
            "1",
            "--fleet",
            FLEET,
            "--mesh-mode",
            "client",
            "--connect",
            setup.connect,
            "--zenoh-config",
            setup.client_file("vehicle-1"),
            "--no-gcs-failsafe",
        )
        assert presence.wait_for(lambda v, _g: 1 in v, timeout_s=30), (
            "the agent did not join through the secured router"
        )
        yield setup, router, gcs, received, agent


def wait(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def forged_state(vid: int, seq: int) -> VehicleState:
    return VehicleState(vid, seq, time.time_ns(), (66.0, 66.0, -6.0), (0.0, 0.0, 0.0), 0.0)


def test_secured_fleet_works_and_strangers_cannot_join_or_inject(secured) -> None:
    setup, _router, gcs, received, _agent = secured
    assert wait(lambda: any(s.vehicle_id == 1 for s in received), 10), "no state from the agent"
    ack = gcs.send_command(
        Command(CommandKind.HOLD, new_nonce(), time.time_ns(), targets=(1,)), timeout_s=5
    )
    assert set(ack.outcomes) == {1} and ack.outcomes[1].ack is not None, ack.summary()
    # The autopilot's outcome (its own message, on the vehicle's event key) passes the ACL.
    outcomes: list[ActionOutcome] = []
    gcs.subscribe_events(lambda e, _t: None, on_outcome=lambda o, _t: outcomes.append(o))
    takeoff = Command.takeoff(3.0, nonce=new_nonce(), stamp_ns=time.time_ns(), targets=(1,))
    res = gcs.send_command(takeoff, timeout_s=5)
    assert res.outcomes[1].status is OutcomeStatus.ACCEPTED, res.summary()
    assert wait(lambda: any(o.nonce == takeoff.nonce and o.ok for o in outcomes), 10), outcomes

    def attempt(cfg: MeshConfig, seq: int, kind: CommandKind) -> tuple[bool, bool] | None:
        """Open a session with `cfg`, publish a state of vehicle 1 and send it a command:
        (the state arrived, the command was answered), or None if the session did not open."""
        try:
            mesh = Mesh(cfg)
        except zenoh.ZError:  # a client that cannot connect does not open at all
            return None
        with mesh:
            try:
                mesh.publish_state(forged_state(1, seq))
            except Exception:  # noqa: BLE001 - refusing to send at all is a pass too
                pass
            payload = Command(kind, new_nonce(), 0, targets=(1,)).encode()
            replies = list(mesh.session.get(keys.cmd(FLEET, 1), payload=payload, timeout=1.0))
            time.sleep(0.5)
        return any(s.seq == seq for s in received), any(r.ok is not None for r in replies)

    # Controls through the very same path: it does reach the fleet with the right identity.
    assert attempt(setup.peer("vehicle-1"), 888_001, CommandKind.HOLD) == (True, False), (
        "control: vehicle-1"
    )
    assert attempt(setup.peer("gcs-1"), 888_002, CommandKind.HOLD) == (False, True), (
        "control: gcs-1"
    )
    for i, (name, cfg) in enumerate(setup.intruders()):
        t0 = time.monotonic()
        outcome = attempt(cfg, 999_000 + i, CommandKind.KILL)
        assert outcome in (None, (False, False)), (
            f"{name}: (state arrived, kill answered) = {outcome}"
        )
        how = "refused at open" if outcome is None else "joined nothing"
        print(f"{setup.kind}/{name}: {how} ({time.monotonic() - t0:.1f} s)")


def test_an_insider_cannot_impersonate_a_vehicle_or_command(secured) -> None:
    """vehicle-2 holds valid credentials: it may publish its own state, not vehicle 1's, and it
    may not send commands at all (only ground stations may)."""
    setup, _router, gcs, received, _agent = secured
    with Mesh(setup.client("vehicle-2")) as v2:
        answered = threading.Event()
        v2.declare_vehicle(2)
        for seq in range(1, 20):
            v2.publish_state(forged_state(2, seq))
            v2.publish_state(forged_state(1, 1_000_000 + seq))
            time.sleep(0.02)
        assert wait(lambda: any(s.vehicle_id == 2 for s in received), 5), (
            "vehicle 2's own state did not arrive"
        )
        replies = list(
            v2.session.get(
                keys.cmd(FLEET, 1),
                payload=Command(CommandKind.KILL, new_nonce(), 0).encode(),
                timeout=1.0,
            )
        )
        if any(r.ok is not None for r in replies):
            answered.set()
        # Hardening block of the router configs: an oversized message never gets through, a
        # small malformed one does (and the station's decoder drops and counts it).
        errors0 = gcs.stats.decode_errors
        v2.session.put(keys.event(FLEET, 2), bytes(5000))
        v2.session.put(keys.event(FLEET, 2), bytes(3))
        assert wait(lambda: gcs.stats.decode_errors > errors0, 5), (
            "the small malformed event did not arrive"
        )
        time.sleep(0.3)
        assert gcs.stats.decode_errors == errors0 + 1, (
            "the 5000-byte message got through the size limit"
        )
    assert not [s for s in received if s.vehicle_id == 1 and s.seq > 1_000_000], (
        "vehicle 2 spoofed vehicle 1's state"
    )
    assert not answered.is_set(), "a vehicle's command reached another vehicle"
    # The station still commands vehicle 1.
    result = gcs.send_command(
        Command(CommandKind.HOLD, new_nonce(), time.time_ns(), targets=(1,)), timeout_s=5
    )
    assert result.outcomes[1].status in (OutcomeStatus.ACCEPTED, OutcomeStatus.REJECTED), (
        result.summary()
    )


def test_the_cell_relay_works_through_the_shipped_acls_and_nobody_else_can_relay(secured) -> None:
    """Behind the shipped access control, vehicle 2 wants its block from the router's cell relay
    (a token under its own v/2/) and hears vehicle 1 through it; a member that puts a batch of
    its own on the relay's key (a forged state of vehicle 9 inside) reaches nobody: only the
    router's own relay puts there."""
    setup, router, gcs, _received, _agent = secured
    assert router.relay is not None
    with Mesh(setup.client("vehicle-2")) as v2:
        heard: list[int] = []
        sub = v2.subscribe_cells(
            lambda s, _t: heard.append(s.vehicle_id),
            keys.block_cells(1, (0, 0)),  # vehicle 1 waits on the ground at (0, 0)
            polled=True,
            relay_for=2,
        )
        assert wait(lambda: (sub.drain(), sub.relayed and 1 in heard)[1], 20), (
            f"not relayed: {router.relay.stats}, heard {sorted(set(heard))}"
        )
        inside = VehicleState(9, 1, time.time_ns(), (5.0, 5.0, -6.0), (0.0, 0.0, 0.0), 0.0)
        forged = RelayBatch(1, (inside.encode(),)).encode()
        block = keys.relay_block(FLEET, router.relay.relay_id, 1, (0, 0))
        for _ in range(10):
            gcs.session.put(block, forged)
            time.sleep(0.05)
            sub.drain()
        assert 9 not in heard, "a member's own relay batch got through the router's ACL"
        assert v2.stats.states_misplaced == 0 and v2.stats.decode_errors == 0


def test_every_shipped_config_loads() -> None:
    for path in sorted(CONFIGS.glob("*.json5")):
        zenoh.Config.from_file(str(path))  # raises on a syntax or schema error


def test_peer_mesh_with_usrpwd_lets_only_dictionary_members_in(tmp_path) -> None:
    """peer_usrpwd.json5: the radio-mesh topology, where every peer checks who connects."""
    (tmp_path / "users.txt").write_text("vehicle-1:pw-1\nvehicle-2:pw-2\n")
    port = free_tcp_port()

    def peer(name: str, password: str, listen: bool, extra=()) -> MeshConfig:
        text = (
            (CONFIGS / "peer_usrpwd.json5")
            .read_text()
            .replace(PLACEHOLDER_USERS, str(tmp_path / "users.txt"))
        )
        text = text.replace('user: "vehicle-1"', f'user: "{name}"').replace(
            '"CHANGE-ME"', f'"{password}"'
        )
        path = tmp_path / f"{name}-{password}.json5"
        path.write_text(text)
        return MeshConfig(
            fleet=FLEET,
            mode="peer",
            connect=() if listen else (f"tcp/127.0.0.1:{port}",),
            listen=(f"tcp/127.0.0.1:{port}",) if listen else (),
            config_file=str(path),
            extra=extra,
        )

    got: list[VehicleState] = []
    with Mesh(peer("vehicle-1", "pw-1", listen=True)) as a:
        a.subscribe_states(lambda s, _t: got.append(s))
        with Mesh(peer("vehicle-2", "pw-2", listen=False)) as b:
            assert wait(lambda: (b.publish_state(forged_state(2, 1)), bool(got))[1], 5), (
                "a member could not join"
            )
        got.clear()
        with Mesh(peer("vehicle-2", "guess", listen=False, extra=QUICK)) as rogue:
            for seq in range(5):
                rogue.publish_state(forged_state(2, 100 + seq))
            time.sleep(0.5)
        assert not got, "a peer with a wrong password got a state in"
