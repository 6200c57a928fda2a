"""Zenoh session configuration for the topologies that work (see shared/DESIGN.md).

- embedded (default): one process (the demo's or the ground station's) is a Zenoh *router* that
  listens on a loopback port; every agent connects to it as a *peer* that also listens, so gossip
  builds a full mesh and traffic between agents does not need the router once they have met.
- peer mesh (radio-mesh analogue): every process is a peer that listens and connects to one or
  more known endpoints.
- clients of site routers (multi-site fleets): each site runs a router (`covey router`, or
  `zenohd`), the routers connect to each other, and every agent and station is a client of its
  site's router (`--mesh-mode client --connect tcp/<router>:7447`); README "Multi-site layout".

Multicast scouting is off unless asked for: it floods the LAN and makes tests flaky.
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import zenoh

from kit.safe_load import BadFileError, check_depth, decode_utf8, read_bounded

log = logging.getLogger(__name__)

DEFAULT_PORT = 7447
Mode = Literal["peer", "client", "router"]
_ENDPOINT_RE = re.compile(r"^([a-z0-9]+)/(.+):([0-9]+)(#.*|\?.*)?$")
MAX_CONFIG_BYTES = 1 << 20
"""The largest --zenoh-config accepted (1 MiB; the shipped ones are under 4 KiB)."""


RUNTIME_ENV = "ZENOH_RUNTIME"
"""Zenoh reads its thread pools' settings from this variable once, when it first runs."""
AGENT_RUNTIME = "(rx: (handover: app))"
"""An agent's Zenoh pools by default (`covey agent`): the receive pool hands its work over to
the application worker, so that a state heard wakes one thread, not two. An agent hears its
neighbours' states one by one, each from its own process at its own phase; at 230 states a
second from 20 publishers spread over each 100 ms, a polled subscriber's process used 22.0 ms
of CPU a second with Zenoh's default pools and 13.3 ms with this (5.1 ms when the same states
came in one burst a tick; docs/companion.md, "Round nine"). The send, link and accept pools
stay Zenoh's."""
ONE_THREAD_RUNTIME = (
    "(rx: (handover: app), tx: (handover: app), net: (handover: app), acc: (handover: app), "
    "app: (worker_threads: 1))"
)
"""Every Zenoh pool of a process on one worker thread (zenoh-runtime's RON syntax), for
`covey agent --one-zenoh-thread`. An agent process moves a few hundred small messages a second;
on the 2 (receive), 1 + 1 (send, links) and 1 (application) threads of Zenoh's default each
message wakes a thread and hands the work on to another, which costs more than the work
(docs/companion.md, "Round six"). Not the default: under a loaded machine one e2e test
(tests/test_record_e2e.py closed loop) missed more traced ticks with it."""


def use_zenoh_runtime(setting: str = ONE_THREAD_RUNTIME) -> str:
    """Run this process's Zenoh pools as `setting` says (AGENT_RUNTIME, ONE_THREAD_RUNTIME),
    unless the user's environment already says how (RUNTIME_ENV wins). Call before the first
    session opens: Zenoh reads the variable once. Returns the setting in force."""
    return os.environ.setdefault(RUNTIME_ENV, setting)


class MeshConfigError(ValueError):
    """The mesh cannot be set up as configured (bad Zenoh config file, endpoint, busy port); the
    message is one line that says why. CLIs turn it into exit status 2."""


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    text = re.sub(r" at /\S+?\.rs:\d+\.?", "", text)  # Rust source locations: noise to a user
    return text[:300] + ("..." if len(text) > 300 else "")


def check_endpoint(ep: object) -> str:
    """Return `ep` if it looks like proto/host:port with a port in 0..65535, else raise."""
    if not isinstance(ep, str) or "/" not in ep:
        raise MeshConfigError(f"endpoint {ep!r} must look like tcp/127.0.0.1:7447")
    m = _ENDPOINT_RE.match(ep)
    if m and not 0 <= int(m.group(3)) <= 65535:
        raise MeshConfigError(f"endpoint {ep!r}: port {m.group(3)} is outside 0..65535")
    return ep


def check_config_file(path: str) -> None:
    """Refuse a --zenoh-config that is missing, not a file, unreadable, not UTF-8, too big or
    nested deeper than MAX_DEPTH, before Zenoh sees it: its errors are multi-line, and deep
    nesting overflows its parser's stack (the process dies of SIGSEGV)."""
    if not isinstance(path, str) or not path.strip():
        raise MeshConfigError("--zenoh-config path is empty (an unset variable?)")
    what = f"Zenoh config {path}"
    if os.path.isdir(path):
        raise MeshConfigError(f"{what} is a directory, not a JSON5 file")
    try:
        raw = read_bounded(path, MAX_CONFIG_BYTES, "Zenoh config")
        check_depth(decode_utf8(raw, what), what)
    except BadFileError as exc:
        raise MeshConfigError(str(exc)) from None


TLS_FILE_FIELDS = (
    "root_ca_certificate",
    "listen_certificate",
    "listen_private_key",
    "connect_certificate",
    "connect_private_key",
)
"""The fields of transport.link.tls that name files (their *_base64 twins hold the data)."""


def check_config_paths(conf: zenoh.Config, where: str = "Zenoh config") -> None:
    """Refuse a Zenoh config whose TLS certificates, keys or password dictionary do not exist
    or cannot be read, naming the field and the file: Zenoh would only fail to connect and a
    client would wait for its router forever."""
    named: list[tuple[str, object]] = []
    tls = _config_json(conf, "transport/link/tls")
    if isinstance(tls, dict):
        named += [(f"transport.link.tls.{k}", tls.get(k)) for k in TLS_FILE_FIELDS]
    usrpwd = _config_json(conf, "transport/auth/usrpwd")
    if isinstance(usrpwd, dict):
        named.append(("transport.auth.usrpwd.dictionary_file", usrpwd.get("dictionary_file")))
    for field_name, file in named:
        if file is None:
            continue
        if not isinstance(file, str) or not file:
            raise MeshConfigError(f"{where}: {field_name} must name a file")
        if not os.path.isfile(file):
            why = "is not a file" if os.path.exists(file) else "does not exist"
            raise MeshConfigError(f"{where}: {field_name} {file} {why}")
        if not os.access(file, os.R_OK):
            raise MeshConfigError(f"{where}: {field_name} {file} cannot be read")


def _config_json(conf: zenoh.Config, key: str) -> object:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - not in this config (Zenoh says so by raising)
        return None


@dataclass(frozen=True)
class MeshConfig:
    """How a process joins the covey mesh."""

    fleet: str = "covey"
    """Fleet name: the second element of every key; fleets never see each other."""
    mode: Mode = "peer"
    """Zenoh role of this process: peer, client (of a router) or router."""
    connect: tuple[str, ...] = (f"tcp/127.0.0.1:{DEFAULT_PORT}",)
    """Endpoints to connect to, e.g. ("tcp/10.0.0.1:7447",)."""
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    """Endpoints to listen on. Peers must listen for gossip to build a mesh; port 0 = any free."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast. Off by default; never on in tests."""
    lease_ms: int = 2000
    """Transport lease: a hung (not killed) peer is declared gone after about this long."""
    config_file: str | None = None
    """A full Zenoh JSON5 config (TLS, user/password, access control). Fields above override it."""
    extra: tuple[tuple[str, str], ...] = field(default_factory=tuple)
    """Additional (path, json5 value) pairs inserted into the Zenoh config."""
    cell_relay_period_s: float | None = 0.1
    """Router mode: relay the fleet's cells to the vehicles that want them from this router every
    this many seconds, within [0.01, 0.3] (comms/relay.py); None: no relay."""
    shared_memory: bool | None = None
    """Zenoh's shared-memory transport between processes on one host; None: as Zenoh or the
    config file has it (Zenoh 1.x: on, for messages above 3 KB). `covey agent` turns it off
    (agent/agent_cli.py): the cell relay's batches (up to 4 KiB) would start a watchdog thread
    in every agent beside its router that wakes 20 times a second (0.08 ms of CPU per 10 Hz
    tick; 40 agents: 800 wake-ups a second), for messages that gain nothing from it. Between
    hosts it never applies. On one host it carries floods of large messages (forged 41 KB
    plans at 30-40 MB/s: the genuine plan through in 6-53 ms with it, 0.4-1.9 s behind the
    backlog without, tests/test_plan_flood.py), so other processes keep Zenoh's default."""
    feed_hz: float = 5.0
    """How often this process sends its vehicles' latest states to the ground stations, batched
    (comms/feed.py). Within 2..50: the station calls a vehicle stale after 1 s without news
    (FleetConfig.stale_after_s), so a feed period must be well under it."""

    def __post_init__(self) -> None:
        from comms.keys import check_fleet

        check_fleet(self.fleet)
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"mesh mode must be peer, client or router, got {self.mode!r}")
        for ep in (*self.connect, *self.listen):
            check_endpoint(ep)
        if self.mode == "client" and not self.connect:
            raise ValueError("a client needs at least one --connect endpoint (its router)")
        if not 100 <= self.lease_ms <= 600_000:
            raise ValueError(f"lease_ms={self.lease_ms} must be within 100..600000")
        if not (isinstance(self.feed_hz, int | float) and 2.0 <= self.feed_hz <= 50.0):
            raise ValueError(f"feed_hz={self.feed_hz} must be within 2..50")
        period = self.cell_relay_period_s
        if period is not None and not (isinstance(period, int | float) and 0.01 <= period <= 0.3):
            raise ValueError(f"cell_relay_period_s={period} must be within [0.01, 0.3] s")

    def zenoh_config(self) -> zenoh.Config:
        """The Zenoh config; raises MeshConfigError (one line) for a bad config file."""
        try:
            return self._zenoh_config()
        except MeshConfigError:
            raise
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError and friends: say it in one line
            where = f"Zenoh config {self.config_file}" if self.config_file else "Zenoh config"
            raise MeshConfigError(f"{where}: {_one_line(exc)}") from None

    def _zenoh_config(self) -> zenoh.Config:
        if self.config_file is not None:
            check_config_file(self.config_file)
        conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        listen = [] if self.mode == "client" else list(self.listen)
        conf.insert_json5("listen/endpoints", json.dumps(listen))
        conf.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        if self.shared_memory is not None:
            conf.insert_json5("transport/shared_memory/enabled", json.dumps(self.shared_memory))
        # Keep retrying to connect: agents may start before their router does, and a router
        # before the routers it links to (with 0, Zenoh tries each endpoint once, never again).
        # Without exit_on_failure, peers and routers retry in the background; a client waits.
        conf.insert_json5("connect/timeout_ms", "-1")
        conf.insert_json5("connect/exit_on_failure", "false")
        for path, value in self.extra:
            conf.insert_json5(path, value)
        where = f"Zenoh config {self.config_file}" if self.config_file else "Zenoh config"
        check_config_paths(conf, where)
        return conf


class MeshUnreachable(MeshConfigError):
    """No router or peer answered at the endpoints this process connects to; the message
    names them. The tools (status, cmd, record, replay, keygen push) exit 1 on it."""


def unreachable(cfg: MeshConfig, waited_s: float, how: str = "waited") -> MeshUnreachable:
    """The one way to say that nobody answered at `cfg.connect`."""
    role = "router" if cfg.mode == "client" else "router or peer"
    return MeshUnreachable(
        f"no {role} answered at {', '.join(cfg.connect) or '(no --connect endpoint)'} "
        f"({how} {waited_s:.1f} s): start `covey demo` or `covey router` there, or give "
        "--connect the endpoint it printed"
    )


def linked(session: zenoh.Session) -> bool:
    """True once this session has a link to some router or peer."""
    info = session.info
    return bool(list(info.routers_zid()) or list(info.peers_zid()))


def wait_linked(
    session: zenoh.Session,
    timeout_s: float,
    stop: threading.Event | None = None,
    clock_s: Callable[[], float] = time.monotonic,
) -> bool:
    """Wait until the session links to a router or peer: True, or False after `timeout_s`
    (or once `stop` is set) with no link."""
    deadline = clock_s() + timeout_s
    while not linked(session):
        if clock_s() >= deadline or (stop is not None and stop.is_set()):
            return False
        (stop or threading.Event()).wait(0.05)
    return True


def expects_answer(cfg: MeshConfig) -> bool:
    """Whether a tool joining with `cfg` should hear from someone at cfg.connect: a peer or
    client that connects somewhere (a router, or a peer with nothing to connect to, may rightly
    wait alone for others to come)."""
    return cfg.mode != "router" and bool(cfg.connect)


def embedded_router(port: int, fleet: str = "covey", host: str = "127.0.0.1") -> MeshConfig:
    """The config of the process that hosts the embedded mesh (no zenohd needed)."""
    return MeshConfig(fleet=fleet, mode="router", connect=(), listen=(f"tcp/{host}:{port}",))


def embedded_peer(port: int, fleet: str = "covey", host: str = "127.0.0.1") -> MeshConfig:
    """The config of a process that joins an embedded mesh hosted on `port`."""
    return MeshConfig(
        fleet=fleet, mode="peer", connect=(f"tcp/{host}:{port}",), listen=(f"tcp/{host}:0",)
    )


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bind to 0 and read it back); `host` may be an
    IPv6 address, with or without brackets."""
    host = host.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def port_free(port: int, host: str = "127.0.0.1") -> bool:
    """True if a TCP listener could bind `host`:`port` a moment ago (connections of a closed
    one lingering in TIME_WAIT do not count, as for Zenoh's listener)."""
    host = host.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


TCP_PROTOCOLS = ("tcp", "tls", "ws")
"""Zenoh link protocols that listen on a TCP port."""


def with_free_port(endpoint: str) -> str:
    """`endpoint` with port 0 replaced by a TCP port that was free a moment ago, so that the
    endpoint can be printed and handed to others (a Zenoh session does not say which port it
    got); any other endpoint unchanged. Raises MeshConfigError (one line) for port 0 on a
    protocol that is not TCP-based, or a host this machine cannot listen on."""
    m = _ENDPOINT_RE.match(check_endpoint(endpoint))
    if not m or int(m.group(3)) != 0:
        return endpoint
    proto, host, tail = m.group(1), m.group(2), m.group(4) or ""
    if proto not in TCP_PROTOCOLS:
        raise MeshConfigError(
            f"endpoint {endpoint}: give a port (port 0 is picked only for {', '.join(TCP_PROTOCOLS)})"
        )
    try:
        port = free_tcp_port(host)
    except (OSError, UnicodeError) as exc:
        raise MeshConfigError(
            f"endpoint {endpoint}: cannot listen on {host} ({getattr(exc, 'strerror', None) or exc})"
        ) from None
    return f"{proto}/{host}:{port}{tail}"


def open_session(
    cfg: MeshConfig,
    stop: threading.Event | None = None,
    note_every_s: float = 5.0,
    wait_s: float | None = None,
) -> zenoh.Session:
    """Open a Zenoh session; the caller closes it (or uses it as a context manager).
    Raises MeshConfigError (one line) when Zenoh refuses: a busy port, a bad certificate...

    A client waits inside Zenoh until a router at `cfg.connect` answers. It waits on a thread
    here, so that this one logs where it waits every `note_every_s` and gives up (a
    MeshUnreachable naming the endpoints) once `stop` is set or after `wait_s` (None: no
    limit), instead of hanging deaf to Ctrl-C."""
    conf = cfg.zenoh_config()
    if cfg.mode != "client":
        return _open(conf, cfg)
    out: list = []
    opened, lock, gave_up = threading.Event(), threading.Lock(), [False]

    def run() -> None:
        try:
            session = _open(conf, cfg)
        except MeshConfigError as exc:
            out.append(exc)
        else:
            with lock:
                late = gave_up[0]
                if not late:
                    out.append(session)
            if late:  # the caller has gone: nobody else would close it
                session.close()
        finally:
            opened.set()

    threading.Thread(target=run, name="zenoh-open", daemon=True).start()
    where, started_s = ", ".join(cfg.connect), time.monotonic()
    noted_s = started_s
    while not opened.wait(0.1):
        late = wait_s is not None and time.monotonic() - started_s >= wait_s
        if late or (stop is not None and stop.is_set()):
            with lock:
                gave_up[0] = not out
            if gave_up[0]:
                how = "gave up after" if late else "stopped after"
                raise unreachable(cfg, time.monotonic() - started_s, how)
            break  # it opened just now: the caller closes it
        if time.monotonic() - noted_s >= note_every_s:
            noted_s = time.monotonic()
            log.warning("waiting for a router at %s (a client starts once one answers)", where)
    if isinstance(out[0], MeshConfigError):
        raise out[0]
    return out[0]


def _open(conf: zenoh.Config, cfg: MeshConfig) -> zenoh.Session:
    try:
        return zenoh.open(conf)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError: one line, not a traceback
        raise MeshConfigError(
            f"cannot join the mesh ({', '.join(cfg.listen) or 'no listen'}): {_one_line(exc)}"
        ) from None
