"""The multi-vehicle host: many simulated vehicles in one process (`covey agent --ids 1-100`,
and `covey fleet-sim`, its open-mode alias for scale tests).

Each vehicle is still its own citizen of the mesh: it publishes its own state on its own key,
answers its own commands on its own queryable, holds its own liveliness token and publishes its
own events, and in keyed mode signs its states, events and acks with its own key (one FleetAuth
per vehicle, sharing one roster: trust/auth.py). It runs the same flight core as `covey agent`
(agent/flight_core.py: modes, checks, vehicle events, failsafes, the ground-station failsafe
included, decide-and-hold guidance with the safety filter), with N rows instead of one, around
the simulator's N-row point masses (agent/backends/sim.py). What is shared is the work: one
batched policy call (nearest `max_neighbours`) and one batched filter per tick, one Zenoh session.

Vehicles of other processes (real agents, other hosts) are neighbours too when `see_others` is
on. Not modelled here (the single agent has them): per-vehicle radio links, guidance traces, and
real autopilots (one per `covey agent` process).
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from agent.actions import ActionQueue, outcome_of, perform
from agent.backends.sim import SimBackend, SimConfig, SimFleet
from agent.failsafe import FailsafeConfig
from agent.flight_core import (
    AIRBORNE_MODES,
    Action,
    CoreConfig,
    FlightCore,
    Note,
    Observed,
)
from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews
from agent.neighbours import NeighbourConfig, NeighbourTable
from agent.traffic import merge_traffic
from cli.options import stop_after
from comms.gate import GateConfig, command_refusals
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.plan import FleetPlan
from comms.plan_sync import START_PULL_S, PlanSync, describe
from comms.schema import (
    POSITION_LIMIT_M,
    AckResult,
    Command,
    CommandAck,
    CommandKind,
    EventKind,
    Mission,
    Mode,
    Severity,
    StateFlag,
    VehicleState,
)
from comms.scope import Scope, ScopeConfig
from comms.session import MeshConfig
from comms.state_rate import IDLE_STATE_HZ, StatePacer, SteadyConfig, check_rates, idle_rows
from comms.traffic import TrafficListener, TrafficTable
from kit.ticks import run_ticks
from policy.runtime import GuidancePolicy
from trust.auth import FleetAuth, host_signers
from trust.heartbeat import HeartbeatConfig, StationHeartbeats

log = logging.getLogger("covey.fleet_sim")
_MODES = {m.value: m for m in Mode}


@functools.cache
def _state_flag(bits: int) -> StateFlag:
    return StateFlag(bits)


@dataclass(frozen=True)
class FleetSimConfig:
    """One process simulating many vehicles."""

    vehicles: int = 500
    """How many vehicles this process simulates (set from `ids` when they are given)."""
    first_id: int = 1
    """Vehicle ids are first_id .. first_id + vehicles - 1 (set from `ids` when given)."""
    ids: tuple[int, ...] = ()
    """The vehicle ids, in start-grid order (`covey agent --ids 1-50,60`); empty: the range
    above."""
    mesh: MeshConfig = MeshConfig()
    """How the process joins the mesh (one Zenoh session for all its vehicles)."""
    rate_hz: float = 10.0
    """Physics, guidance and state-publishing rate."""
    idle_state_hz: float = IDLE_STATE_HZ
    """State rate of an idle vehicle (landed, disarmed: comms/state_rate.py, as the agent's)."""
    steady: SteadyConfig | None = None
    """Steady vehicles publish at its lower rate (comms/state_rate.py, as the agent's)."""
    spacing_m: float = 8.0
    """Start positions form a square grid with this spacing."""
    start_ne_m: tuple[float, float] = (0.0, 0.0)
    """North-east corner of the start grid."""
    max_neighbours: int | None = 10
    """Nearest neighbours fed to each vehicle's policy (None: all within its sense range)."""
    see_others: bool = True
    """Subscribe to other processes' vehicle states and avoid them too."""
    scope: ScopeConfig = ScopeConfig()
    """Which of them to hear: the union of the grid cells within reach of this process's
    vehicles, or every state of the fleet with `enabled=False` (comms/scope.py)."""
    guidance: GuidanceConfig = GuidanceConfig()
    """Separation, speed, arrival and vertical tuning (as the agent's)."""
    sim: SimConfig = SimConfig()
    """Point-mass limits (acceleration, climb and descent rates); start fields are ignored."""
    failsafe: FailsafeConfig = FailsafeConfig(require_gcs=False)
    """Target checks (geofence, altitude limits) and failsafes, as the agent's."""
    origin: GeoOrigin = GeoOrigin()
    """Fleet origin for goto-global commands."""
    drop_s: float = 3.0
    """Other processes' vehicles older than this are forgotten."""

    def __post_init__(self) -> None:
        from cli.options import MAX_HOSTED_VEHICLES
        from comms.keys import check_vehicle_id

        if self.ids:
            ids = tuple(self.ids)
            for vid in ids:
                check_vehicle_id(vid)
            if len(set(ids)) != len(ids):
                raise ValueError("ids must not repeat a vehicle id")
            # frozen: the derived fields are set once, here
            object.__setattr__(self, "ids", ids)
            object.__setattr__(self, "vehicles", len(ids))
            object.__setattr__(self, "first_id", min(ids))
        if not 1 <= self.vehicles <= MAX_HOSTED_VEHICLES:
            raise ValueError(
                f"vehicles must be within 1..{MAX_HOSTED_VEHICLES}, got {self.vehicles}"
            )
        if not self.ids:
            check_vehicle_id(self.first_id)
            check_vehicle_id(self.first_id + self.vehicles - 1)
            object.__setattr__(
                self, "ids", tuple(range(self.first_id, self.first_id + self.vehicles))
            )
        if not (math.isfinite(self.rate_hz) and 0 < self.rate_hz <= 100):
            raise ValueError(f"rate_hz must be within (0, 100], got {self.rate_hz}")
        check_rates(self.rate_hz, self.idle_state_hz)
        if not (math.isfinite(self.spacing_m) and self.spacing_m > 0):
            raise ValueError(f"spacing_m must be positive, got {self.spacing_m}")
        far_ne_m = start_grid(self.vehicles, self.spacing_m, self.start_ne_m)[-1, :2]
        if not all(abs(v) <= POSITION_LIMIT_M for v in (*self.start_ne_m, *far_ne_m)):
            raise ValueError(
                f"the start grid from N {self.start_ne_m[0]:g} E {self.start_ne_m[1]:g} m "
                f"(spacing {self.spacing_m:g} m) leaves the ±{POSITION_LIMIT_M:g} m a state "
                "can carry"
            )
        if self.max_neighbours is not None and self.max_neighbours < 0:
            raise ValueError(f"max_neighbours must be >= 0, got {self.max_neighbours}")


@dataclass
class TickStats:
    """Wall time spent per tick (read them after `run`)."""

    ticks: int = 0
    overruns: int = 0
    tick_ms: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        t = np.array(self.tick_ms[-10_000:]) if self.tick_ms else np.zeros(1)
        return {
            "ticks": self.ticks,
            "overruns": self.overruns,
            "tick_ms_p50": float(np.median(t)),
            "tick_ms_p99": float(np.percentile(t, 99)),
        }


def start_grid(n: int, spacing_m: float, corner_ne_m: tuple[float, float]) -> np.ndarray:
    """(n, 3) NED start positions on the ground, a square grid filled row by row."""
    side = math.ceil(math.sqrt(n))
    k = np.arange(n)
    return np.stack(
        [
            corner_ne_m[0] + spacing_m * (k // side),
            corner_ne_m[1] + spacing_m * (k % side),
            np.zeros(n),
        ],
        axis=1,
    )


class Fleet:
    """The vehicles of one process: the flight core with N rows, N simulated point masses, one
    mesh session. `auths`: each vehicle's own FleetAuth (keyed mode, trust.auth
    .load_vehicle_auths; the mesh's must share their roster); None: open mode."""

    def __init__(
        self,
        cfg: FleetSimConfig,
        mesh: Mesh,
        *,
        auths: Mapping[int, FleetAuth] | None = None,
        policy: GuidancePolicy | None = None,
        clock_s: Callable[[], float] = time.monotonic,
        rng: np.random.Generator | None = None,
    ) -> None:
        """`rng` draws the simulated vehicles' gusts and GNSS drift (cfg.sim.vehicle; None:
        fresh entropy)."""
        n = cfg.vehicles
        self.cfg, self.mesh, self.clock_s = cfg, mesh, clock_s
        self.ids = np.array(cfg.ids)
        self._own = frozenset(cfg.ids)
        self.auths = host_signers(cfg.ids, mesh.auth, auths)
        """Row i's FleetAuth, or None in open mode (then the mesh signs nothing either)."""
        g = replace(cfg.guidance, max_neighbours=cfg.max_neighbours)
        self.policy = policy or g.load_policy()
        now = clock_s()
        self.sim = SimFleet(
            cfg.sim, start_grid(n, cfg.spacing_m, cfg.start_ne_m), now_s=now, rng=rng
        )
        core_cfg = CoreConfig(origin=cfg.origin, guidance=g, failsafe=cfg.failsafe)
        self.core = FlightCore(
            core_cfg,
            n,
            now_s=now,
            guidance=BatchGuidance(g, n, self.policy),
            vehicle_ids=cfg.ids,
        )
        # Each vehicle's actions run on its row of the simulator, at once (its calls take microseconds).
        self.backends = [SimBackend(fleet=self.sim, index=i) for i in range(n)]
        self.actions = ActionQueue(
            lambda a: perform(a, self.backends[a.index]), self._on_outcome, threaded=False
        )
        self.flags = StateFlag.NONE if auths is not None else StateFlag.OPEN_MODE
        self.filtered = np.zeros(n, bool)
        self.slowed = np.zeros(n, bool)
        self.seq = np.zeros(n, np.int64)
        """Each vehicle's last published seq (one per state it published: idle is not loss)."""
        self.pacer = StatePacer(cfg.rate_hz, cfg.idle_state_hz, cfg.rate_hz, n, cfg.steady)
        self.stats = TickStats()
        self._lock = threading.RLock()
        self.others = NeighbourTable(None, replace(NeighbourConfig(), drop_s=cfg.drop_s))
        """Other processes' vehicles (ours are kept out by `_on_state`)."""
        self.traffic = TrafficTable()
        """Traffic that does not cooperate, from the mesh (agent/traffic.py)."""
        self.traffic_listener = TrafficListener(mesh, self.traffic, clock_s)
        # As the agent: the station-lost failsafe and the take-off check trust signed station
        # heartbeats (trust/heartbeat.py), which also give the host's clock offset.
        self.stations = StationHeartbeats(
            mesh,
            HeartbeatConfig(),
            clock_s=clock_s,
            on_summary=(lambda line: self._event(0, line, EventKind.SECURITY))
            if auths is not None
            else None,
            tokens=cfg.failsafe.require_gcs,
        )
        if auths is not None:
            for auth in self.auths:  # named in stale-command refusals
                auth.clock_note = self.stations.clock_problem
            # As the agent: refused commands and neighbour states become SECURITY events (one
            # per cause a second), a vehicle's own refusals from that vehicle, signed by it.
            for i, auth in enumerate(self.auths):
                emit = lambda line, i=i: self._event(i, line, EventKind.SECURITY)  # noqa: E731
                auth.on_reject = command_refusals(emit, mesh.clock_ns)
            mesh.on_security = lambda line: self._event(0, line, EventKind.SECURITY)
        # The fleet plan (comms/plan_sync.py): every row's gotos and take-offs are checked against
        # it; it lives as long as the mesh session.
        self.plan = PlanSync(
            mesh.session,
            mesh.fleet,
            mesh.auth,
            on_plan=self._on_plan,
            on_summary=(lambda line: self._event(0, line, EventKind.SECURITY))
            if auths is not None
            else None,
        )
        self.plan.pull_now(START_PULL_S)  # hold the plan before answering any command
        gate = GateConfig(min_interval_s=NeighbourConfig().verify_min_interval_s)
        self.scope: Scope | None = None
        self.states = None
        if cfg.see_others and cfg.scope.enabled:
            self.scope = Scope(g.scope(cfg.scope), n)
            cells = self.scope.update(self.sim.pos_m)
            # Our own vehicles are in our cells too: Zenoh keeps this session's states local.
            self.states = mesh.subscribe_cells(
                self._on_state, cells or (), gate=gate, remote_only=True
            )
        elif cfg.see_others:
            self.states = mesh.subscribe_states(self._on_state, gate=gate)
        # Answered from the tick (`tick`), not from one Zenoh thread per vehicle: a command to
        # all would wake every one of them at once (docs/scaling.md, "Commands to a host").
        self.commands = [
            mesh.serve_commands(
                vid,
                lambda c, i=i: self.handle_command(i, c),
                auth=self.auths[i],
                polled=True,
                on_mission=lambda m, i=i: self.handle_mission(i, m),
            )
            for i, vid in enumerate(cfg.ids)
        ]
        for vid in cfg.ids:  # answer commands before announcing presence
            mesh.declare_vehicle(vid)

    # -- what tests and benches read -----------------------------------------------------------
    @property
    def modes(self) -> list[Mode]:
        return self.core.modes

    @property
    def pos_m(self) -> np.ndarray:
        return self.sim.pos_m

    @property
    def armed(self) -> np.ndarray:
        return self.sim.armed

    @property
    def home_m(self) -> np.ndarray:
        return self.core.home_m

    @property
    def _decided_s(self) -> np.ndarray:
        return self.core.guidance.decided_s

    # -- mesh (Zenoh threads) ------------------------------------------------------------------
    def _on_state(self, state: VehicleState, _recv_ns: int) -> None:
        if state.vehicle_id not in self._own:
            self.others.update(state, self.clock_s())

    def handle_command(self, i: int, cmd: Command) -> CommandAck:
        """Vehicle i's answer at once (the mode machine's verdict), as the agent's."""
        problem = None
        if cmd.kind is CommandKind.TAKEOFF:
            problem = self.stations.takeoff_problem(self.clock_s(), self.cfg.failsafe.require_gcs)
        with self._lock:
            tel = self.sim.telemetry(i)
            d = self.core.command(i, cmd, np.array(tel.pos_ned_m), tel.link_ok, problem)
            for action in d.actions:
                self.actions.submit(action)
            notes = self.core.drain_notes()
            mode = self.core.mode_of(i)
        self._publish_notes(notes)
        if d.result is not AckResult.ACCEPTED:
            why = f"refused {cmd.kind.name.lower()}: {d.reason}"
            self._event(i, why, EventKind.COMMAND, Severity.WARNING)
        return CommandAck(
            int(self.ids[i]), cmd.nonce, self.mesh.clock_ns(), d.result, d.reason, mode
        )

    def handle_mission(self, i: int, mission: Mission) -> CommandAck:
        """Vehicle i's answer to a mission upload: kept (not flown before a start), or refused
        with the first bad item's reason."""
        with self._lock:
            d = self.core.load_mission(i, mission)
            notes = self.core.drain_notes()
            mode = self.core.mode_of(i)
        self._publish_notes(notes)
        if d.result is not AckResult.ACCEPTED:
            self._event(i, f"refused mission: {d.reason}", EventKind.COMMAND, Severity.WARNING)
        return CommandAck(
            int(self.ids[i]), mission.nonce, self.mesh.clock_ns(), d.result, d.reason, mode
        )

    # -- the simulated autopilots --------------------------------------------------------------
    def _on_outcome(self, action: Action, error: str | None) -> None:
        if error is not None:
            self.core.action_failed(action, error)
        if action.nonce is None:
            return
        i = action.index
        outcome = outcome_of(action, int(self.ids[i]), error)
        auth = self.auths[i]
        self._send(self.mesh.publish_event, outcome.to_event(self.mesh.clock_ns()), auth=auth)

    def _on_plan(self, plan: FleetPlan) -> None:
        with self._lock:
            self.core.set_plan(plan)
        log.info("fleet plan v%d: %s", plan.version, describe(plan))

    def _publish_notes(self, notes: list[Note]) -> None:
        for n in notes:
            self._event(n.index, n.text, n.kind, n.severity)

    def _event(
        self, i: int, text: str, kind: EventKind, severity: Severity = Severity.WARNING
    ) -> None:
        """An event of vehicle i (row), signed with its own key in keyed mode."""
        vid = int(self.ids[i])
        self._send(self.mesh.event, vid, text, kind=kind, severity=severity, auth=self.auths[i])

    @staticmethod
    def _send(publish: Callable[..., None], *args, **kw) -> None:
        try:
            publish(*args, **kw)
        except Exception as exc:  # noqa: BLE001 - an event that cannot be sent must not stop the fleet
            log.warning("could not publish event: %s", exc)

    # -- the loop ------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """The commands that came since the last tick, physics, the core's events and
        failsafes, batched guidance, then every state."""
        t0 = time.perf_counter()
        for commands in self.commands:
            commands.poll()
        with self._lock:
            sim, core = self.sim, self.core
            sim.step(now_s)
            link_ok = ~sim.closed
            obs = Observed(
                sim.pos_m, sim.vel_m_s, sim.armed, sim.pos_m[:, 2] < -0.05, sim.battery_pct, link_ok
            )
            gcs_alive = not self.cfg.failsafe.require_gcs or self.stations.alive(now_s)
            # a landing order needs the other processes' vehicles (agent/returning.py)
            ordered = self.cfg.failsafe.returning.land_radius_m > 0
            others = self.others.snapshot(now_s) if ordered else None
            for action in core.observe(now_s, obs, gcs_alive, others):
                self.actions.submit(action)
            rows = core.guided_rows(sim.armed, link_ok)
            self.filtered[:] = False
            self.slowed[:] = False
            if rows.size:
                views = self._views(now_s, rows)
                out = core.guide(now_s, rows, sim.pos_m[rows], sim.vel_m_s[rows], views)
                sim.set_velocities(rows, out.vel_ned_m_s, out.heading_rad)
                self.filtered[rows] = out.filtered
                self.slowed[rows] = out.slowed_for_stale
            else:
                self.others.expire(now_s)  # unheard vehicles go, flying or not
            notes = core.drain_notes()
            idle = idle_rows(core.mode, sim.armed, obs.in_air)
            due = np.flatnonzero(
                self.pacer.due(
                    now_s, idle, sim.pos_m, sim.vel_m_s, core.heading_rad, core.mode, sim.armed
                )
            )
            cells = self.scope.update(sim.pos_m) if self.scope is not None else None
            states = self._states(due)  # stamped now: nothing but their puts from here on
        for s, row in zip(states, due.tolist(), strict=True):
            try:
                self.mesh.publish_state(s, auth=self.auths[row])
            except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop the fleet
                log.warning("state publish failed: %s", exc)
        if cells is not None:  # outside the lock: Zenoh's threads take it to deliver states
            self.states.set_cells(cells)
        self._publish_notes(notes)
        reports = self.stations.clock_reports(now_s, self.cfg.ids)  # one per vehicle, in order
        for row, (report, stamp_ns) in enumerate(reports):
            self._send(self.mesh.publish_event, report.to_event(stamp_ns), auth=self.auths[row])
        self.stats.ticks += 1
        self.stats.tick_ms.append((time.perf_counter() - t0) * 1e3)

    def _views(self, now_s: float, rows: np.ndarray) -> NeighbourViews:
        """What each guided row sees: the nearest airborne vehicles, ours and other processes'
        (dead-reckoned from their last state; stale past NeighbourConfig.stale_s)."""
        sim, ext = self.sim, merge_traffic(self.traffic, self.others.snapshot(now_s), now_s)
        airborne = np.isin(self.core.mode, AIRBORNE_MODES) & sim.armed
        return NeighbourViews.nearest(
            sim.pos_m[rows],
            rows,
            np.concatenate([sim.pos_m, ext.pos_ned_m]),
            np.concatenate([sim.vel_m_s, ext.vel_ned_m_s]),
            np.concatenate([self.core.heading_rad, ext.heading_rad]),
            np.concatenate([airborne, np.ones(len(ext), bool)]),
            np.concatenate(
                [np.zeros(self.cfg.vehicles, bool), ext.age_s > self.others.cfg.stale_s]
            ),
            self.cfg.max_neighbours,
            np.concatenate([self.ids, np.array(ext.ids, np.int64)]),
            self.ids[rows],
            **self._sky(ext, rows),
        )

    def _sky(self, ext, rows: np.ndarray) -> dict:
        """NeighbourViews.nearest's position 1-sigmas and cooperative flags for our vehicles
        (the simulator's drift) and the others (their states', traffic non-cooperative); none
        when every position is exact and everyone cooperates (the views as before)."""
        n = self.cfg.vehicles
        sigma = np.concatenate([np.full(n, self.sim.pos_sigma_m), ext.column("pos_sigma_m", 0.0)])
        coop = np.concatenate([np.ones(n, bool), ext.column("cooperative", True)])
        out: dict = {}
        if sigma.any():
            out["world_pos_sigma_m"] = sigma
            out["rows_pos_sigma_m"] = sigma[rows]
        if not coop.all():
            out["world_cooperative"] = coop
        manned = np.concatenate([np.zeros(n, bool), ext.column("manned", False)])
        if manned.any():
            out["world_manned"] = manned
        return out

    def _states(self, rows: np.ndarray) -> list[VehicleState]:
        """The states of `rows` (those due: comms/state_rate.py), each with its next seq."""
        self.seq[rows] = (self.seq[rows] + 1) & 0xFFFFFFFF
        stamp_ns = self.mesh.clock_ns()
        core, sim = self.core, self.sim
        # whole arrays to Python floats once: per-row numpy access costs more than the rest
        pos, vel = sim.pos_m[rows].tolist(), sim.vel_m_s[rows].tolist()
        targets = core.targets()[rows]
        has = ~np.isnan(targets[:, 0])
        goal = np.where(has[:, None], targets, 0.0).tolist()
        hdg = (np.remainder(core.heading_rad[rows] + math.pi, 2 * math.pi) - math.pi).tolist()
        # flags as ints, one enum per distinct value (enum arithmetic per row cost more than the
        # rest of the state)
        bits = (
            int(self.flags)
            | np.array([int(core.failsafes[r].flags) for r in rows.tolist()], np.int64)
            | np.where(has, int(StateFlag.HAS_GOAL), 0)
            | np.where(self.filtered[rows], int(StateFlag.FILTER_ACTIVE), 0)
            | np.where(self.slowed[rows], int(StateFlag.NEIGHBOURS_STALE), 0)
        )
        flags = [_state_flag(b) for b in bits.tolist()]
        modes = [_MODES[m] for m in core.mode[rows].tolist()]
        ids, seqs = self.ids[rows].tolist(), self.seq[rows].tolist()
        armed, battery = sim.armed[rows].tolist(), sim.battery_pct[rows].tolist()
        sigma = float(sim.pos_sigma_m)
        item, items = (x.tolist() for x in core.mission_progress(rows))
        return [
            VehicleState(
                vehicle_id=ids[i],
                seq=seqs[i],
                stamp_ns=stamp_ns,
                pos_ned_m=tuple(pos[i]),
                vel_ned_m_s=tuple(vel[i]),
                heading_rad=hdg[i],
                mode=modes[i],
                armed=armed[i],
                battery_pct=battery[i],
                flags=flags[i],
                goal_ned_m=tuple(goal[i]),
                mission_item=item[i],
                mission_items=items[i],
                pos_sigma_m=sigma,
            )
            for i in range(len(ids))
        ]

    def run(self, stop: threading.Event) -> None:
        """Tick at `rate_hz` until `stop` is set (overruns are counted in `stats`)."""

        def overrun() -> None:
            self.stats.overruns += 1

        run_ticks(self.tick, self.cfg.rate_hz, self.clock_s, stop, overrun)


def main(
    cfg: FleetSimConfig,
    stop: threading.Event | None = None,
    duration_s: float | None = None,
    ready: Callable[[Fleet], None] | None = None,
    auths: Mapping[int, FleetAuth] | None = None,
) -> dict:
    """Run the host until `stop` (or `duration_s`); returns the tick statistics. `auths`: one
    FleetAuth per vehicle (keyed mode), the first of which keys the mesh."""
    stop = stop or threading.Event()
    # The duration bounds the whole run, waiting for a router included.
    with (
        stop_after(duration_s, stop),
        Mesh(cfg.mesh, auth=auths[cfg.ids[0]] if auths else None, stop=stop) as mesh,
    ):
        fleet = Fleet(cfg, mesh, auths=auths)
        if ready is not None:
            ready(fleet)
        fleet.run(stop)
        return fleet.stats.summary()
