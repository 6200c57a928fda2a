"""The agent: one process per vehicle. Mesh in, guidance, vehicle backend out.

Every tick (10 Hz by default) it reads its vehicle, builds the neighbour table's snapshot,
advances the mode machine on vehicle events and failsafes, flies the current mode (policy
guidance in goto and return, hold-with-avoidance in hold) and publishes its state. Commands
arrive on Zenoh's thread and are answered at once with an ack that carries the reason for any
refusal.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from agent.backends.base import BackendError, Capability, Traffic, VehicleBackend
from agent.failsafe import FailsafeConfig, Failsafes
from agent.guidance import Guidance, GuidanceConfig, heading_towards
from agent.modes import AIRBORNE, COMMAND_TRIGGERS, Trigger, step
from agent.neighbours import NeighbourConfig, NeighbourTable
from comms.gate import GateConfig, Summaries
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.schema import (
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    EventKind,
    GuidanceTrace,
    Mode,
    Severity,
    StateFlag,
    VehicleState,
)
from comms.session import MeshConfig

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
    takeoff_alt_m: float = 10.0
    """Default take-off altitude when a takeoff command gives none."""
    origin: GeoOrigin = GeoOrigin()
    guidance: GuidanceConfig = GuidanceConfig()
    neighbours: NeighbourConfig = NeighbourConfig()
    failsafe: FailsafeConfig = FailsafeConfig()
    link: str = "perfect"
    """Radio link emulated between this agent and the others (comms.link spec)."""
    open_mode: bool = True
    """Commands are not authenticated (simulator demo only)."""
    trace_guidance: bool = False
    """Publish a guidance trace Event after each state (what the policy saw and commanded), so
    that `covey replay --policy` can replay this flight closed-loop exactly."""

    def __post_init__(self) -> None:
        from comms.keys import check_vehicle_id

        check_vehicle_id(self.vehicle_id)
        for name in ("tick_hz", "state_hz"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 < value <= 100):
                raise ValueError(f"{name} must be within (0, 100], got {value}")


@dataclass
class _Flight:
    mode: Mode = Mode.LANDED
    goal_m: np.ndarray | None = None
    hold_m: np.ndarray | None = None
    home_m: np.ndarray | None = None
    takeoff_alt_m: float = 10.0
    heading_rad: float = 0.0
    resume_goal_m: np.ndarray | None = None
    flags: StateFlag = StateFlag.NONE
    seq: int = 0
    extra: dict = field(default_factory=dict)


class Agent:
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
        self.guidance = (guidance or Guidance(cfg.guidance)) if self.velocity_mode else guidance
        self.table = NeighbourTable(self.vid, cfg.neighbours)
        now = clock_s()
        self.failsafes = Failsafes(cfg.failsafe, now)
        self.flight = _Flight(takeoff_alt_m=cfg.takeoff_alt_m)
        self._lock = threading.RLock()
        self._last_state_s = -math.inf
        self._last_traffic_s = -math.inf
        self._link_was_ok = True
        self.link = link
        self.on_position: Callable[[tuple[float, float, float]], None] | None = None
        self._last_link_stats_s = clock_s()
        self.presence = mesh.presence()
        # Refused commands: one SECURITY event per cause a second (a flood must not become one).
        self._refusals = Summaries(
            lambda line: self._event(line, EventKind.SECURITY, Severity.WARNING)
        )
        if getattr(mesh, "auth", None) is not None:
            mesh.auth.on_reject = self._on_auth_refusal  # refused before handle_command runs
            # Refused neighbour states (forged, replayed...): one SECURITY event per cause a second.
            mesh.on_security = lambda line: self._event(
                line, EventKind.SECURITY, Severity.WARNING, quiet=True
            )
        mesh.subscribe_states(
            lambda s, _t: self.table.update(s, self.clock_s()),
            link=link,
            ignore_id=self.vid,
            gate=GateConfig(min_interval_s=cfg.neighbours.verify_min_interval_s),
        )
        # Answer commands before announcing presence: whoever sees us alive can command us.
        mesh.serve_commands(self.vid, self.handle_command)
        mesh.declare_vehicle(self.vid)
        if cfg.open_mode:
            self.flight.flags |= StateFlag.OPEN_MODE

    # -- events ------------------------------------------------------------------------------
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

    def _on_auth_refusal(self, cmd: Command, _vehicle_id: int, reason: str) -> None:
        cause = reason.split(":", 1)[0]
        self._refusals.note(
            cause,
            self.mesh.clock_ns(),
            lambda n: (
                f"refused {cmd.kind.name.lower()} from station {cmd.source_id}: {reason}"
                if n == 1
                else f"refused {n} commands ({cause}); latest {cmd.kind.name.lower()} from station {cmd.source_id}"
            ),
        )

    # -- commands (Zenoh thread) ---------------------------------------------------------------
    def handle_command(self, cmd: Command) -> CommandAck:
        with self._lock:
            result, reason = self._apply_command(cmd)
            mode = self.flight.mode
        if result is not AckResult.ACCEPTED:
            self._event(
                f"refused {cmd.kind.name.lower()}: {reason}", EventKind.COMMAND, Severity.WARNING
            )
        return CommandAck(self.vid, cmd.nonce, self.mesh.clock_ns(), result, reason, mode)

    def _target_of(self, cmd: Command, pos_m: np.ndarray) -> np.ndarray:
        if cmd.kind is CommandKind.GOTO_GLOBAL:
            return np.array(self.cfg.origin.to_local(*cmd.params))
        return np.array(cmd.params, dtype=float)

    def _apply_command(self, cmd: Command) -> tuple[AckResult, str]:
        tel = self.backend.telemetry()
        if tel is None:
            return AckResult.REJECTED, "no telemetry from the vehicle yet"
        if not tel.link_ok and cmd.kind is not CommandKind.KILL:
            return AckResult.REJECTED, "autopilot link lost"
        pos_m = np.array(tel.pos_ned_m)
        trigger = COMMAND_TRIGGERS[cmd.kind]
        target = None
        if trigger is Trigger.GOTO:
            target = self._target_of(cmd, pos_m)
            problem = self.cfg.failsafe.check_target(target)
            if problem:
                return AckResult.REJECTED, problem
        if cmd.kind is CommandKind.TAKEOFF and cmd.params[0] > self.cfg.failsafe.max_alt_m:
            return (
                AckResult.REJECTED,
                f"takeoff altitude {cmd.params[0]:g} m is above the {self.cfg.failsafe.max_alt_m:g} m limit",
            )
        res = step(self.flight.mode, trigger)
        if not res.accepted:
            return AckResult.REJECTED, res.reason
        try:
            self._enter(res.mode, trigger, pos_m, target, cmd)
        except BackendError as exc:
            return AckResult.FAILED, f"vehicle refused: {exc}"
        return AckResult.ACCEPTED, ""

    def _enter(
        self,
        mode: Mode,
        trigger: Trigger,
        pos_m: np.ndarray,
        target: np.ndarray | None,
        cmd: Command | None = None,
    ) -> None:
        """Make the vehicle do what `mode` means, then record the mode. Raises BackendError."""
        fl, be = self.flight, self.backend
        previous = fl.mode
        if mode is Mode.KILLED:
            be.kill()
        elif mode is Mode.TAKING_OFF:
            alt_m = (
                cmd.params[0]
                if cmd is not None and cmd.kind is CommandKind.TAKEOFF
                else fl.takeoff_alt_m
            )
            if previous is Mode.LANDED:
                fl.home_m = pos_m.copy()
            be.takeoff(alt_m)
            fl.takeoff_alt_m = alt_m
            fl.goal_m = None
        elif mode is Mode.HOLDING:
            fl.hold_m = (
                fl.goal_m if trigger is Trigger.ARRIVED and fl.goal_m is not None else pos_m
            ).copy()
            if trigger is Trigger.REACHED_ALTITUDE:
                fl.hold_m[2] = -fl.takeoff_alt_m
            if trigger is Trigger.FAILSAFE_HOLD and previous is Mode.GOTO:
                fl.resume_goal_m = fl.goal_m
            if not self.velocity_mode:
                be.hold()
        elif mode is Mode.GOTO:
            assert target is not None
            fl.goal_m = target
            fl.resume_goal_m = None
            fl.heading_rad = (
                heading_towards(pos_m, target, fl.heading_rad)
                if previous is not Mode.GOTO
                else fl.heading_rad
            )
            if not self.velocity_mode:
                be.goto_local(tuple(target))
        elif mode is Mode.RETURNING:
            home = fl.home_m if fl.home_m is not None else np.zeros(3)
            fl.goal_m = np.array([home[0], home[1], min(pos_m[2], -self.cfg.failsafe.min_alt_m)])
            fl.heading_rad = heading_towards(pos_m, fl.goal_m, fl.heading_rad)
            if not self.velocity_mode:
                be.goto_local(tuple(fl.goal_m))
        elif mode is Mode.LANDING:
            be.land()
        if mode is not previous:
            self._event(
                f"{previous.name.lower()} -> {mode.name.lower()} ({trigger.value})",
                EventKind.MODE_CHANGE,
            )
        fl.mode = mode
        if mode not in (Mode.GOTO, Mode.RETURNING):
            fl.goal_m = None if mode is not Mode.HOLDING else fl.goal_m
        if mode in (Mode.LANDED, Mode.LANDING, Mode.KILLED, Mode.TAKING_OFF):
            fl.goal_m = None

    def _internal(self, trigger: Trigger, pos_m: np.ndarray, why: str = "") -> None:
        res = step(self.flight.mode, trigger)
        if not res.accepted:
            return
        try:
            self._enter(res.mode, trigger, pos_m, self.flight.goal_m)
        except BackendError as exc:
            self._event(f"{trigger.value} failed: {exc}", EventKind.FAILSAFE, Severity.ERROR)
            return
        if why:
            self._event(why, EventKind.FAILSAFE, Severity.WARNING)

    # -- the loop ------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """One guidance step at time `now_s` (the caller's clock)."""
        with self._lock:
            self._tick(now_s)

    def _tick(self, now_s: float) -> None:
        be, fl = self.backend, self.flight
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
        if math.hypot(vel[0], vel[1]) > 0.2 * self.cfg.guidance.cruise_speed_m_s:
            fl.heading_rad = math.atan2(vel[1], vel[0])
        # Vehicle events.
        if fl.mode is Mode.TAKING_OFF and -pos[2] >= fl.takeoff_alt_m - 0.3:
            self._internal(Trigger.REACHED_ALTITUDE, pos)
        elif (
            fl.mode in (Mode.GOTO, Mode.RETURNING)
            and fl.goal_m is not None
            and self._arrived(pos, fl.goal_m)
        ):
            self._internal(Trigger.ARRIVED, pos)
        elif fl.mode in (Mode.LANDING, Mode.KILLED) and not tel.in_air and not tel.armed:
            self._internal(Trigger.TOUCHED_DOWN, pos)
        elif fl.mode in AIRBORNE - {Mode.TAKING_OFF} and not tel.armed and not tel.in_air:
            fl.mode = Mode.LANDED
            self._event(
                "vehicle is on the ground and disarmed", EventKind.MODE_CHANGE, Severity.WARNING
            )
        # Failsafes.
        gcs_alive = bool(self.presence.ground_stations)
        if gcs_alive and self.failsafes.gcs_failsafe_active:
            self.failsafes.gcs_back(now_s)
            self._event("ground station back", EventKind.FAILSAFE)
            if fl.mode is Mode.HOLDING and fl.resume_goal_m is not None:
                goal, fl.resume_goal_m = fl.resume_goal_m, None
                self._enter(Mode.GOTO, Trigger.GOTO, pos, goal)
        action = self.failsafes.evaluate(now_s, fl.mode, gcs_alive, tel.battery_pct, pos)
        if action is not None:
            self._internal(action.trigger, pos, action.reason)
        nbrs = self.table.snapshot(now_s, pos)
        flags = fl.flags | self.failsafes.flags
        if not tel.link_ok:
            flags |= StateFlag.FAILSAFE_LINK_LOST
        # Fly.
        out = None
        heading_in_rad = fl.heading_rad
        # Half a tick of tolerance: with equal tick and state rates, jitter must not skip states.
        publish = now_s - self._last_state_s >= 1.0 / self.cfg.state_hz - 0.5 / self.cfg.tick_hz
        if tel.link_ok and self.velocity_mode and tel.armed:
            if fl.mode in (Mode.GOTO, Mode.RETURNING) and fl.goal_m is not None:
                decide = self.guidance.decision_due(now_s, fl.goal_m)
                if decide and self.cfg.trace_guidance and not publish:
                    decide = not self.guidance.has_decision  # decide on traced ticks: replayable
                out = self.guidance.goto(pos, vel, fl.heading_rad, fl.goal_m, nbrs, now_s, decide)
            elif fl.mode is Mode.HOLDING and fl.hold_m is not None:
                out = self.guidance.hold(pos, vel, fl.heading_rad, fl.hold_m, nbrs)
            if out is not None:
                try:
                    be.set_velocity_ned(out.vel_ned_m_s, out.heading_rad)
                except BackendError as exc:
                    log.warning("setpoint refused: %s", exc)
                fl.heading_rad = out.heading_rad
                fl.extra["cmd_vel_ned_m_s"] = out.vel_ned_m_s
                if out.filtered:
                    flags |= StateFlag.FILTER_ACTIVE
                if out.slowed_for_stale:
                    flags |= StateFlag.NEIGHBOURS_STALE
        elif (
            tel.link_ok
            and Capability.TRAFFIC_INPUT in be.capabilities
            and now_s - self._last_traffic_s >= 0.1
        ):
            self._last_traffic_s = now_s
            traffic = [
                Traffic(vid, tuple(p), tuple(v), float(h), float(a))
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
            self._last_state_s = now_s
            self._publish(tel, pos, vel, flags)
            if self.cfg.trace_guidance and out is not None:
                self._trace(heading_in_rad, out, nbrs)

    def _trace(self, heading_in_rad: float, out, nbrs) -> None:
        trace = GuidanceTrace.build(
            self.vid,
            self.flight.seq,
            self.mesh.clock_ns(),
            heading_in_rad,
            out.vel_ned_m_s,
            nbrs.ids,
            nbrs.seqs,
            nbrs.age_s,
            decided=out.decided,
        )
        try:
            self.mesh.publish_trace(trace)
        except Exception as exc:  # noqa: BLE001 - a trace that cannot be sent must not stop flying
            log.warning("could not publish a guidance trace: %s", exc)

    def _arrived(self, pos: np.ndarray, goal: np.ndarray) -> bool:
        if self.guidance is not None:
            return self.guidance.arrived(pos, goal)
        return bool(np.hypot(*(goal[:2] - pos[:2])) <= 1.0 and abs(goal[2] - pos[2]) <= 0.5)

    def _publish(self, tel, pos: np.ndarray, vel: np.ndarray, flags: StateFlag) -> None:
        fl = self.flight
        goal = (
            fl.goal_m if fl.goal_m is not None else (fl.hold_m if fl.mode is Mode.HOLDING else None)
        )
        if goal is not None:
            flags |= StateFlag.HAS_GOAL
        fl.seq = (fl.seq + 1) & 0xFFFFFFFF
        state = VehicleState(
            vehicle_id=self.vid,
            seq=fl.seq,
            stamp_ns=self.mesh.clock_ns(),
            pos_ned_m=tuple(float(x) for x in pos),
            vel_ned_m_s=tuple(float(x) for x in vel),
            heading_rad=float(math.remainder(fl.heading_rad, 2 * math.pi)),
            mode=fl.mode,
            armed=tel.armed,
            battery_pct=float(min(100.0, max(0.0, tel.battery_pct))),
            flags=flags,
            goal_ned_m=tuple(float(x) for x in goal) if goal is not None else (0.0, 0.0, 0.0),
        )
        try:
            self.mesh.publish_state(state)
        except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop guidance
            log.warning("state publish failed: %s", exc)

    def run(self, stop: threading.Event) -> None:
        """Tick at `tick_hz` until `stop` is set. Overruns skip ticks instead of bunching up."""
        period_s = 1.0 / self.cfg.tick_hz
        next_s = self.clock_s()
        while not stop.is_set():
            try:
                self.tick(self.clock_s())
            except Exception:  # noqa: BLE001 - keep flying; the log has the traceback
                log.exception("guidance tick failed")
            next_s += period_s
            now = self.clock_s()
            if next_s < now:
                next_s = now + period_s
            stop.wait(max(0.0, next_s - now))
