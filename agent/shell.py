"""The vehicle shell: the flight core with N rows between N vehicle backends and the mesh.

One shell serves one vehicle (`covey agent --id 3`: a simulator, PX4 over MAVSDK, or a relay to
an autopilot that runs the policy onboard) and many (`covey agent --ids 1-100`, `covey
fleet-sim`: the rows of one simulated fleet). The flight logic (modes, command checks, vehicle
events, failsafes, guidance) is the flight core (agent/flight_core.py); the shell only moves
data. Each tick (10 Hz by default) it answers the commands that came since the last one, reads
its vehicles (agent/autopilots.py), lets the core see the telemetry, flies what the core decides
(velocity setpoints in companion mode, traffic reports in onboard mode) and publishes the states
that are due. A command's ack says whether the mode machine accepted it, with the reason for a
refusal; the autopilot's part runs on the vehicle's action queue (agent/actions.py) and its
outcome follows as an ActionOutcome message (on its event key) bound to the command's nonce; a
failure rolls the mode back.

Each vehicle is its own citizen of the mesh: its own state key, command queryable, liveliness
token and events, and in keyed mode its own key (one FleetAuth per vehicle sharing one roster:
trust/auth.py). What rows share is the work: one batched policy call and one batched filter per
tick, one Zenoh session.
"""

from __future__ import annotations

import collections
import functools
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from agent.actions import ActionQueue, outcome_of, perform
from agent.autopilots import Autopilots
from agent.backends.base import BackendError, Capability, NotSupported
from agent.calm import calm, holding_at_rest
from agent.flight_core import Action, CoreConfig, FlightCore, Note, Observed
from agent.guidance import BatchGuidance, GuidanceStep
from agent.neighbours import NeighbourSnapshot, NeighbourTable
from agent.shell_config import ShellConfig
from agent.shell_rows import link_receivers, stale_rows, vehicle_states
from agent.shell_views import neighbour_views
from agent.traffic import autopilot_traffic, merge_traffic
from comms.gate import GateConfig, command_refusals
from comms.mesh import CellSubscription, Mesh
from comms.one_row import FLAG, NO_ROWS, ROW0
from comms.plan import FleetPlan
from comms.plan_sync import START_PULL_S, PlanSync, describe
from comms.schema import (
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    Event,
    EventKind,
    GuidanceTrace,
    Mission,
    Mode,
    Role,
    Severity,
    StateFlag,
    VehicleState,
)
from comms.scope import Scope
from comms.state_rate import StatePacer, idle_one, idle_rows
from comms.traffic import TrafficListener, TrafficTable, TrafficTrack, publish_report
from kit.ticks import run_ticks
from policy.runtime import GuidancePolicy
from policy.tracking import Tracking
from trust.auth import FleetAuth
from trust.heartbeat import HeartbeatConfig, StationHeartbeats

if TYPE_CHECKING:  # the link emulator is imported only when one is asked for
    from comms.link import LinkEmulator

log = logging.getLogger(__name__)
LINK_STATS_PERIOD_S = 5.0
"""How often a vehicle behind an emulated link publishes the link's statistics as an Event."""

_NOBODY = NeighbourSnapshot(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), (), np.zeros(0), ())


@dataclass
class TickStats:
    """Wall time spent per tick (read them after `run`)."""

    ticks: int = 0
    overruns: int = 0
    tick_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=10_000)
    )
    """The last 10,000 ticks' wall times (a process that runs for days keeps no more)."""

    def summary(self) -> dict[str, float]:
        t = np.array(self.tick_ms) if self.tick_ms else np.zeros(1)
        return {
            "ticks": self.ticks,
            "overruns": self.overruns,
            "tick_ms_p50": float(np.median(t)),
            "tick_ms_p99": float(np.percentile(t, 99)),
        }


class VehicleShell:
    """The vehicles of one process: the flight core with N rows, N backends, one mesh session.
    `auths`: row i's own FleetAuth (keyed mode; the mesh's must share their roster), or None
    each (open mode). A context manager."""

    def __init__(
        self,
        cfg: ShellConfig,
        mesh: Mesh,
        autopilots: Autopilots,
        auths: Sequence[FleetAuth | None],
        *,
        policy: GuidancePolicy | None = None,
        clock_s: Callable[[], float] = time.monotonic,
        link: LinkEmulator | None = None,
    ) -> None:
        n = len(cfg.ids)
        if autopilots.n != n or len(auths) != n:
            raise ValueError(f"{n} vehicle ids need {n} backends and {n} signers")
        self.cfg, self.mesh, self.clock_s, self.link = cfg, mesh, clock_s, link
        self.vehicles = autopilots
        self.ids = np.array(cfg.ids)
        self._own = frozenset(cfg.ids)
        self.auths = list(auths)
        if not cfg.open_mode and self.auths[0] is None:
            raise ValueError("open_mode is off, but the mesh has no key to sign with")
        self.flags = StateFlag.OPEN_MODE if self.auths[0] is None else StateFlag.NONE
        self.velocity_mode = Capability.VELOCITY_SETPOINT in autopilots.capabilities
        guidance = BatchGuidance(cfg.guidance, n, policy) if self.velocity_mode else None
        self.policy = guidance.policy if guidance is not None else None
        now = clock_s()
        core_cfg = CoreConfig(cfg.takeoff_alt_m, cfg.origin, cfg.guidance, cfg.failsafe)
        self.core = FlightCore(
            core_cfg,
            n,
            now_s=now,
            velocity_mode=self.velocity_mode,
            guidance=guidance,
            vehicle_ids=cfg.ids,
        )
        self._lock = threading.RLock()  # guards the core: the tick and Zenoh's threads share it
        backends = autopilots.backends
        if autopilots.sim is not None:
            # Simulated autopilots answer in microseconds: their actions run at once, in order.
            queue = ActionQueue(
                lambda a: perform(a, backends[a.index]), self._on_outcome, threaded=False
            )
            self._queues = [queue] * n
            self._threaded = False
        else:  # real ones take seconds: each vehicle's run on its own thread
            self._queues = [
                ActionQueue(
                    lambda a: perform(a, backends[a.index]), self._on_outcome, f"actions-{v}"
                )
                for v in cfg.ids
            ]
            self._threaded = True
        self._idle_q = np.zeros(n, bool)  # an action queue that runs at once is never busy
        self._one = n == 1  # an agent: one vehicle's tick takes its one-row paths
        self._wake = threading.Event()  # a command came: tick now (`run`, kit/ticks.py)
        self._drained: tuple[int, float] | None = None  # (mesh ns, tick s) while draining
        self._resting = False  # every vehicle idle after the last tick: tick at the idle rate
        self._calm = False  # nothing near any vehicle after the last tick: tick at the calm rate
        self._calm_every = cfg.calm_every
        self._calm_horizon_s = 2.0 * self._calm_every / cfg.tick_hz  # agent/calm.py's H
        self._hold_every = cfg.hold_every
        self._hold_horizon_s = 2.0 * self._hold_every / cfg.tick_hz
        self._calm_periods = 1  # grid periods to the next tick while calm (calm or hold tier)
        self.filtered = np.zeros(n, bool)
        self.slowed = np.zeros(n, bool)
        sim = autopilots.sim
        self.tracking = Tracking(cfg.tracking_config(sim.body.model if sim else None), n)
        """What each row's velocity loop did not fly, taken off its next setpoint."""
        self.seq = np.zeros(n, np.int64)
        """Each vehicle's last published seq (one per state it published: idle is not loss)."""
        self.pacer = StatePacer(cfg.state_hz, cfg.idle_state_hz, cfg.tick_hz, n, cfg.steady)
        """Which ticks publish a state (comms/state_rate.py: the idle rate while idle)."""
        self.stats = TickStats()
        # One vehicle with scoping keeps (and signature-checks) only the others within the scope's
        # reach: its subscribed cells hold several times the reach's disc (agent/neighbours.py).
        reach_m = None
        if len(cfg.ids) == 1 and cfg.see_others and cfg.scope.enabled:
            reach_m = cfg.guidance.scope(cfg.scope).reach_m
        self.table = NeighbourTable(None, cfg.neighbours, reach_m=reach_m)
        """Other processes' vehicles (ours are kept out by `_on_state`)."""
        self.traffic = TrafficTable(cfg.traffic)
        """Traffic that does not cooperate, from the mesh and our receivers (agent/traffic.py)."""
        self.traffic_listener = TrafficListener(mesh, self.traffic, clock_s)
        self._heard: dict[int, tuple[int, TrafficTrack]] = {}  # by our receivers since a report
        self._last_traffic_report_s = -math.inf
        self._last_traffic_s = -math.inf
        self._link_ok = np.ones(n, bool)
        self._last_link_stats_s = now
        self.on_position: Callable[[np.ndarray], None] | None = None
        """Called with the (n, 3) positions each tick (a range-dependent emulated link)."""
        self._security_hookup(mesh)
        # The fleet plan (comms/plan_sync.py): gotos and take-offs are checked against it.
        self.plan = PlanSync(
            mesh.session,
            mesh.fleet,
            mesh.auth,
            plan=cfg.plan,
            on_plan=self._on_plan,
            on_summary=self._security_line,
        )
        if self.plan.plan is not None:  # the one it started with
            self.core.set_plan(self.plan.plan)
        self.plan.pull_now(START_PULL_S)  # hold the plan before answering any command
        self._subscribe(mesh)
        # Answered from the tick, not from one Zenoh thread per vehicle: a command to all would
        # wake every one of them at once (docs/scaling.md, "Commands to a host").
        self.commands = [
            mesh.serve_commands(
                vid,
                functools.partial(self.command, i),
                auth=self.auths[i],
                polled=True,
                on_mission=functools.partial(self.mission, i),
                wake=self._wake,
            )
            for i, vid in enumerate(cfg.ids)
        ]
        for vid in cfg.ids:  # answer commands before announcing presence
            mesh.declare_vehicle(vid)

    def _security_hookup(self, mesh: Mesh) -> None:
        # The station-lost failsafe and the take-off check trust signed station heartbeats,
        # not liveliness tokens (trust/heartbeat.py); they also give this process's clock offset.
        self.stations = StationHeartbeats(
            mesh,
            HeartbeatConfig(),
            clock_s=self.clock_s,
            on_summary=self._security_line,
            tokens=self.cfg.failsafe.require_gcs,
        )
        for i, auth in enumerate(self.auths):
            if auth is None:
                continue
            auth.clock_note = self.stations.clock_problem  # named in stale-command refusals
            # Commands refused before `command` runs: one SECURITY event per cause a second (a
            # flood must not become one), from the vehicle refused, signed by it.
            auth.on_reject = command_refusals(
                functools.partial(self._security_line, row=i, quiet=False), mesh.clock_ns
            )
        if mesh.auth is not None:
            # Refused neighbour states (forged, replayed...): one SECURITY event per cause a second.
            mesh.on_security = self._security_line

    def _subscribe(self, mesh: Mesh) -> None:
        """Hear the other vehicles: the grid cells within reach of ours, moved as they fly, from
        the first tick one of them is not idle (`_hear`); or every state of the fleet."""
        gate = GateConfig(min_interval_s=self.cfg.neighbours.verify_min_interval_s)
        self.scope: Scope | None = None
        self.states = None
        self._cells: frozenset = frozenset()
        one = len(self.cfg.ids) == 1
        if not self.cfg.see_others:
            return
        if self.cfg.scope.enabled:
            self.scope = Scope(self.cfg.guidance.scope(self.cfg.scope), len(self.cfg.ids))
            # Several vehicles share this session: Zenoh would deliver their own states too.
            self.states = mesh.subscribe_cells(
                self._on_state,
                (),
                self.link,
                gate=gate,
                ignore_id=self.cfg.ids[0] if one else None,
                # never this session's own states: its vehicles' echoes (one or several)
                remote_only=True,
                worth_checking=self.table.worth_checking if self.table.reach_m else None,
                polled=True,  # taken at each tick's start (`tick`): no Python call per state
                relay_for=self.cfg.ids[0] if one and self.cfg.cell_relay else None,
            )
        else:
            self.states = mesh.subscribe_states(
                self._on_state,
                link=self.link,
                ignore_id=self.cfg.ids[0] if one else None,
                gate=gate,
            )

    def close(self) -> None:
        """Stop the action queues (what still waits is reported as not run)."""
        for queue in set(self._queues):
            queue.close()
        self.plan.undeclare()
        self.stations.close()
        self.traffic_listener.close()

    def __enter__(self) -> VehicleShell:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- what tests and benches read -----------------------------------------------------------
    @property
    def actions(self) -> ActionQueue:
        """Row 0's action queue."""
        return self._queues[0]

    @property
    def modes(self) -> list[Mode]:
        return self.core.modes

    # -- events ------------------------------------------------------------------------------
    def _on_state(self, state: VehicleState, recv_ns: int) -> None:
        if state.vehicle_id in self._own:
            return
        # the mesh's receive stamp on this clock: a polled state, taken at the tick's start
        # (`_drained`: the mesh clock then and the tick's time), arrived before it
        taken_ns, taken_s = self._drained or (self.mesh.clock_ns(), self.clock_s())
        self.table.update(state, taken_s - max(0, taken_ns - recv_ns) / 1e9)

    def _on_plan(self, plan: FleetPlan) -> None:
        with self._lock:
            self.core.set_plan(plan)
        self._event(f"fleet plan v{plan.version}: {describe(plan)}", quiet=len(self.ids) > 1)
        for i in self.vehicles.capable(Capability.GEOFENCE):  # the autopilot's own backstop
            threading.Thread(
                target=self._upload_fence, args=(i, plan), name="fence-upload", daemon=True
            ).start()

    def _upload_fence(self, i: int, plan: FleetPlan) -> None:
        """Give an autopilot the plan's fence (slow I/O: off the Zenoh thread), and say how
        that went."""
        try:
            self.vehicles.backends[i].upload_fence(plan)
        except (BackendError, NotSupported) as exc:
            self._event(f"autopilot geofence NOT updated: {exc}", severity=Severity.WARNING, row=i)
            return
        self._event(f"autopilot geofence set from fleet plan v{plan.version}", row=i)

    def _security_line(self, line: str, *, row: int = 0, quiet: bool = True) -> None:
        self._event(line, EventKind.SECURITY, Severity.WARNING, quiet=quiet, row=row)

    def _event(
        self,
        text: str,
        kind: EventKind = EventKind.STATUS,
        severity: Severity = Severity.INFO,
        quiet: bool = False,
        *,
        row: int = 0,
    ) -> None:
        """An event of vehicle `row`, signed with its own key in keyed mode."""
        vid = int(self.ids[row])
        if not quiet:
            log.info("vehicle %d: %s", vid, text)
        try:
            self.mesh.event(vid, text, kind=kind, severity=severity, auth=self.auths[row])
        except Exception as exc:  # noqa: BLE001 - an event that cannot be sent must not stop flying
            log.warning("could not publish event: %s", exc)

    def _publish_event(self, event: Event, row: int) -> None:
        try:
            self.mesh.publish_event(event, auth=self.auths[row])
        except Exception as exc:  # noqa: BLE001 - an event that cannot be sent must not stop flying
            log.warning("could not publish an event: %s", exc)

    def _notes(self, notes: list[Note]) -> None:
        for note in notes:
            self._event(note.text, note.kind, note.severity, row=note.index)

    # -- commands (the tick's thread; tests call them directly) --------------------------------
    def command(self, i: int, cmd: Command) -> CommandAck:
        """Vehicle i's answer at once: the mode machine's verdict. The autopilot's part is
        queued."""
        problem = None
        if cmd.kind is CommandKind.TAKEOFF:
            problem = self.stations.takeoff_problem(self.clock_s(), self.cfg.failsafe.require_gcs)
        obs = self.vehicles.read()
        pos = None if obs is None else np.array(obs.pos_m[i])
        link_ok = obs is not None and bool(obs.link_ok[i])
        with self._lock:
            d = self.core.command(i, cmd, pos, link_ok=link_ok, takeoff_problem=problem)
            for action in d.actions:
                self._queues[i].submit(action)
            notes = self.core.drain_notes()
            mode = self.core.mode_of(i)
        self._notes(notes)
        if d.result is not AckResult.ACCEPTED:
            why = f"refused {cmd.kind.name.lower()}: {d.reason}"
            self._event(why, EventKind.COMMAND, Severity.WARNING, row=i)
        return CommandAck(
            int(self.ids[i]), cmd.nonce, self.mesh.clock_ns(), d.result, d.reason, mode
        )

    def mission(self, i: int, mission: Mission) -> CommandAck:
        """Vehicle i's answer to a mission upload: kept (flown on a start), or refused with the
        first bad item's reason."""
        with self._lock:
            d = self.core.load_mission(i, mission)
            notes = self.core.drain_notes()
            mode = self.core.mode_of(i)
        self._notes(notes)
        if d.result is not AckResult.ACCEPTED:
            self._event(f"refused mission: {d.reason}", EventKind.COMMAND, Severity.WARNING, row=i)
        return CommandAck(
            int(self.ids[i]), mission.nonce, self.mesh.clock_ns(), d.result, d.reason, mode
        )

    # -- an action queue's thread ----------------------------------------------------------------
    def _on_outcome(self, action: Action, error: str | None) -> None:
        i = action.index
        back_to = None
        if error is not None:
            with self._lock:
                if self.core.action_failed(action, error):
                    back_to = self.core.mode_of(i)
                notes = self.core.drain_notes()
            self._notes(notes)
        if action.nonce is None:
            return
        outcome = outcome_of(action, int(self.ids[i]), error, back_to, self.mesh.clock_ns())
        try:
            self.mesh.publish_outcome(outcome, auth=self.auths[i])
        except Exception as exc:  # noqa: BLE001 - an outcome that cannot be sent must not stop flying
            log.warning("could not publish an action outcome: %s", exc)

    # -- the loop ------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """The commands that came since the last tick, the vehicles' telemetry, the core's
        events and failsafes, batched guidance, then the states that are due."""
        t0 = time.perf_counter()
        if isinstance(self.states, CellSubscription):
            # the states that came since the last tick, checked at once, received by `now_s`
            self._drained = (self.mesh.clock_ns(), now_s)
            self.states.drain(self._drained[0])
            self._drained = None
        for commands in self.commands:
            commands.poll()
        self.vehicles.step(now_s)
        obs = self.vehicles.read()
        if obs is None:
            return
        self._link_events(obs.link_ok)
        if self.on_position is not None:
            self.on_position(obs.pos_m)
        if self.link is not None and now_s - self._last_link_stats_s >= LINK_STATS_PERIOD_S:
            self._last_link_stats_s = now_s
            self._event(self.link.stats_text(), EventKind.LINK_STATS, Severity.DEBUG)
        # without the station-lost failsafe nobody asks (and the core skips its checks)
        gcs_alive = not self.cfg.failsafe.require_gcs or self.stations.alive(now_s)
        self._hear_traffic(now_s)
        out: GuidanceStep | None = None
        heading_in_rad = 0.0
        with self._lock:
            core = self.core
            # the others, for a returning vehicle's landing order (only then: a snapshot a tick)
            landing = (
                self.table.snapshot(now_s)
                if self.cfg.failsafe.returning.land_radius_m > 0
                and bool((core.mode == int(Mode.RETURNING)).any())
                else None
            )
            actions = core.observe(now_s, obs, gcs_alive, landing)
            busy, idle = self._submit(actions, obs)
            self._resting = bool(idle.all())
            self._calm = False
            due = self.pacer.due(
                now_s, idle, obs.pos_m, obs.vel_m_s, core.heading_rad, core.mode, obs.armed
            )
            rows = core.guided_rows(obs.armed, obs.link_ok)
            ext = self._neighbours(now_s, obs, rows.size > 0 or bool(due.any()))
            self.filtered[:] = False
            self.slowed[:] = False
            if rows.size:
                # Traced flights decide only on published ticks (replayable), unless nothing is held.
                decide = None
                if self.cfg.trace_guidance and not due[rows].any():
                    decide = np.zeros(len(rows), bool)
                views = neighbour_views(
                    core,
                    obs,
                    self.vehicles.pos_sigma_m,
                    self.ids,
                    ext,
                    rows,
                    self.cfg.guidance.max_neighbours,
                )
                heading_in_rad = float(core.heading_rad[0])  # what a trace says the policy saw
                out = core.guide(now_s, rows, obs.pos_m[rows], obs.vel_m_s[rows], views, decide)
                self.filtered[rows] = out.filtered
                self.slowed[rows] = out.slowed_for_stale
            if out is not None and self._calm_every > 1 and not self.cfg.trace_guidance:
                corrected = self.filtered | self.slowed
                if (
                    self._hold_every > self._calm_every
                    and holding_at_rest(core, obs)
                    and calm(core, obs, busy, corrected, ext, self._hold_horizon_s)
                ):
                    self._calm, self._calm_periods = True, self._hold_every
                else:
                    self._calm = calm(core, obs, busy, corrected, ext, self._calm_horizon_s)
                    self._calm_periods = self._calm_every
            notes = core.drain_notes()
            rows_due = (ROW0 if due.item(0) else NO_ROWS) if self._one else np.flatnonzero(due)
            states = self._states(rows_due, obs, ext)  # stamped now: only their puts from here on
        if out is not None:
            vel = out.vel_ned_m_s
            if self.tracking.cfg.enabled:
                vel = vel.copy()
                vel[:, :2] = self.tracking.correct(rows, now_s, vel[:, :2], obs.vel_m_s[rows, :2])
            self.vehicles.set_velocities(rows, vel, out.heading_rad)
        elif not self.velocity_mode:
            self._forward_traffic(now_s, obs, ext)
        tags = self.cfg.link_tags
        for s, row in zip(states, rows_due.tolist(), strict=True):
            auth = self.auths[row]
            receivers = (
                link_receivers(ext, obs.pos_m[row], tags) if auth is not None and tags else []
            )
            try:
                self.mesh.publish_state(s, auth=auth, receivers=receivers)
            except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop flying
                log.warning("state publish failed: %s", exc)
        if out is not None and self.cfg.trace_guidance and rows_due.size:
            self._trace(heading_in_rad, out, ext)
        if self.scope is not None:  # outside the lock: Zenoh's threads take it to deliver states
            self._hear(obs.pos_m, idle)
        self._notes(notes)
        reports = self.stations.clock_reports(now_s, self.cfg.ids)  # one per vehicle, in order
        for row, (report, stamp_ns) in enumerate(reports):
            self._publish_event(report.to_event(stamp_ns), row)
        self.stats.ticks += 1
        self.stats.tick_ms.append((time.perf_counter() - t0) * 1e3)

    def _neighbours(self, now_s: float, obs: Observed, needed: bool) -> NeighbourSnapshot:
        """The other vehicles and the traffic, dead-reckoned to now, when guidance, a state or
        an onboard autopilot needs them; else nothing (and the unheard are forgotten)."""
        if not (needed or not self.velocity_mode):
            self.table.expire(now_s)
            return _NOBODY
        # One vehicle hears only the others in its vertical band (agent/neighbours.py); several
        # hear all of them, and each row's nearest are chosen (agent/shell_views.py).
        own = obs.pos_m[0] if len(self.ids) == 1 else None
        return merge_traffic(self.traffic, self.table.snapshot(now_s, own), now_s, own)

    def _submit(self, actions: list[Action], obs: Observed) -> tuple[np.ndarray, np.ndarray]:
        """Hand `actions` to their vehicles' queues; returns (busy, idle), (N,) each: an action
        waits or runs, the vehicle is idle (comms/state_rate.py `idle_rows`). One vehicle (an
        agent's every tick) on Python bools, `_submit_rows` the reference (tests/test_shell.py)."""
        if not self._one:
            return self._submit_rows(actions, obs)
        busy = bool(actions) or (self._threaded and self._queues[0].busy)
        for action in actions:
            self._queues[0].submit(action)
        idle = idle_one(self.core.mode.item(0), obs.armed.item(0), obs.in_air.item(0), busy)
        return FLAG[busy], FLAG[idle]

    def _submit_rows(self, actions: list[Action], obs: Observed) -> tuple[np.ndarray, np.ndarray]:
        busy = np.array([q.busy for q in self._queues], bool) if self._threaded else self._idle_q
        if actions:
            busy = busy.copy()
        for action in actions:
            self._queues[action.index].submit(action)
            busy[action.index] = True
        return busy, idle_rows(self.core.mode, obs.armed, obs.in_air, busy)

    def _link_events(self, link_ok: np.ndarray) -> None:
        """Say when an autopilot link is lost or restored."""
        if self._one and link_ok.item(0) == self._link_ok.item(0):
            return  # an agent's every tick: nothing changed
        changed = np.flatnonzero(link_ok != self._link_ok)
        if not changed.size:
            return
        self._link_ok = np.array(link_ok, bool)
        for i in changed.tolist():
            ok = bool(link_ok[i])
            self._event(
                "autopilot link " + ("restored" if ok else "LOST"),
                EventKind.FAILSAFE,
                Severity.INFO if ok else Severity.CRITICAL,
                row=i,
            )

    def _hear(self, pos_ned_m: np.ndarray, idle: np.ndarray) -> None:
        """Subscribe to the cells within reach, or to none while every vehicle is idle: guidance
        does not run on the ground, and the tick that ends idleness (a command, arming)
        subscribes again before the vehicle climbs (docs/scaling.md, "Idle vehicles")."""
        assert self.scope is not None and self.states is not None
        if idle.all():
            want: frozenset = frozenset()
        else:
            self.scope.update(pos_ned_m)
            want = self.scope.cells
        if want != self._cells:
            self.states.set_cells(want)
            self._cells = want

    def _states(
        self, rows: np.ndarray, obs: Observed, ext: NeighbourSnapshot
    ) -> list[VehicleState]:
        """The states of `rows` (those due: comms/state_rate.py), each with its next seq."""
        if not rows.size:
            return []
        band_m = self.cfg.neighbours.vertical_band_m
        bits: np.ndarray | int
        if rows.size == 1:  # one row (an agent's every tick): its seq and bits in Python ints
            r = rows.item(0)
            self.seq[r] = (self.seq.item(r) + 1) & 0xFFFFFFFF
            # stale_rows is the slowed rows themselves while no neighbour is stale
            stale = (
                stale_rows(self.slowed, obs.pos_m, ext, band_m).item(r)
                if ext.stale_ids
                else self.slowed.item(r)
            )
            bits = (
                int(self.flags)
                | (int(StateFlag.FILTER_ACTIVE) if self.filtered.item(r) else 0)
                | (int(StateFlag.NEIGHBOURS_STALE) if stale else 0)
            )
        else:
            self.seq[rows] = (self.seq[rows] + 1) & 0xFFFFFFFF
            stale = stale_rows(self.slowed, obs.pos_m, ext, band_m)
            bits = (
                int(self.flags)
                | np.where(self.filtered, int(StateFlag.FILTER_ACTIVE), 0)
                | np.where(stale, int(StateFlag.NEIGHBOURS_STALE), 0)
            )
        sigma = self.vehicles.pos_sigma_m
        return vehicle_states(
            self.core, obs, sigma, self.ids, self.seq, rows, bits, self.mesh.clock_ns()
        )

    def _trace(self, heading_in_rad: float, out: GuidanceStep, ext: NeighbourSnapshot) -> None:
        """What the one vehicle's policy saw and commanded (`covey replay --policy`)."""
        trace = GuidanceTrace.build(
            int(self.ids[0]),
            int(self.seq[0]),
            self.mesh.clock_ns(),
            heading_in_rad,
            out.vel_ned_m_s[0],
            ext.ids,
            ext.seqs,
            ext.age_s,
            decided=bool(out.decided[0]),
        )
        try:
            self.mesh.publish_trace(trace)
        except Exception as exc:  # noqa: BLE001 - a trace that cannot be sent must not stop flying
            log.warning("could not publish a guidance trace: %s", exc)

    # -- traffic -------------------------------------------------------------------------------
    def _hear_traffic(self, now_s: float) -> None:
        """The autopilots' receivers' traffic into the table, and onto the mesh for the others
        (as the hearing vehicle's signed reports) at `traffic_report_hz`."""
        rows = self.vehicles.capable(Capability.TRAFFIC_RECEIVER)
        if not rows:
            return
        for i in rows:
            for track in self.vehicles.backends[i].traffic_tracks(now_s):
                if self.traffic.put(track):
                    self._heard[track.track_id] = (i, track)
        if now_s - self._last_traffic_report_s < 1.0 / self.cfg.traffic_report_hz:
            return
        self._last_traffic_report_s = now_s
        stamp_ns = self.mesh.clock_ns()
        # only what our own receivers heard since the last report, never others' reports again
        heard, self._heard = list(self._heard.values()), {}
        for i, track in heard:
            age_ns = int(max(0.0, now_s - track.stamp_s) * 1e9)
            report = track.report(Role.VEHICLE, int(self.ids[i]), stamp_ns - age_ns)
            try:
                publish_report(self.mesh, report)  # signed with the mesh's key: row 0's
            except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop the tick
                log.warning("traffic report not published: %s", exc)

    def _forward_traffic(self, now_s: float, obs: Observed, ext: NeighbourSnapshot) -> None:
        """Onboard mode: the autopilot flies around its neighbours itself; tell it where they
        are (at most 10 Hz)."""
        rows = [i for i in self.vehicles.capable(Capability.TRAFFIC_INPUT) if obs.link_ok[i]]
        if not rows or now_s - self._last_traffic_s < 0.1:
            return
        self._last_traffic_s = now_s
        traffic = autopilot_traffic(ext, self.traffic, now_s)
        for i in rows:
            try:
                self.vehicles.backends[i].send_traffic(traffic)
            except BackendError as exc:
                log.warning("traffic forward failed: %s", exc)

    def run(self, stop: threading.Event) -> None:
        """Tick at `tick_hz` until `stop` is set (overruns are counted in `stats`)."""

        def overrun() -> None:
            self.stats.overruns += 1

        def ring_on_stop() -> None:  # the loop waits on the doorbell alone
            stop.wait()
            self._wake.set()

        threading.Thread(target=ring_on_stop, name="tick-stop", daemon=True).start()
        run_ticks(
            self.tick,
            self.cfg.tick_hz,
            self.clock_s,
            stop,
            overrun,
            idle_hz=self.cfg.resting_tick_hz,
            idle=lambda: self._resting,
            wake=self._wake,
            calm_every=self._calm_every,
            calm=lambda: self._calm,
            calm_periods=lambda: self._calm_periods,
        )
