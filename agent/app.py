"""The agent: one vehicle's shell around the flight core. Mesh in, vehicle backend out.

The flight logic (modes, command checks, vehicle events, failsafes, guidance) is the flight core
(agent/flight_core.py) with one vehicle; this module only moves data. Every tick (10 Hz by
default) it reads its vehicle, lets the core see the telemetry, flies what the core decides
(velocity setpoints in companion mode, traffic reports in onboard mode) and publishes its state.
Commands arrive on Zenoh's thread and are answered at once: the ack says whether the mode
machine accepted the command, with the reason for a refusal. The autopilot's part runs on the
vehicle's action queue (agent/actions.py); its outcome follows as an ACTION event bound to the
command's nonce, and a failure rolls the mode back. Neither the tick nor the state stream ever
waits on the autopilot's actions.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.actions import ActionQueue, outcome_of, perform
from agent.backends.base import (
    BackendError,
    Capability,
    NotSupported,
    Traffic,
    VehicleBackend,
)
from agent.failsafe import FailsafeConfig
from agent.flight_core import Action, CoreConfig, FlightCore, Note, Observed
from agent.guidance import Guidance, GuidanceConfig, NeighbourViews
from agent.neighbours import NeighbourConfig, NeighbourSnapshot, NeighbourTable
from agent.traffic import merge_traffic
from comms.gate import GateConfig, command_refusals
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.plan import FleetPlan
from comms.plan_sync import START_PULL_S, PlanSync, describe
from comms.schema import (
    POS_SIGMA_LIMIT_M,
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    EventKind,
    GuidanceTrace,
    Mission,
    Mode,
    Role,
    Severity,
    StateFlag,
    VehicleState,
)
from comms.scope import Scope, ScopeConfig
from comms.session import MeshConfig
from comms.state_rate import IDLE_STATE_HZ, StatePacer, SteadyConfig, check_rates, idle_rows
from comms.traffic import (
    TrafficConfig,
    TrafficListener,
    TrafficTable,
    TrafficTrack,
    is_traffic_id,
    publish_report,
)
from kit.ticks import run_ticks
from trust.heartbeat import HeartbeatConfig, StationHeartbeats

log = logging.getLogger(__name__)
LINK_STATS_PERIOD_S = 5.0
"""How often an agent behind an emulated link publishes the link's statistics as an Event."""


@dataclass(frozen=True)
class AgentConfig:
    """Everything one vehicle's agent needs."""

    vehicle_id: int
    mesh: MeshConfig = MeshConfig()
    tick_hz: float = 10.0
    """Guidance rate."""
    state_hz: float = 10.0
    """State publishing rate (a radio link may pass fewer; see comms.link)."""
    idle_state_hz: float = IDLE_STATE_HZ
    """State publishing rate while the vehicle is idle: landed (or killed), disarmed, on the
    ground, no autopilot action under way. At least 1 Hz (comms/state_rate.py); back to
    `state_hz` from the tick after a command or arming ends it."""
    steady: SteadyConfig | None = None
    """Publish at the steady rate while receivers can predict the state (hovering, flying
    straight): comms/state_rate.py; None: always at `state_hz` in the air."""
    takeoff_alt_m: float = 10.0
    """Default take-off altitude when a takeoff command gives none."""
    origin: GeoOrigin = GeoOrigin()
    guidance: GuidanceConfig = GuidanceConfig()
    neighbours: NeighbourConfig = NeighbourConfig()
    traffic: TrafficConfig = TrafficConfig()
    """Traffic that does not cooperate (agent/traffic.py): mesh reports and the autopilot's
    ADS-B receiver, flown around as non-cooperative neighbours."""
    traffic_report_hz: float = 2.0
    """How often the traffic the autopilot's receiver hears is reported on the mesh."""
    scope: ScopeConfig = ScopeConfig()
    """Which neighbours' states to hear: the grid cells within reach (widened to what `guidance`
    needs), or the whole fleet with `enabled=False` (comms/scope.py, docs/scaling.md)."""
    failsafe: FailsafeConfig = FailsafeConfig()
    link: str = "perfect"
    """Radio link emulated between this agent and the others (comms.link spec)."""
    open_mode: bool = True
    """Commands are not authenticated (simulator demo only)."""
    trace_guidance: bool = False
    """Publish a GuidanceTrace message after each state (what the policy saw and commanded), so
    that `covey replay --policy` can replay this flight closed-loop exactly."""
    plan: FleetPlan | None = None
    """A fleet plan to hold from start (`covey agent --plan plan.bin`), checked as one that
    arrives (its signer, in keyed mode); a newer one on the mesh replaces it."""

    def __post_init__(self) -> None:
        from comms.keys import check_vehicle_id

        check_vehicle_id(self.vehicle_id)
        if not (math.isfinite(self.tick_hz) and 0 < self.tick_hz <= 100):
            raise ValueError(f"tick_hz must be within (0, 100], got {self.tick_hz}")
        check_rates(self.state_hz, self.idle_state_hz)


class Agent:
    """One vehicle: the flight core with N = 1 between a backend and the mesh."""

    def __init__(
        self,
        cfg: AgentConfig,
        backend: VehicleBackend,
        mesh: Mesh,
        *,
        guidance: Guidance | None = None,
        clock_s: Callable[[], float] = time.monotonic,
        link: object | None = None,
    ) -> None:
        self.cfg = cfg
        self.vid = cfg.vehicle_id
        self.backend = backend
        self.mesh = mesh
        self.clock_s = clock_s
        self.velocity_mode = Capability.VELOCITY_SETPOINT in backend.capabilities
        if self.velocity_mode and guidance is None:
            guidance = Guidance(cfg.guidance)
        self.guidance = guidance
        now = clock_s()
        core_cfg = CoreConfig(cfg.takeoff_alt_m, cfg.origin, cfg.guidance, cfg.failsafe)
        self.core = FlightCore(
            core_cfg,
            1,
            now_s=now,
            velocity_mode=self.velocity_mode,
            guidance=guidance.batch if guidance is not None else None,
            vehicle_ids=(self.vid,),
        )
        # With scoping, the table keeps (and signature-checks) only the neighbours within the
        # scope's reach: the subscribed cells hold several times its disc (agent/neighbours.py).
        self.table = NeighbourTable(
            self.vid,
            cfg.neighbours,
            reach_m=cfg.guidance.scope(cfg.scope).reach_m if cfg.scope.enabled else None,
        )
        self.traffic = TrafficTable(cfg.traffic)
        self.traffic_listener = TrafficListener(mesh, self.traffic, clock_s)
        self._last_traffic_report_s = -math.inf
        self._heard: dict[int, TrafficTrack] = {}  # heard by our autopilot since the last report
        self.flags = StateFlag.OPEN_MODE if cfg.open_mode else StateFlag.NONE
        self.seq = 0
        self._progress = (0, 0)
        """The mission progress (item, items) of the last tick, for its state."""
        self._lock = threading.Lock()  # guards the core: the tick and Zenoh's threads share it
        self.pacer = StatePacer(cfg.state_hz, cfg.idle_state_hz, cfg.tick_hz, steady=cfg.steady)
        """Which ticks publish a state (comms/state_rate.py: the idle rate while idle)."""
        self._last_traffic_s = -math.inf
        self._link_was_ok = True
        self.link = link
        self.on_position: Callable[[tuple[float, float, float]], None] | None = None
        self._last_link_stats_s = now
        self.actions = ActionQueue(
            lambda a: perform(a, backend), self._on_outcome, name=f"actions-{self.vid}"
        )
        # The station-lost failsafe and the take-off check trust signed station heartbeats,
        # not liveliness tokens (trust/heartbeat.py); they also give this vehicle's clock offset.
        self.stations = StationHeartbeats(
            mesh,
            HeartbeatConfig(),
            clock_s=clock_s,
            on_summary=lambda line: self._event(
                line, EventKind.SECURITY, Severity.WARNING, quiet=True
            ),
        )
        if getattr(mesh, "auth", None) is not None:
            mesh.auth.clock_note = self.stations.clock_problem  # named in stale-command refusals
            # Commands refused before handle_command runs: one SECURITY event per cause a second
            # (a flood must not become one).
            mesh.auth.on_reject = command_refusals(
                lambda line: self._event(line, EventKind.SECURITY, Severity.WARNING),
                mesh.clock_ns,
            )
            # Refused neighbour states (forged, replayed...): one SECURITY event per cause a second.
            mesh.on_security = lambda line: self._event(
                line, EventKind.SECURITY, Severity.WARNING, quiet=True
            )
        gate = GateConfig(min_interval_s=cfg.neighbours.verify_min_interval_s)
        self.scope: Scope | None = None
        self._cells: frozenset = frozenset()
        if cfg.scope.enabled:
            # Hear the cells within reach of this vehicle, moved as it flies, from its first tick
            # that is not idle on: a vehicle that does not know where it is, or that sits on the
            # ground with nothing to do, hears nothing (`_hear`).
            self.scope = Scope(cfg.guidance.scope(cfg.scope))
            self.states = mesh.subscribe_cells(
                self._on_state,
                (),
                link,
                gate=gate,
                ignore_id=self.vid,
                worth_checking=self.table.worth_checking,
            )
        else:
            self.states = mesh.subscribe_states(
                self._on_state, link=link, ignore_id=self.vid, gate=gate
            )
        # The fleet plan (comms/plan_sync.py): gotos and take-offs are checked against it.
        self.plan = PlanSync(
            mesh.session,
            mesh.fleet,
            getattr(mesh, "auth", None),
            plan=cfg.plan,
            on_plan=self._on_plan,
            on_summary=lambda line: self._event(
                line, EventKind.SECURITY, Severity.WARNING, quiet=True
            ),
        )
        if self.plan.plan is not None:  # the one it started with
            self.core.set_plan(self.plan.plan)
        self.plan.pull_now(START_PULL_S)  # a rebooted vehicle holds the plan before any command
        # Answer commands before announcing presence: whoever sees us alive can command us.
        mesh.serve_commands(self.vid, self.handle_command, on_mission=self.handle_mission)
        mesh.declare_vehicle(self.vid)

    def _on_state(self, state: VehicleState, _recv_ns: int) -> None:
        self.table.update(state, self.clock_s())

    def _hear(self, pos_ned_m: np.ndarray, idle: bool) -> None:
        """Subscribe to the cells within reach, or to none while idle: guidance does not run on
        the ground, and the tick that ends idleness (a command, arming) subscribes again before
        the vehicle climbs (docs/scaling.md, "Idle vehicles"). A few comparisons per tick unless
        the set changes."""
        if idle:
            want: frozenset = frozenset()
        else:
            self.scope.update(pos_ned_m)
            want = self.scope.cells
        if want != self._cells:
            self.states.set_cells(want)
            self._cells = want

    def close(self) -> None:
        """Stop the action queue (what still waits is reported as not run)."""
        self.actions.close()
        self.plan.undeclare()
        self.stations.close()
        self.traffic_listener.close()

    def __enter__(self) -> Agent:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def mode(self) -> Mode:
        return self.core.mode_of(0)

    # -- events ------------------------------------------------------------------------------
    def _on_plan(self, plan: FleetPlan) -> None:
        with self._lock:
            self.core.set_plan(plan)
        self._event(f"fleet plan v{plan.version}: {describe(plan)}")
        if Capability.GEOFENCE in self.backend.capabilities:  # the autopilot's own backstop
            threading.Thread(
                target=self._upload_fence, args=(plan,), name="fence-upload", daemon=True
            ).start()

    def _upload_fence(self, plan: FleetPlan) -> None:
        """Give the autopilot the plan's fence (slow I/O: off the Zenoh thread), and say how
        that went."""
        try:
            self.backend.upload_fence(plan)
        except (BackendError, NotSupported) as exc:
            self._event(f"autopilot geofence NOT updated: {exc}", severity=Severity.WARNING)
            return
        self._event(f"autopilot geofence set from fleet plan v{plan.version}")

    def _event(
        self,
        text: str,
        kind: EventKind = EventKind.STATUS,
        severity: Severity = Severity.INFO,
        quiet: bool = False,
    ) -> None:
        if not quiet:
            log.info("vehicle %d: %s", self.vid, text)
        try:
            self.mesh.event(self.vid, text, kind=kind, severity=severity)
        except Exception as exc:  # noqa: BLE001 - an event that cannot be sent must not stop flying
            log.warning("could not publish event: %s", exc)

    def _notes(self, notes: list[Note]) -> None:
        for note in notes:
            self._event(note.text, note.kind, note.severity)

    # -- commands (Zenoh thread) ---------------------------------------------------------------
    def handle_command(self, cmd: Command) -> CommandAck:
        """Answer at once: the mode machine's verdict. The autopilot's part is queued."""
        tel = self.backend.telemetry()
        pos = None if tel is None else np.array(tel.pos_ned_m)
        problem = None
        if cmd.kind is CommandKind.TAKEOFF:
            problem = self.stations.takeoff_problem(self.clock_s(), self.cfg.failsafe.require_gcs)
        with self._lock:
            decision = self.core.command(
                0, cmd, pos, link_ok=tel is not None and tel.link_ok, takeoff_problem=problem
            )
            notes = self.core.drain_notes()
        self._notes(notes)
        for action in decision.actions:
            self.actions.submit(action)
        if decision.result is not AckResult.ACCEPTED:
            self._event(
                f"refused {cmd.kind.name.lower()}: {decision.reason}",
                EventKind.COMMAND,
                Severity.WARNING,
            )
        return CommandAck(
            self.vid,
            cmd.nonce,
            self.mesh.clock_ns(),
            decision.result,
            decision.reason,
            decision.mode,
        )

    def handle_mission(self, mission: Mission) -> CommandAck:
        """Answer a mission upload at once: kept (flown on a start), or refused with the reason."""
        with self._lock:
            decision = self.core.load_mission(0, mission)
            notes = self.core.drain_notes()
        self._notes(notes)
        if decision.result is not AckResult.ACCEPTED:
            self._event(f"refused mission: {decision.reason}", EventKind.COMMAND, Severity.WARNING)
        return CommandAck(
            self.vid,
            mission.nonce,
            self.mesh.clock_ns(),
            decision.result,
            decision.reason,
            decision.mode,
        )

    # -- the action queue's thread -------------------------------------------------------------
    def _on_outcome(self, action: Action, error: str | None) -> None:
        rolled = False
        if error is not None:
            with self._lock:
                rolled = self.core.action_failed(action, error)
                notes = self.core.drain_notes()
            self._notes(notes)
        if action.nonce is None:
            return
        outcome = outcome_of(action, self.vid, error, self.mode if rolled else None)
        self._publish_event(outcome.to_event(self.mesh.clock_ns()))

    def _publish_event(self, event) -> None:
        try:
            self.mesh.publish_event(event)
        except Exception as exc:  # noqa: BLE001 - an event that cannot be sent must not stop flying
            log.warning("could not publish an event: %s", exc)

    # -- the loop ------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """One guidance step at time `now_s` (the caller's clock)."""
        be = self.backend
        be.step(now_s)
        tel = be.telemetry()
        if tel is None:
            return
        if tel.link_ok != self._link_was_ok:
            self._link_was_ok = tel.link_ok
            self._event(
                "autopilot link " + ("restored" if tel.link_ok else "LOST"),
                EventKind.FAILSAFE,
                Severity.INFO if tel.link_ok else Severity.CRITICAL,
            )
        pos = np.array(tel.pos_ned_m)
        vel = np.array(tel.vel_ned_m_s)
        if self.on_position is not None:
            self.on_position(tel.pos_ned_m)
        if self.link is not None and now_s - self._last_link_stats_s >= LINK_STATS_PERIOD_S:
            self._last_link_stats_s = now_s
            self._event(self.link.stats_text(), EventKind.LINK_STATS, Severity.DEBUG)
        obs = Observed(
            pos[None],
            vel[None],
            np.array([tel.armed]),
            np.array([tel.in_air]),
            np.array([tel.battery_pct]),
            np.array([tel.link_ok]),
        )
        gcs_alive = self.stations.alive(now_s)
        for report, stamp_ns in self.stations.clock_reports(now_s, (self.vid,)):
            self._publish_event(report.to_event(stamp_ns))
        self._hear_traffic(now_s)
        nbrs = merge_traffic(self.traffic, self.table.snapshot(now_s, pos), now_s, pos)
        busy = self.actions.busy
        flags = self.flags
        out = None
        with self._lock:
            core = self.core
            actions = core.observe(now_s, obs, gcs_alive, self._landing_traffic(now_s))
            idle = bool(idle_rows(core.mode, tel.armed, tel.in_air, busy or bool(actions))[0])
            publish = bool(
                self.pacer.due(
                    now_s,
                    [idle],
                    obs.pos_m,
                    obs.vel_m_s,
                    core.heading_rad,
                    core.mode,
                    obs.armed,
                )[0]
            )
            heading_in_rad = float(core.heading_rad[0])
            rows = core.guided_rows(obs.armed, obs.link_ok)
            if rows.size:
                # Traced flights decide only on published ticks (replayable), unless nothing is held.
                decide = np.zeros(1, bool) if self.cfg.trace_guidance and not publish else None
                out = core.guide(
                    now_s,
                    rows,
                    obs.pos_m,
                    obs.vel_m_s,
                    NeighbourViews.of_snapshot(nbrs, self.vid, tel.pos_sigma_m),
                    decide,
                )
            flags |= core.flags_of(0)
            mode, target, heading = core.mode_of(0), core.target_of(0), float(core.heading_rad[0])
            run = core.missions[0]
            self._progress = run.progress() if run is not None else (0, 0)
            notes = core.drain_notes()
        self._notes(notes)
        for action in actions:
            self.actions.submit(action)
        if self.scope is not None:
            self._hear(pos, idle)
        if not tel.link_ok:
            flags |= StateFlag.FAILSAFE_LINK_LOST
        if out is not None:
            try:
                be.set_velocity_ned(out.vel_ned_m_s[0], heading)
            except BackendError as exc:
                log.warning("setpoint refused: %s", exc)
            if out.filtered[0]:
                flags |= StateFlag.FILTER_ACTIVE
            if out.slowed_for_stale[0]:
                flags |= StateFlag.NEIGHBOURS_STALE
        elif (
            tel.link_ok
            and Capability.TRAFFIC_INPUT in be.capabilities
            and now_s - self._last_traffic_s >= 0.1
        ):
            self._last_traffic_s = now_s
            manned = {t.neighbour_id for t in self.traffic.tracks(now_s) if t.manned}
            traffic = [
                Traffic(
                    vid,
                    tuple(p),
                    tuple(v),
                    float(h),
                    float(a),
                    cooperative=not is_traffic_id(vid),
                    manned=vid in manned,
                )
                for vid, p, v, h, a in zip(
                    nbrs.ids,
                    nbrs.pos_ned_m,
                    nbrs.vel_ned_m_s,
                    nbrs.heading_rad,
                    nbrs.age_s,
                    strict=True,
                )
            ]
            try:
                be.send_traffic(traffic)
            except BackendError as exc:
                log.warning("traffic forward failed: %s", exc)
        if nbrs.stale_ids:
            flags |= StateFlag.NEIGHBOURS_STALE
        if publish:
            self._publish(tel, pos, vel, heading, mode, target, flags)
            if self.cfg.trace_guidance and out is not None:
                self._trace(heading_in_rad, out, nbrs)

    def _landing_traffic(self, now_s: float) -> NeighbourSnapshot | None:
        """For the landing order (agent/returning.py): every flying neighbour at any height (the
        guidance's snapshot keeps only those in its vertical band); None while it is off."""
        if self.cfg.failsafe.returning.land_radius_m <= 0:
            return None
        return self.table.snapshot(now_s)

    def _hear_traffic(self, now_s: float) -> None:
        """The autopilot's receiver's traffic into the table, and onto the mesh for the others
        (as this vehicle's signed reports) at `traffic_report_hz`."""
        if Capability.TRAFFIC_RECEIVER not in self.backend.capabilities:
            return
        for track in self.backend.traffic_tracks(now_s):
            if self.traffic.put(track):
                self._heard[track.track_id] = track
        if now_s - self._last_traffic_report_s < 1.0 / self.cfg.traffic_report_hz:
            return
        self._last_traffic_report_s = now_s
        stamp_ns = self.mesh.clock_ns()
        # only what our own receiver heard since the last report, never others' reports again
        heard, self._heard = list(self._heard.values()), {}
        for track in heard:
            age_ns = int(max(0.0, now_s - track.stamp_s) * 1e9)
            try:
                publish_report(self.mesh, track.report(Role.VEHICLE, self.vid, stamp_ns - age_ns))
            except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop the tick
                log.warning("traffic report not published: %s", exc)

    def _trace(self, heading_in_rad: float, out, nbrs) -> None:
        trace = GuidanceTrace.build(
            self.vid,
            self.seq,
            self.mesh.clock_ns(),
            heading_in_rad,
            out.vel_ned_m_s[0],
            nbrs.ids,
            nbrs.seqs,
            nbrs.age_s,
            decided=bool(out.decided[0]),
        )
        try:
            self.mesh.publish_trace(trace)
        except Exception as exc:  # noqa: BLE001 - a trace that cannot be sent must not stop flying
            log.warning("could not publish a guidance trace: %s", exc)

    def _publish(self, tel, pos, vel, heading_rad, mode: Mode, target, flags: StateFlag) -> None:
        if target is not None:
            flags |= StateFlag.HAS_GOAL
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        state = VehicleState(
            vehicle_id=self.vid,
            seq=self.seq,
            stamp_ns=self.mesh.clock_ns(),
            pos_ned_m=tuple(float(x) for x in pos),
            vel_ned_m_s=tuple(float(x) for x in vel),
            heading_rad=float(math.remainder(heading_rad, 2 * math.pi)),
            mode=mode,
            armed=tel.armed,
            battery_pct=float(min(100.0, max(0.0, tel.battery_pct))),
            flags=flags,
            goal_ned_m=tuple(float(x) for x in target) if target is not None else (0.0, 0.0, 0.0),
            mission_item=self._progress[0],
            mission_items=self._progress[1],
            pos_sigma_m=float(min(POS_SIGMA_LIMIT_M, max(0.0, tel.pos_sigma_m))),
        )
        try:
            self.mesh.publish_state(state)
        except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop guidance
            log.warning("state publish failed: %s", exc)

    def run(self, stop: threading.Event) -> None:
        """Tick at `tick_hz` until `stop` is set."""
        run_ticks(self.tick, self.cfg.tick_hz, self.clock_s, stop)
