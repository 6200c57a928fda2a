"""`covey fleet-sim`: hundreds of simulated vehicles in one process, for scale tests.

    covey fleet-sim --vehicles 500 --connect tcp/127.0.0.1:7447 --rate-hz 10

Each vehicle is still its own citizen of the mesh: it publishes its own state on its own key,
answers its own commands on its own queryable, holds its own liveliness token and publishes its
own events. It runs the same flight core as `covey agent` (agent/flight_core.py: modes, checks,
vehicle events, failsafes, decide-and-hold guidance with the safety filter), with N rows instead
of one, around the simulator's N-row point masses (agent/backends/sim.py). What is shared is
the work: one batched policy call (nearest `max_neighbours`) and one batched filter per tick.

Vehicles of other processes (real agents, other fleet-sims) are neighbours too when
`see_others` is on. Not modelled here (the single agent has them): per-vehicle radio links.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from agent.actions import ActionQueue, outcome_of, perform, run_ticks
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
from agent.neighbours import NeighbourConfig
from comms.cli_options import stop_after
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.schema import Command, CommandAck, Mode, StateFlag, VehicleState
from comms.scope import Scope, ScopeConfig
from comms.session import MeshConfig
from comms.state_rate import IDLE_STATE_HZ, StatePacer, check_rates, idle_rows
from policy.runtime import GuidancePolicy

log = logging.getLogger("covey.fleet_sim")


@dataclass(frozen=True)
class FleetSimConfig:
    """One process simulating many vehicles."""

    vehicles: int = 500
    """How many vehicles this process simulates."""
    first_id: int = 1
    """Vehicle ids are first_id .. first_id + vehicles - 1."""
    mesh: MeshConfig = MeshConfig()
    """How the process joins the mesh (one Zenoh session for all its vehicles)."""
    rate_hz: float = 10.0
    """Physics, guidance and state-publishing rate."""
    idle_state_hz: float = IDLE_STATE_HZ
    """State rate of an idle vehicle (landed, disarmed: comms/state_rate.py, as the agent's)."""
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
        from comms.keys import check_vehicle_id

        if not 1 <= self.vehicles <= 10_000:
            raise ValueError(f"vehicles must be within 1..10000, got {self.vehicles}")
        check_vehicle_id(self.first_id)
        check_vehicle_id(self.first_id + self.vehicles - 1)
        if not (math.isfinite(self.rate_hz) and 0 < self.rate_hz <= 100):
            raise ValueError(f"rate_hz must be within (0, 100], got {self.rate_hz}")
        check_rates(self.rate_hz, self.idle_state_hz)
        if not (math.isfinite(self.spacing_m) and self.spacing_m > 0):
            raise ValueError(f"spacing_m must be positive, got {self.spacing_m}")
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
    mesh session."""

    def __init__(
        self,
        cfg: FleetSimConfig,
        mesh: Mesh,
        *,
        policy: GuidancePolicy | None = None,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        n = cfg.vehicles
        self.cfg, self.mesh, self.clock_s = cfg, mesh, clock_s
        self.ids = np.arange(cfg.first_id, cfg.first_id + n)
        g = replace(cfg.guidance, max_neighbours=cfg.max_neighbours)
        self.policy = policy or g.load_policy()
        now = clock_s()
        self.sim = SimFleet(cfg.sim, start_grid(n, cfg.spacing_m, cfg.start_ne_m), now_s=now)
        core_cfg = CoreConfig(origin=cfg.origin, guidance=g, failsafe=cfg.failsafe)
        self.core = FlightCore(core_cfg, n, now_s=now, guidance=BatchGuidance(g, n, self.policy))
        # Each vehicle's actions run on its row of the simulator, at once (its calls take microseconds).
        self.backends = [SimBackend(fleet=self.sim, index=i) for i in range(n)]
        self.actions = ActionQueue(
            lambda a: perform(a, self.backends[a.index]), self._on_outcome, threaded=False
        )
        self.filtered = np.zeros(n, bool)
        self.seq = np.zeros(n, np.int64)
        """Each vehicle's last published seq (one per state it published: idle is not loss)."""
        self.pacer = StatePacer(cfg.rate_hz, cfg.idle_state_hz, cfg.rate_hz, n)
        self.stats = TickStats()
        self._lock = threading.RLock()
        self._others: dict[int, tuple[VehicleState, float]] = {}
        self.presence = mesh.presence() if cfg.failsafe.require_gcs else None
        self.scope: Scope | None = None
        self.states = None
        if cfg.see_others and cfg.scope.enabled:
            self.scope = Scope(g.scope(cfg.scope), n)
            cells = self.scope.update(self.sim.pos_m)
            # Our own vehicles are in our cells too: Zenoh keeps this session's states local.
            self.states = mesh.subscribe_cells(self._on_state, cells or (), remote_only=True)
        elif cfg.see_others:
            self.states = mesh.subscribe_states(self._on_state)
        for i, vid in enumerate(self.ids.tolist()):
            mesh.serve_commands(vid, lambda c, i=i: self.handle_command(i, c))
        for vid in self.ids.tolist():  # answer commands before announcing presence
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
        if self.cfg.first_id <= state.vehicle_id < self.cfg.first_id + self.cfg.vehicles:
            return
        with self._lock:
            self._others[state.vehicle_id] = (state, self.clock_s())

    def handle_command(self, i: int, cmd: Command) -> CommandAck:
        with self._lock:
            tel = self.sim.telemetry(i)
            d = self.core.command(i, cmd, np.array(tel.pos_ned_m), tel.link_ok)
            for action in d.actions:
                self.actions.submit(action)
            notes = self.core.drain_notes()
            mode = self.core.mode_of(i)
        self._publish_notes(notes)
        return CommandAck(
            int(self.ids[i]), cmd.nonce, self.mesh.clock_ns(), d.result, d.reason, mode
        )

    # -- the simulated autopilots --------------------------------------------------------------
    def _on_outcome(self, action: Action, error: str | None) -> None:
        if error is not None:
            self.core.action_failed(action, error)
        if action.nonce is None:
            return
        outcome = outcome_of(action, int(self.ids[action.index]), error)
        self._send(self.mesh.publish_event, outcome.to_event(self.mesh.clock_ns()))

    def _publish_notes(self, notes: list[Note]) -> None:
        for n in notes:
            vid = int(self.ids[n.index])
            self._send(self.mesh.event, vid, n.text, kind=n.kind, severity=n.severity)

    @staticmethod
    def _send(publish: Callable[..., None], *args, **kw) -> None:
        try:
            publish(*args, **kw)
        except Exception as exc:  # noqa: BLE001 - an event that cannot be sent must not stop the fleet
            log.warning("could not publish event: %s", exc)

    # -- the loop ------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """Physics, the core's events and failsafes, batched guidance, then every state."""
        t0 = time.perf_counter()
        with self._lock:
            sim, core = self.sim, self.core
            sim.step(now_s)
            link_ok = ~sim.closed
            obs = Observed(
                sim.pos_m, sim.vel_m_s, sim.armed, sim.pos_m[:, 2] < -0.05, sim.battery_pct, link_ok
            )
            gcs_alive = self.presence is None or bool(self.presence.ground_stations)
            for action in core.observe(now_s, obs, gcs_alive):
                self.actions.submit(action)
            rows = core.guided_rows(sim.armed, link_ok)
            self.filtered[:] = False
            if rows.size:
                views = self._views(now_s, rows)
                out = core.guide(now_s, rows, sim.pos_m[rows], sim.vel_m_s[rows], views)
                sim.set_velocities(rows, out.vel_ned_m_s, out.heading_rad)
                self.filtered[rows] = out.filtered
            notes = core.drain_notes()
            idle = idle_rows(core.mode, sim.armed, obs.in_air)
            states = self._states(np.flatnonzero(self.pacer.due(now_s, idle)))
            cells = self.scope.update(sim.pos_m) if self.scope is not None else None
        if cells is not None:  # outside the lock: Zenoh's threads take it to deliver states
            self.states.set_cells(cells)
        self._publish_notes(notes)
        for s in states:
            try:
                self.mesh.publish_state(s)
            except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop the fleet
                log.warning("state publish failed: %s", exc)
        self.stats.ticks += 1
        self.stats.tick_ms.append((time.perf_counter() - t0) * 1e3)

    def _views(self, now_s: float, rows: np.ndarray) -> NeighbourViews:
        """What each guided row sees: the nearest airborne vehicles, ours and other processes'
        (dead-reckoned from their last state; stale past NeighbourConfig.stale_s)."""
        sim, stale_s = self.sim, NeighbourConfig().stale_s
        for vid in [v for v, (_, t) in self._others.items() if now_s - t > self.cfg.drop_s]:
            del self._others[vid]
        ext = [
            (s, now_s - t)
            for s, t in self._others.values()
            if s.armed or s.mode not in (Mode.LANDED, Mode.KILLED)
        ]
        ext_pos = np.array([np.add(s.pos_ned_m, np.multiply(s.vel_ned_m_s, a)) for s, a in ext])
        ext_vel = np.array([s.vel_ned_m_s for s, _ in ext]).reshape(-1, 3)
        airborne = np.isin(self.core.mode, AIRBORNE_MODES) & sim.armed
        return NeighbourViews.nearest(
            sim.pos_m[rows],
            rows,
            np.concatenate([sim.pos_m, ext_pos.reshape(-1, 3)]),
            np.concatenate([sim.vel_m_s, ext_vel]),
            np.concatenate([self.core.heading_rad, [s.heading_rad for s, _ in ext]]),
            np.concatenate([airborne, np.ones(len(ext), bool)]),
            np.concatenate(
                [np.zeros(self.cfg.vehicles, bool), np.array([a > stale_s for _, a in ext], bool)]
            ),
            self.cfg.max_neighbours,
        )

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
        flags = [
            StateFlag.OPEN_MODE
            | core.failsafes[r].flags
            | (StateFlag.HAS_GOAL if h else StateFlag.NONE)
            | (StateFlag.FILTER_ACTIVE if f else StateFlag.NONE)
            for r, h, f in zip(
                rows.tolist(), has.tolist(), self.filtered[rows].tolist(), strict=True
            )
        ]
        modes = [Mode(m) for m in core.mode[rows].tolist()]
        ids, seqs = self.ids[rows].tolist(), self.seq[rows].tolist()
        armed, battery = sim.armed[rows].tolist(), sim.battery_pct[rows].tolist()
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
) -> dict:
    """Run the fleet until `stop` (or `duration_s`); returns the tick statistics."""
    stop = stop or threading.Event()
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh)
        if ready is not None:
            ready(fleet)
        with stop_after(duration_s, stop):
            fleet.run(stop)
        return fleet.stats.summary()


def parser() -> argparse.ArgumentParser:
    from comms.cli_options import add_mesh_args, floats, refuse, renamed

    p = argparse.ArgumentParser(
        prog="covey fleet-sim",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--vehicles", type=int, default=500, help="vehicles in this process (default 500)"
    )
    p.add_argument("--first-id", type=int, default=1, help="id of the first vehicle (default 1)")
    p.add_argument("--rate-hz", type=float, default=10.0, help="tick and state rate (default 10)")
    p.add_argument("--spacing-m", type=float, default=8.0, help="start grid spacing (default 8)")
    p.add_argument(
        "--start-ne-m",
        type=lambda s: floats(s, 2, "--start-ne-m"),
        default=(0.0, 0.0),
        metavar="N,E",
        help="grid corner north,east in metres",
    )
    renamed(p, {"--start": "--start-ne-m"})
    p.add_argument(
        "--max-neighbours",
        type=int,
        default=10,
        help="nearest neighbours per policy call (default 10)",
    )
    p.add_argument("--separation-m", type=float, default=3.0)
    p.add_argument("--cruise-speed-m-s", type=float, default=1.0)
    p.add_argument("--no-safety-filter", action="store_true", help="fly the pure learned policy")
    p.add_argument(
        "--no-see-others", action="store_true", help="ignore vehicles of other processes"
    )
    p.add_argument("--geofence-radius-m", type=float, default=2000.0, help="0 = no fence")
    p.add_argument("--duration-s", type=float, default=None, help="exit after this long")
    p.add_argument("-v", "--verbose", action="store_true")
    add_mesh_args(p, key_file=False)
    refuse(p, "--key-file", NO_KEY_REASON, show=True)
    return p


NO_KEY_REASON = (
    "fleet-sim signs nothing (a key signs for one vehicle, this process flies hundreds): "
    "it joins open-mode fleets only"
)


def cli(argv: list[str]) -> int:
    from comms.cli_options import key_env_note, mesh_config, stop_on_signals

    p = parser()
    args = p.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    key_env_note(p, NO_KEY_REASON)
    try:
        cfg = FleetSimConfig(
            vehicles=args.vehicles,
            first_id=args.first_id,
            mesh=mesh_config(args, p),
            rate_hz=args.rate_hz,
            spacing_m=args.spacing_m,
            start_ne_m=args.start_ne_m,
            max_neighbours=args.max_neighbours,
            see_others=not args.no_see_others,
            guidance=GuidanceConfig(
                separation_m=args.separation_m,
                cruise_speed_m_s=args.cruise_speed_m_s,
                safety_filter=not args.no_safety_filter,
            ),
            failsafe=FailsafeConfig(require_gcs=False, geofence_radius_m=args.geofence_radius_m),
        )
    except ValueError as exc:
        p.error(str(exc))

    def ready(fleet: Fleet) -> None:
        print(
            f"READY {cfg.vehicles} vehicles {cfg.first_id}..{cfg.first_id + cfg.vehicles - 1}",
            flush=True,
        )

    with stop_on_signals() as stop, contextlib.suppress(KeyboardInterrupt):
        stats = main(cfg, stop=stop, duration_s=args.duration_s, ready=ready)
        print("STATS " + json.dumps(stats), flush=True)
    return 0
