"""The ground station: joins the mesh, keeps the fleet model, serves the viser web app.

    with GroundStation(cfg) as gcs:       # mesh + viser server + render loop
        print(gcs.url); gcs.wait()

The mesh feeds the FleetModel from Zenoh threads; one render thread draws the scene at
`scene_rate_hz` and the table at `table_rate_hz` from snapshots; commands go out on a worker.
"""

from __future__ import annotations

import functools
import itertools
import logging
import secrets
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import viser

from comms.commands import OutcomeStatus
from comms.geo import GeoOrigin
from comms.link import LinkEmulator
from comms.mesh import Mesh
from comms.plan import FleetPlan, PadLayout
from comms.presence import Presence
from comms.schema import (
    ActionOutcome,
    ClockReport,
    Command,
    CommandAck,
    CommandKind,
    DecodeError,
    Event,
    EventKind,
    Mission,
    Severity,
    VehicleState,
)
from comms.session import MeshConfig
from comms.traffic import TrafficListener, TrafficTable
from groundstation import dispatch, layout, plan_editor, scenarios
from groundstation.browser_form import BrowserForms
from groundstation.command_log import CommandLog, LoggedCommand
from groundstation.dispatch import CommandWorker, Dispatched
from groundstation.events import EventBuffer, EventsView
from groundstation.fleet import FleetConfig, FleetModel
from groundstation.formation import FormationMemory
from groundstation.inputs import CommandRequest
from groundstation.mission_io import MissionRequest
from groundstation.panel import FORM_LABELS, CommandPanel, Job, PanelHooks
from groundstation.plan_view import PlanView
from groundstation.scene import FleetScene, SceneConfig
from groundstation.tables import command_log_html, fleet_table, legend, traffic_table
from groundstation.web_auth import Gate, GateConfig, is_loopback, read_password_file, url_host
from groundstation.web_proxy import WebProxy, bind_listener, tls_context
from groundstation.web_viser import operator_of, start_viser
from kit.ticks import run_ticks
from trust.auth import load_auth
from trust.heartbeat import HeartbeatPublisher

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GcsConfig:
    """Everything `covey gcs` needs."""

    mesh: MeshConfig = field(default_factory=MeshConfig)
    """How to join the mesh (ignored when a Mesh is passed to GroundStation)."""
    host: str = "127.0.0.1"
    """Address the web app listens on (loopback unless you mean to share it: another address
    needs `certfile`/`keyfile`, or `insecure_http`)."""
    port: int = 8080
    """Web port; if busy, the next free one is used and printed."""
    login_token: str | None = None
    """The token of the login URL (`/?token=...`); None: a random one made at start. Unused with
    a password file."""
    token_label: str = "operator"
    """Operator name of a token login (the command log names it)."""
    password_file: str | None = None
    """Operator accounts (`name:<scrypt hash>` lines, mode 600): log in by name and password
    instead of the token; the account names the operator."""
    allow_origins: tuple[str, ...] = ()
    """Origins besides the page's own allowed to open the websocket (a reverse proxy's)."""
    certfile: str | None = None
    """TLS certificate (PEM): serve HTTPS and WSS."""
    keyfile: str | None = None
    """The certificate's private key (PEM)."""
    insecure_http: bool = False
    """Serve plain HTTP on a non-loopback host: the token, the session cookie and every command
    cross the network readable and alterable by anyone on the path."""
    session_max_age_s: float = 12 * 3600.0
    """How long a browser login lasts."""
    gcs_id: int = 1
    """This station's id on the mesh (its liveliness token; the commands' source id)."""
    geofence_radius_m: float = 50.0
    """Geofence drawn around the origin, in metres; also bounds goto targets."""
    separation_m: float = 3.0
    """Vehicles closer than this are flagged red."""
    landing_pads: PadLayout = PadLayout()
    """The landing pads the agents' returns lay around home and each rally point (their
    `--rally-pads`, `--rally-pad-spacing-m`): a plan is pushed only if every pad keeps the
    zones' clearance inside the fence (groundstation/plan_edit.py `check_landing`)."""
    scene_rate_hz: float = 10.0
    """Scene updates per second."""
    table_rate_hz: float = 5.0
    """Fleet table updates per second (presence loss shows within 1 / rate)."""
    command_timeout_s: float = 2.0
    """How long to wait for every vehicle's ack."""
    origin: GeoOrigin = field(default_factory=GeoOrigin)
    """Fleet origin (NED 0,0,0), for goto-global defaults."""
    swap_radius_m: float = 12.0
    """Radius of the swap scenario's circle."""
    kill_window_s: float = 5.0
    """Seconds after 'Arm kill' during which 'CONFIRM KILL' works."""
    seed: int = 0
    """Seed of the random-goals scenario."""
    view_radius_m: float = 20.0
    """The initial camera frames about this radius around the origin."""
    link: str = "perfect"
    """Emulated radio link between the vehicles and this station (comms.link spec: perfect, xbee,
    wifi, ...); the station sits at the origin. The link-health columns then show its effect."""
    key_file: str | None = None
    """Fleet key that signs commands (trust/auth.py); None: $COVEY_FLEET_KEY_FILE, $COVEY_FLEET_KEY,
    else open mode (ignored when a Mesh is passed to GroundStation)."""
    every_state: bool = False
    """Hear every state of every vehicle at its full rate, instead of the fleet feed (each
    process's latest states at its MeshConfig.feed_hz, docs/scaling.md). For small fleets and
    debugging: it costs the station a message, a decode and (keyed) a verification per state."""


def web_host_problem(host: str) -> str | None:
    """Why the web app cannot listen on `host` (not an address of this machine, or not an
    address at all), or None. Checked before the station joins the mesh."""
    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        return f"--host {host!r} is not an address this machine can listen on ({exc})"
    family, _, _, _, addr = infos[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.bind(addr)
    except OSError as exc:
        return f"--host {host!r}: cannot listen there ({exc.strerror or exc})"
    return None


def web_exposure_problem(cfg: GcsConfig) -> str | None:
    """Why the web app must not start as configured (a network-reachable host without TLS and
    without --insecure-http, half a certificate), or None. Checked before the station joins the
    mesh."""
    if (cfg.certfile is None) != (cfg.keyfile is None):
        return "--certfile and --keyfile go together (the certificate and its private key)"
    tls = cfg.certfile is not None
    if cfg.insecure_http and tls:
        return "--insecure-http and --certfile contradict each other: choose one"
    if cfg.insecure_http and is_loopback(cfg.host):
        return f"--insecure-http is for a non-loopback --host; {cfg.host} is loopback"
    if not is_loopback(cfg.host) and not tls and not cfg.insecure_http:
        return (
            f"--host {cfg.host} is reachable from the network: serve it over TLS (--certfile "
            "and --keyfile), or pass --insecure-http to accept that anyone on the path can read "
            "the login and the commands"
        )
    return None


class GroundStation:
    """Context manager: the running ground station."""

    def __init__(
        self,
        cfg: GcsConfig,
        *,
        mesh: Mesh | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        stop: threading.Event | None = None,
    ) -> None:
        """`stop`: a client waiting for its router gives up once it is set (Mesh)."""
        self.cfg = cfg
        self._stop_waiting = stop
        self._clock_ns = clock_ns
        self._given_mesh = mesh
        self.mesh: Mesh | None = None
        self.fleet = FleetModel(FleetConfig(separation_m=cfg.separation_m))
        self.presence: Presence | None = None
        self.server: viser.ViserServer | None = None
        self.web: WebProxy | None = None
        self._operators: dict[int, str | None] = {}  # client id -> who logged in that tab
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rng = np.random.default_rng(cfg.seed)
        self.update_times_s: list[float] = []
        self.events = EventBuffer()
        self.commands = CommandLog(on_superseded=self._on_superseded)
        self._commands_shown: tuple[int, int] = (-1, -1)
        self._tabs_lock = threading.Lock()
        self.panels: dict[int, CommandPanel] = {}
        self.plan_editors: dict[int, plan_editor.PlanEditor] = {}
        """Each browser tab's fleet plan editor, by client id."""
        self._event_views: dict[int, EventsView] = {}
        self._sent_by: OrderedDict[int, int] = OrderedDict()  # nonce -> client id that sent it
        self.last_result: Dispatched | None = None
        self.routes: dict[int, list[tuple[float, float, float]]] = {}
        """Each vehicle's route (NED waypoints) of the last mission it accepted from this
        station, drawn while its states say it has a mission."""
        self._routes_drawn: frozenset[int] | None = None
        self._routes_lock = threading.Lock()
        self._link: LinkEmulator | None = None
        self._heartbeats: HeartbeatPublisher | None = None
        self.traffic = TrafficTable()
        """Traffic that does not cooperate, as the mesh reports it (agent/traffic.py)."""
        self._traffic_listener: TrafficListener | None = None

    # -- lifecycle -----------------------------------------------------------------------
    def __enter__(self) -> GroundStation:
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _start(self) -> None:
        cfg = self.cfg
        problem = web_host_problem(cfg.host) or web_exposure_problem(cfg)
        if problem:  # before anything joins the mesh
            raise ValueError(problem)
        accounts = read_password_file(cfg.password_file) if cfg.password_file else {}
        tls = tls_context(cfg.certfile, cfg.keyfile) if cfg.certfile and cfg.keyfile else None
        self.mesh = self._given_mesh or Mesh(
            cfg.mesh,
            clock_ns=self._clock_ns,
            auth=load_auth(cfg.key_file),
            stop=self._stop_waiting,
        )
        if self.mesh.auth is not None:  # list only vehicles that something signed proved
            self.fleet = FleetModel(FleetConfig(separation_m=cfg.separation_m, verified_only=True))
        if cfg.link not in ("", "perfect"):
            from comms.link import emulator_from_spec

            self._link = emulator_from_spec(
                cfg.link, seed=cfg.seed, receiver_pos=lambda: (0.0, 0.0, 0.0)
            )
            self._link.__enter__()
        subscribe = self.mesh.subscribe_states if cfg.every_state else self.mesh.subscribe_feed
        subscribe(self._on_state, link=self._link, on_refused=self.fleet.on_state_refused)
        self.mesh.on_security = self._on_security
        self.mesh.subscribe_events(self._on_event, on_outcome=self._on_outcome)
        self._traffic_listener = TrafficListener(self.mesh, self.traffic, time.monotonic)
        self.mesh.observe_commands(self._on_command, self._on_ack)
        self.presence = self.mesh.presence(self._on_presence)
        self._start_web(accounts, tls)
        assert self.server is not None  # _start_web started it
        self.server.gui.configure_theme(
            control_width="large", show_share_button=False, brand_color=(20, 110, 160)
        )
        cam, view_m = self.server.initial_camera, self.cfg.view_radius_m
        cam.position, cam.look_at = (-0.45 * view_m, -1.3 * view_m, 0.9 * view_m), (0.0, 0.0, 2.0)
        self._build_gui()
        self._worker: CommandWorker | None = CommandWorker(self._on_result)
        self._thread = threading.Thread(target=self._loop, name="gcs-render", daemon=True)
        self._thread.start()
        # Present on the mesh only once the web app and the mesh are both up: vehicles treat a
        # present station as one that an operator can use.
        self.mesh.declare_gcs(cfg.gcs_id)
        # What the vehicles' station-lost failsafe trusts (the token above is unsigned).
        self._heartbeats = HeartbeatPublisher(self.mesh, cfg.gcs_id)

    def _start_web(self, accounts: dict[str, str], tls) -> None:
        """viser on an internal port, behind the login gate on the public one (web_viser)."""
        cfg, secret = self.cfg, secrets.token_urlsafe(32)
        self.server = start_viser(secret)
        sock = bind_listener(cfg.host, cfg.port)
        token = None if accounts else (cfg.login_token or secrets.token_urlsafe(24))
        gate = Gate(
            GateConfig(
                scheme="https" if tls else "http",
                port=sock.getsockname()[1],
                bind_host=cfg.host,
                token=token,
                token_label=cfg.token_label,
                accounts=accounts,
                allow_origins=cfg.allow_origins,
                session_max_age_s=cfg.session_max_age_s,
            ),
            clock_s=lambda: self._clock_ns() / 1e9,
        )
        self.web = WebProxy(sock, gate, self.server.get_port(), secret, ssl_context=tls)
        self.web.__enter__()

    def _build_gui(self) -> None:
        assert self.server is not None and self.mesh is not None
        gui = self.server.gui
        auth = self.mesh.auth
        trust = (
            f"keyed, roster v{auth.roster.version}"
            if auth is not None
            else "**OPEN MODE**: commands and states are not signed"
        )
        gui.add_markdown(
            f"**covey** ground station · fleet `{self.mesh.fleet}` · station {self.cfg.gcs_id} · {trust}",
            order=layout.TITLE,
        )
        with gui.add_folder("Fleet", order=layout.FLEET):
            self.table = gui.add_html("<i>waiting for vehicles…</i>")
            gui.add_html(legend())
        with gui.add_folder("Traffic (not cooperating)", order=layout.TRAFFIC):
            self.traffic_html = gui.add_html(traffic_table([], 0.0))
        with gui.add_folder("Command log (every station)", order=layout.COMMAND_LOG):
            self.command_log_html = gui.add_html(command_log_html([]))
        self.forms = BrowserForms(self.server, FORM_LABELS + plan_editor.LABELS)
        self._hooks = PanelHooks(
            known_ids=self.known_ids,
            dispatch=self.dispatch,
            scenario=self.scenario_jobs,
            now_s=time.monotonic,
            positions=self.fleet.positions,
            pos_sigmas=self.fleet.pos_sigmas,
            formations=FormationMemory(),
            separation_m=self.cfg.separation_m,
            fleet_plan=self._fleet_plan,
        )
        self.server.on_client_connect(self._open_tab)
        self.server.on_client_disconnect(self._close_tab)
        self.scene = FleetScene(
            self.server,
            SceneConfig(self.cfg.geofence_radius_m, self.cfg.separation_m),
            on_vehicle_click=self._select,
        )
        # The fleet plan: followed, drawn, listed, replaced by an uploaded file (plan_view.py).
        self.plan_view: PlanView | None = PlanView(
            self.server,
            self.mesh,
            self.scene,
            self.cfg.origin,
            order=layout.TRAFFIC + 0.25,
            log=self.commands,
            states=self._vehicle_states,
            separation_m=self.cfg.separation_m,
            pads=self.cfg.landing_pads,
        )

    # -- browser tabs: each has its own events filter and command panel ------------------
    def _open_tab(self, client: viser.ClientHandle) -> None:
        view = EventsView(client.gui, self.events, self.commands.name_of, order=layout.EVENTS)
        panel = CommandPanel(
            client,
            self._hooks,
            self.forms,
            self.cfg.origin,
            goto_limit_m=self.cfg.geofence_radius_m,
            kill_window_s=self.cfg.kill_window_s,
        )
        assert self.server is not None and self.plan_view is not None  # only while it serves
        operator = operator_of(self.server, client.client_id)
        editor = plan_editor.PlanEditor(
            client,
            self.plan_view,
            self.forms,
            states=self._vehicle_states,
            operator=lambda: operator,
            order=layout.TRAFFIC + 0.3,
        )
        with self._tabs_lock:
            self._event_views[client.client_id] = view
            self.panels[client.client_id] = panel
            self.plan_editors[client.client_id] = editor
            self._operators[client.client_id] = operator

    def _close_tab(self, client: viser.ClientHandle) -> None:
        with self._tabs_lock:
            self._event_views.pop(client.client_id, None)
            self.panels.pop(client.client_id, None)
            self.plan_editors.pop(client.client_id, None)
            self._operators.pop(client.client_id, None)

    def _tabs(self) -> tuple[list[CommandPanel], list[EventsView]]:
        with self._tabs_lock:
            return list(self.panels.values()), list(self._event_views.values())

    def _select(self, vehicle_id: int, client_id: int | None, add: bool = False) -> None:
        with self._tabs_lock:
            panel = self.panels.get(client_id) if client_id is not None else None
        if panel is not None:
            panel.select(vehicle_id, add)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        worker = getattr(self, "_worker", None)
        if worker is not None:
            worker.close()
            self._worker = None
        if self.web is not None:
            self.web.close()
            self.web = None
        if self.server is not None:
            self.server.stop()
            self.server = None
        if self._heartbeats is not None:
            self._heartbeats.close()
            self._heartbeats = None
        if self._traffic_listener is not None:
            self._traffic_listener.close()
            self._traffic_listener = None
        plan_view = getattr(self, "plan_view", None)
        if plan_view is not None:
            plan_view.close()
            self.plan_view = None
        if self.mesh is not None and self._given_mesh is None:
            self.mesh.close()
        self.mesh = None
        if self._link is not None:
            self._link.close()
            self._link = None

    @property
    def port(self) -> int:
        """The public web port (the login gate's)."""
        assert self.web is not None
        return self.web.port

    @property
    def url(self) -> str:
        """The page's URL, with the login token when token login is on (click it to log in)."""
        assert self.web is not None
        gate = self.web.gate.cfg
        token = f"/?token={gate.token}" if gate.token else "/"
        return f"{gate.scheme}://{url_host(self.cfg.host)}:{self.web.port}{token}"

    def wait(self) -> None:
        """Block until close() is called from another thread (or a signal handler)."""
        while not self._stop.wait(0.5):
            pass

    # -- mesh callbacks ------------------------------------------------------------------
    def _on_presence(self, kind: str, ident: int, alive: bool) -> None:
        if kind == "vehicle":
            self.fleet.on_presence(ident, alive, self._clock_ns())

    def _on_security(self, line: str) -> None:
        """The mesh's own refusal summaries (one per cause a second) go to the events panel."""
        self.events.add(
            Event(
                vehicle_id=0,
                stamp_ns=self._clock_ns(),
                text=line[:119],
                kind=EventKind.SECURITY,
                severity=Severity.WARNING,
            )
        )

    def _on_outcome(self, outcome: ActionOutcome, recv_ns: int) -> None:
        self.commands.on_outcome(outcome)
        self.events.add(outcome, recv_ns)

    def _on_event(self, event: Event, recv_ns: int) -> None:
        if event.kind is EventKind.CLOCK:
            try:
                self.fleet.on_clock(ClockReport.from_event(event), recv_ns)
            except DecodeError as exc:
                log.warning("vehicle %d sent a malformed clock report: %s", event.vehicle_id, exc)
        self.events.add(event, recv_ns)

    def _on_state(self, state: VehicleState, recv_ns: int, *entry_seq: int) -> None:
        self.fleet.on_state(state, recv_ns, *entry_seq)
        self.commands.on_state(state)  # it may show the vehicle finished its latest command

    def _on_command(self, command: Command | Mission, recv_ns: int, digest: bytes) -> None:
        """Keyed mode: only commands (and mission uploads) whose station signature verifies are
        logged; the rest are counted by cause (one summary line), so a forger can neither pose
        as a station nor push real commands out of the log."""
        auth = self.mesh.auth if self.mesh is not None else None
        check = None
        if auth is not None:
            label = "mission" if isinstance(command, Mission) else "cmd"
            check = functools.partial(auth.verify_command, label=label)
        self.commands.on_command(command, recv_ns, digest, check=check)

    def _on_ack(self, ack: CommandAck, recv_ns: int) -> None:
        auth = self.mesh.auth if self.mesh is not None else None
        check = auth.check_ack if auth is not None else None
        self.commands.on_ack(ack, recv_ns, check=check)

    def _on_superseded(self, before: LoggedCommand, vehicle_id: int, later: LoggedCommand) -> None:
        """Tell the tab that sent `before` that another tab or station replaced it on a vehicle."""
        with self._tabs_lock:
            mine = self._sent_by.get(before.command.nonce)
            theirs = self._sent_by.get(later.command.nonce)
            panel = self.panels.get(mine) if mine is not None else None
        if panel is None or theirs == mine:
            return
        by = (
            "another tab of this station"
            if later.source_id == self.cfg.gcs_id
            else f"station {later.source_id}"
        )
        panel.say(
            f"Superseded on vehicle {vehicle_id}: your {before.describe()} was replaced by "
            f"{by}'s {later.describe()}.",
            error=True,
        )

    # -- panel hooks ---------------------------------------------------------------------
    def _present(self) -> set[int]:
        """Who should answer a command to all: in keyed mode the listed (verified) vehicles
        whose token is up, never a bare token; in open mode every vehicle token."""
        if self.fleet.cfg.verified_only:
            return self.fleet.present_ids()
        return self.presence.vehicles if self.presence else set()

    def _vehicle_states(self) -> list[VehicleState]:
        """The vehicles' latest states (the plan's routes and edits check them)."""
        snap = self.fleet.snapshot(self._clock_ns(), trails=False)
        return [v.state for v in snap.vehicles if v.state is not None]

    def _fleet_plan(self) -> FleetPlan | None:
        """The fleet plan the station follows (plan_view.py), or None."""
        view = getattr(self, "plan_view", None)  # None before start and after close
        return view.sync.plan if view is not None else None

    def known_ids(self) -> set[int]:
        return self._present() | set(self.fleet.ids())

    def dispatch(
        self,
        label: str,
        jobs: Sequence[Job],
        on_done: Callable[[Dispatched], None],
        client_id: int | None = None,
    ) -> None:
        mesh, present = self.mesh, self._present()
        assert mesh is not None  # commands are sent only while the station runs
        timeout_s, source = self.cfg.command_timeout_s, self.cfg.gcs_id
        operator = self.operator(client_id)
        if operator is None:  # a tab the login gate did not name: never send for it
            on_done(Dispatched(label, (), error="this tab has no logged-in operator; nothing sent"))
            return
        log.info("operator %s: %s", operator, label)

        def remember(cmd: Command | Mission) -> None:
            self._remember_sender(cmd, client_id, operator)

        def run() -> list:
            results = []
            for req, targets in jobs:
                res = dispatch.send(
                    mesh,
                    req,
                    targets,
                    present=present,
                    source_id=source,
                    timeout_s=timeout_s,
                    on_built=remember,
                )
                if isinstance(req, MissionRequest):  # the accepted routes, for the scene
                    route = req.route_ned_m(self.cfg.origin)
                    with self._routes_lock:
                        for vid in res.by_status(OutcomeStatus.ACCEPTED):
                            self.routes[vid] = route
                        self._routes_drawn = None
                results.append(res)
            return results

        if self._worker is not None:  # None once closed: nothing is sent any more
            self._worker.submit(label, run, on_done)

    def operator(self, client_id: int | None) -> str | None:
        """Who sends for browser tab `client_id` (the login's account or token label; None if
        the tab has none); "station" for a command with no tab (this process's own API)."""
        if client_id is None:
            return "station"
        with self._tabs_lock:
            return self._operators.get(client_id)

    def _remember_sender(
        self, cmd: Command | Mission, client_id: int | None, operator: str
    ) -> None:
        self.commands.mark_own(cmd.nonce, operator)
        if client_id is None:
            return
        with self._tabs_lock:
            self._sent_by[cmd.nonce] = client_id
            while len(self._sent_by) > 1000:
                self._sent_by.popitem(last=False)

    def scenario_jobs(self, name: str) -> list[Job]:
        positions = {v: p for v, p in self.fleet.positions().items() if v in self.known_ids()}
        if name == "swap":
            goals = scenarios.swap_goals(
                positions, min(self.cfg.swap_radius_m, 0.8 * self.cfg.geofence_radius_m)
            )
        else:
            goals = scenarios.random_goals(positions, 0.6 * self.cfg.geofence_radius_m, self._rng)
        return [
            (CommandRequest(CommandKind.GOTO_LOCAL, g), (vid,)) for vid, g in sorted(goals.items())
        ]

    def _on_result(self, done: Dispatched) -> None:
        self.last_result = done

    # -- render loop ---------------------------------------------------------------------
    def render_once(self, with_table: bool) -> float:
        """One update burst; returns its duration in seconds."""
        assert self.server is not None
        t0 = time.perf_counter()
        now_ns = self._clock_ns()
        trails = self.scene.trail_ids(self.fleet.ids())
        snap = self.fleet.snapshot(now_ns, trails=trails)
        now_s = time.monotonic()
        tracks = self.traffic.tracks(now_s)
        with self._routes_lock:  # a vehicle's route while its states say it has a mission
            flying = frozenset(
                v.vehicle_id
                for v in snap.vehicles
                if v.state is not None and v.state.mission_items and v.vehicle_id in self.routes
            )
            routes = None if flying == self._routes_drawn else {v: self.routes[v] for v in flying}
            self._routes_drawn = flying
        with self.server.atomic():
            self.scene.update(snap)
            self.scene.update_traffic(tracks, now_s)
            if routes is not None:
                self.scene.update_routes(routes)
            if with_table:
                self.table.content = fleet_table(
                    snap, refused_states=self.fleet.phantom_refusals, origin=self.cfg.origin
                )
                self.traffic_html.content = traffic_table(tracks, now_s)
                # Redrawn on a change, and each second (timeouts, the refusals' minute).
                shown = (self.commands.version, now_ns // 1_000_000_000)
                if self._commands_shown != shown:
                    self._commands_shown = shown
                    self.command_log_html.content = command_log_html(
                        self.commands.entries(),
                        now_ns,
                        present=self.known_ids(),
                        answer_timeout_s=self.cfg.command_timeout_s + 1.0,
                        refused=self.commands.refused_last_minute(now_ns),
                        plans=self.commands.plan_changes(),
                    )
                for view in self._tabs()[1]:
                    view.render()
        return time.perf_counter() - t0

    def _loop(self) -> None:
        table_every = max(1, round(self.cfg.scene_rate_hz / self.cfg.table_rate_hz))
        frames = itertools.count()

        def frame(_now_s: float) -> None:
            k = next(frames)
            self.update_times_s.append(self.render_once(with_table=k % table_every == 0))
            del self.update_times_s[:-1000]
            for panel in self._tabs()[0]:
                panel.tick()
            if self.plan_view is not None:
                self.plan_view.tick()

        run_ticks(frame, self.cfg.scene_rate_hz, time.monotonic, self._stop, what="render update")
