"""`covey router`: the Zenoh router of one site of a multi-site fleet.

    covey router --listen tcp/0.0.0.0:7447 --connect tcp/site-b:7447,tcp/site-c:7447
    covey agent --id 3 --mesh-mode client --connect tcp/site-a:7447
    covey gcs --mesh-mode client --connect tcp/site-a:7447

Each site runs one router; the routers connect to each other and route between sites with
Zenoh's link-state routing, so states, commands and their acks, and presence cross any number
of routers. Every agent and station is a client of its own site's router. A link needs one side
to connect: a router keeps trying an endpoint that is not up yet, and re-makes a link that drops.
(`zenohd -l tcp/0.0.0.0:7447 -e tcp/site-b:7447 --no-multicast-scouting` does the same job.)

Every router relays the cells its vehicles want (comms/relay.py): an agent flying one vehicle
hears the states of its block of cells as one message every `--cell-relay-period-s` (0.1 s)
instead of one per state; `--no-cell-relay` turns it off, and the agents then hear their cells
themselves, as they do behind zenohd.

It prints `READY <endpoints>` once it listens (port 0: a free port, picked and printed), then a
line for each router that links or unlinks, named by its Zenoh id, the address its link comes
from and, over TLS or user/password, who it authenticated as (`peer_name`), and the number of
clients and peers when it changed. SIGINT or SIGTERM stop it (exit status 0); a bad endpoint, Zenoh config or busy port
is one line and exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace

import zenoh

from cli.options import (
    add_mesh_args,
    die,
    finite,
    key_env_note,
    mesh_config,
    refuse,
    stop_on_signals,
)
from comms.relay import CellRelay, RelayConfig
from comms.session import MeshConfig, MeshConfigError, open_session, with_free_port

ROLES = ("router", "peer", "client")


@dataclass(frozen=True)
class RouterConfig:
    """What `covey router` runs."""

    mesh: MeshConfig
    """Its Zenoh session: mode router, the endpoints it listens on and the routers it links to."""
    count_period_s: float = 2.0
    """How often the number of clients and peers is looked at (printed when it changed)."""

    def __post_init__(self) -> None:
        if self.mesh.mode != "router":
            raise ValueError(f"covey router needs a router session, got mode {self.mesh.mode!r}")
        if not self.mesh.listen:
            raise ValueError("covey router needs at least one --listen endpoint")
        if not 0.0 < self.count_period_s <= 3600.0:
            raise ValueError(f"count_period_s={self.count_period_s} must be within (0, 3600]")


class Links:
    """The sessions linked to this router, by Zenoh id and role, from Zenoh's transport events.
    A router's arrival or departure is said at once (there are few, and they make the site
    topology); clients and peers are counted (a site may have hundreds)."""

    def __init__(
        self, say: Callable[[str], None], name: Callable[[str], str] = lambda zid: zid
    ) -> None:
        self._say = say
        self._name = name
        self._lock = threading.Lock()
        self._roles: dict[str, str] = {}
        self._names: dict[str, str] = {}  # linked routers' names, to say who went

    def on_event(self, event: zenoh.TransportEvent) -> None:
        """Zenoh's thread: never raises."""
        try:
            zid, role = str(event.transport.zid), str(event.transport.whatami).lower()
            up = event.kind == zenoh.SampleKind.PUT
            with self._lock:
                was = zid in self._roles
                if up:
                    self._roles[zid] = role
                else:
                    self._roles.pop(zid, None)
                routers = sum(r == "router" for r in self._roles.values())
            if role == "router" and up != was:
                with self._lock:
                    if up:
                        name = self._names[zid] = self._name(zid)
                    else:
                        name = self._names.pop(zid, zid)
                self._say(
                    f"router {name} {'linked' if up else 'unlinked'}; {routers} router link(s)"
                )
        except Exception as exc:  # noqa: BLE001 - a report must not kill Zenoh's thread
            self._say(f"could not read a transport event: {exc}")

    def counts(self) -> dict[str, int]:
        """Linked sessions by role: {"router": n, "peer": n, "client": n}."""
        with self._lock:
            roles = list(self._roles.values())
        return {role: roles.count(role) for role in ROLES}


def relay_line(relay: CellRelay) -> str:
    """What an operator watches of the cell relay: the blocks wanted, the cells heard, and the
    refusals with the last reason (printed when it changed)."""
    st = relay.stats
    line = f"cell relay: {st.blocks} block(s) wanted, {st.cells} cell(s) heard"
    if st.refused:
        line += f"; {st.refused} refused, the last: {st.last_refusal}"
    return line


def peer_name(session: zenoh.Session, zid: str) -> str:
    """A linked node as an operator can place it: its Zenoh id, the remote address of its link,
    and the identity it authenticated with (TLS certificate name or user), where there is one:
    `3f1c… at tcp/10.0.0.7:41234 (site-b)`. The id alone if its link is not found."""
    for link in session.info.links():
        if str(link.zid) == zid:
            who = f" ({link.auth_identifier})" if link.auth_identifier else ""
            return f"{zid} at {link.dst}{who}"
    return zid


def main(
    cfg: RouterConfig,
    stop: threading.Event,
    out: Callable[[str], None] = print,
) -> int:
    """Route until `stop` is set. Raises MeshConfigError (one line) if the session cannot open."""
    lock = threading.Lock()  # Zenoh's thread says links: whole lines, READY first

    def emit(line: str) -> None:
        with lock:
            out(line)

    def say(line: str) -> None:
        emit(f"covey router: {line}")

    mesh = replace(cfg.mesh, listen=tuple(with_free_port(ep) for ep in cfg.mesh.listen))
    with contextlib.ExitStack() as stack:
        session = stack.enter_context(open_session(mesh))
        relay = None
        if mesh.cell_relay_period_s is not None:
            relay = stack.enter_context(CellRelay(session, RelayConfig(mesh.cell_relay_period_s)))
        links = Links(say, lambda zid: peer_name(session, zid))
        emit(f"READY {','.join(mesh.listen)}")
        to = ", ".join(mesh.connect) or "no other router"
        say(f"listening on {', '.join(mesh.listen)}; linking to {to} (Ctrl-C to stop)")
        if mesh.cell_relay_period_s is not None:
            say(
                f"relaying cells to the vehicles that want them every {mesh.cell_relay_period_s:g} s "
                "(--no-cell-relay: off)"
            )
        listener = session.info.declare_transport_events_listener(links.on_event, history=True)
        try:
            said: dict[str, int] = {}
            relay_said = ""
            while not stop.wait(cfg.count_period_s):
                counts = links.counts()
                if counts != said:
                    said = counts
                    say(", ".join(f"{n} {role}(s)" for role, n in counts.items()))
                if relay is not None and (line := relay_line(relay)) != relay_said:
                    relay_said = line
                    say(line)
        finally:
            listener.undeclare()
    say("stopped")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey router",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_mesh_args(p, key_file=False, router=True)
    refuse(
        p, "--key-file", "a router holds no member key: it forwards signed messages unread", True
    )
    p.add_argument(
        "--count-period-s",
        type=finite("seconds"),
        default=2.0,
        metavar="SECONDS",
        help="how often the number of clients and peers is looked at (default: 2)",
    )
    p.add_argument(
        "--cell-relay-period-s",
        type=finite("seconds"),
        default=RelayConfig.period_s,
        metavar="SECONDS",
        help="how often the cell relay sends each vehicle its block of cells, within [0.01, 0.3] "
        f"(default: {RelayConfig.period_s:g}); a state waits half of it on average "
        "(comms/relay.py)",
    )
    p.add_argument(
        "--no-cell-relay",
        action="store_true",
        help="no cell relay: each vehicle hears each neighbour state as a message of its own",
    )
    return p


def cli(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    key_env_note(p, "a router holds no member key")
    try:
        relay_period_s = None if args.no_cell_relay else args.cell_relay_period_s
        mesh = replace(mesh_config(args, p), cell_relay_period_s=relay_period_s)
        cfg = RouterConfig(mesh, count_period_s=args.count_period_s)
    except ValueError as exc:
        die(p, str(exc))
    with stop_on_signals() as stop:
        try:
            return main(cfg, stop, lambda line: print(line, flush=True))
        except MeshConfigError as exc:
            die(p, str(exc))


if __name__ == "__main__":
    sys.exit(cli())
