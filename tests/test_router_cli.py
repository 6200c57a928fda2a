"""`covey router` (tools/router_cli.py) on real Zenoh sessions on loopback: it says where it
listens, which routers link to it and how many clients it has; it links to a router that comes
up after it; it stops on SIGTERM. The fleet across three of them: tests/test_multisite_e2e.py."""

from __future__ import annotations

import signal
import threading

import pytest
from conftest import wait_until

from comms.mesh import Mesh
from comms.schema import VehicleState
from comms.session import MeshConfig, MeshConfigError, free_tcp_port, with_free_port
from tools.router_cli import RouterConfig, main

FLEET = "routers"


class Lines:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.lines: list[str] = []

    def out(self, line: str) -> None:
        with self.lock:
            self.lines.append(line)

    def has(self, text: str) -> bool:
        with self.lock:
            return any(text in line for line in self.lines)


def router(listen: str, *connect: str) -> RouterConfig:
    mesh = MeshConfig(mode="router", listen=(listen,), connect=connect)
    return RouterConfig(mesh, count_period_s=0.1)


def run(cfg: RouterConfig, lines: Lines, stop: threading.Event) -> threading.Thread:
    t = threading.Thread(target=main, args=(cfg, stop, lines.out), daemon=True)
    t.start()
    return t


def test_port_zero_is_picked_and_other_endpoints_are_kept() -> None:
    ep = with_free_port("tcp/127.0.0.1:0")
    assert ep.startswith("tcp/127.0.0.1:") and int(ep.rsplit(":", 1)[1]) > 0
    assert with_free_port("tls/127.0.0.1:0#iface=lo").endswith("#iface=lo")
    assert with_free_port("tcp/127.0.0.1:7447") == "tcp/127.0.0.1:7447"
    with pytest.raises(MeshConfigError, match="give a port"):
        with_free_port("udp/127.0.0.1:0")
    with pytest.raises(MeshConfigError, match="cannot listen on 10.9.9.9"):
        with_free_port("tcp/10.9.9.9:0")


def test_a_router_config_is_a_router_that_listens() -> None:
    with pytest.raises(ValueError, match="needs a router session"):
        RouterConfig(MeshConfig(mode="peer"))
    with pytest.raises(ValueError, match="at least one --listen"):
        RouterConfig(MeshConfig(mode="router", listen=(), connect=()))


def test_routers_link_in_any_order_and_carry_states_between_their_clients() -> None:
    """B starts first and connects to A, which is not up yet: B keeps trying. A client of each
    then hears the other's states through both routers."""
    a_ep, b_ep = (f"tcp/127.0.0.1:{free_tcp_port()}" for _ in range(2))
    a_lines, b_lines = Lines(), Lines()
    stop = threading.Event()
    threads = [run(router(b_ep, a_ep), b_lines, stop)]
    try:
        assert wait_until(lambda: b_lines.has(f"READY {b_ep}"), 10)
        threads.append(run(router(a_ep), a_lines, stop))
        assert wait_until(lambda: a_lines.has("linked; 1 router link(s)"), 20), a_lines.lines
        # named by its id and the address of its link, not by a bare hex id (issue 39 #13)
        assert any(" at tcp/127.0.0.1:" in line for line in a_lines.lines if "linked" in line)
        assert any(f" at {a_ep} " in line for line in b_lines.lines if "linked" in line)
        assert wait_until(lambda: b_lines.has("linked; 1 router link(s)"), 20), b_lines.lines
        heard: list[int] = []
        with (
            Mesh(MeshConfig(fleet=FLEET, mode="client", connect=(a_ep,))) as on_a,
            Mesh(MeshConfig(fleet=FLEET, mode="client", connect=(b_ep,))) as on_b,
        ):
            on_a.subscribe_states(lambda s, _t: heard.append(s.seq))
            for seq in range(1, 200):
                on_b.publish_state(VehicleState(7, seq, 0, (1.0, 2.0, -3.0), (0, 0, 0), 0.0))
                if wait_until(lambda: bool(heard), 0.1):
                    break
            assert heard, "a state never crossed the two routers"
            assert wait_until(lambda: a_lines.has("1 router(s), 0 peer(s), 1 client(s)"), 10)
    finally:
        stop.set()
        for t in threads:
            t.join(10)
    assert not any(t.is_alive() for t in threads)
    assert a_lines.lines[-1] == "covey router: stopped"
    assert a_lines.lines[0] == f"READY {a_ep}"  # READY always comes first


def test_the_process_says_ready_and_stops_on_sigterm(procs) -> None:
    child = procs.start("-m", "covey_cli", "router", "--listen", "tcp/127.0.0.1:0")
    ready = child.wait_for("READY", 30)
    port = int(ready.split()[-1].rsplit(":", 1)[1])
    assert port > 0
    child.signal(signal.SIGTERM)
    assert child.wait(timeout=20) == 0
    assert "covey router: stopped" in child.output()


def test_the_cli_refuses_a_busy_port_in_one_line(capsys) -> None:
    import socket

    from tools.router_cli import cli

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        with pytest.raises(SystemExit) as exc:
            cli(["--listen", f"tcp/127.0.0.1:{busy.getsockname()[1]}"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "covey router: error:" in err, err


def test_a_client_given_two_routers_fails_over_to_the_other() -> None:
    """A vehicle at a site with two routers (`--connect b,a`) uses the first; when it goes, the
    vehicle's states reach the station through the other."""
    a_ep, b_ep = (f"tcp/127.0.0.1:{free_tcp_port()}" for _ in range(2))
    a_lines, b_lines = Lines(), Lines()
    stop_a, stop_b = threading.Event(), threading.Event()
    threads = [run(router(a_ep), a_lines, stop_a), run(router(b_ep, a_ep), b_lines, stop_b)]
    heard: list[int] = []
    try:
        assert wait_until(lambda: b_lines.has("linked; 1 router link(s)"), 20), b_lines.lines
        with (
            Mesh(MeshConfig(fleet=FLEET, mode="client", connect=(a_ep,))) as station,
            Mesh(MeshConfig(fleet=FLEET, mode="client", connect=(b_ep, a_ep))) as vehicle,
        ):
            station.subscribe_states(lambda s, _t: heard.append(s.seq))
            assert wait_until(lambda: b_lines.has("0 peer(s), 1 client(s)"), 10), b_lines.lines

            def crosses(first_seq: int) -> bool:
                for seq in range(first_seq, first_seq + 100):
                    vehicle.publish_state(VehicleState(7, seq, 0, (1.0, 2.0, -3.0), (0, 0, 0), 0))
                    if wait_until(lambda s=seq: s in heard, 0.1):
                        return True
                return False

            assert crosses(1), "no state through router b"
            stop_b.set()
            threads[1].join(10)
            assert crosses(1000), "no state after router b stopped"
            assert wait_until(lambda: a_lines.has("0 router(s), 0 peer(s), 2 client(s)"), 10)
    finally:
        stop_a.set()
        stop_b.set()
        for t in threads:
            t.join(10)
