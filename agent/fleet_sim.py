"""`covey fleet-sim`: hundreds of simulated vehicles in one process, for scale tests.

    covey fleet-sim --vehicles 500 --connect tcp/127.0.0.1:7447 --rate-hz 10

Each vehicle is still its own citizen of the mesh: it publishes its own state on its own key,
answers its own commands on its own queryable and holds its own liveliness token, and its
commands go through the agent's mode machine (`agent.modes.step`) with the agent's checks
(geofence, altitude limits). What is shared is the work: the point-mass physics is one set of
arrays, and guidance is one batched policy call (`GuidancePolicy.action_batch`, nearest
`max_neighbours`) plus one batched safety filter for every airborne vehicle at once.

Vehicles of other processes (real agents, other fleet-sims) are neighbours too when
`see_others` is on. Not modelled here (the single agent has them): ground-station-lost and
battery failsafes, per-vehicle radio links, events on the mesh, the vertical traffic band.
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
from dataclasses import dataclass, field

import numpy as np

from agent.backends.sim import GRAVITY_M_S2, SimConfig
from agent.failsafe import FailsafeConfig
from agent.guidance import DECISION_DUE_SHARE, GuidanceConfig
from agent.modes import AIRBORNE, COMMAND_TRIGGERS, Trigger, step
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandAck, CommandKind, Mode, StateFlag, VehicleState
from comms.session import MeshConfig
from policy import features, safety
from policy.runtime import GuidancePolicy

log = logging.getLogger("covey.fleet_sim")
FLYING = (Mode.GOTO, Mode.RETURNING)
_HAS_GOAL = StateFlag.OPEN_MODE | StateFlag.HAS_GOAL


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
    spacing_m: float = 8.0
    """Start positions form a square grid with this spacing."""
    start_ne_m: tuple[float, float] = (0.0, 0.0)
    """North-east corner of the start grid."""
    max_neighbours: int = 10
    """Nearest neighbours fed to each vehicle's policy."""
    see_others: bool = True
    """Subscribe to other processes' vehicle states and avoid them too."""
    guidance: GuidanceConfig = GuidanceConfig()
    """Separation, speed, arrival and vertical tuning (as the agent's)."""
    sim: SimConfig = SimConfig()
    """Point-mass limits (acceleration, climb and descent rates); start fields are ignored."""
    failsafe: FailsafeConfig = FailsafeConfig(require_gcs=False)
    """Only the target checks (geofence, altitude limits) are used."""
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
        if not (math.isfinite(self.spacing_m) and self.spacing_m > 0):
            raise ValueError(f"spacing_m must be positive, got {self.spacing_m}")
        if self.max_neighbours < 0:
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
    """The vehicles of one process: arrays for physics, a mode per vehicle, one mesh session."""

    def __init__(
        self,
        cfg: FleetSimConfig,
        mesh: Mesh,
        *,
        policy: GuidancePolicy | None = None,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        n, g = cfg.vehicles, cfg.guidance
        self.cfg, self.mesh, self.clock_s = cfg, mesh, clock_s
        self.ids = np.arange(cfg.first_id, cfg.first_id + n)
        self.policy = policy or GuidancePolicy.load(
            g.policy_path,
            separation_m=g.separation_m,
            cruise_speed_m_s=g.cruise_speed_m_s,
            safety_filter=False,
            max_neighbours=cfg.max_neighbours,
        )
        self.pos_m = start_grid(n, cfg.spacing_m, cfg.start_ne_m)
        self.vel_m_s = np.zeros((n, 3))
        self.cmd_vel_m_s = np.zeros((n, 3))
        self.heading_rad = np.zeros(n)
        self.armed = np.zeros(n, bool)
        self.battery_pct = np.full(n, 100.0)
        self.modes = [Mode.LANDED] * n
        self.goal_m = np.zeros((n, 3))
        self.hold_m = self.pos_m.copy()
        # Held policy decisions, as agent.guidance: decide once per period, filter every tick.
        period = g.decision_period_s
        self.decision_period_s = self.policy.decision_period_s if period is None else period
        self._held_pref_m_s = np.zeros((n, 2))
        self._held_goal_m = np.full((n, 3), np.nan)  # NaN: nothing held
        self._decided_s = np.full(n, -np.inf)
        self.home_m = self.pos_m.copy()
        self.takeoff_alt_m = np.full(n, 10.0)
        self.seq = 0
        self.stats = TickStats()
        self._lock = threading.Lock()
        self._others: dict[int, tuple[VehicleState, float]] = {}
        self._now_s = clock_s()
        if cfg.see_others:
            mesh.subscribe_states(self._on_state)
        for i, vid in enumerate(self.ids.tolist()):
            mesh.serve_commands(vid, lambda c, i=i: self.handle_command(i, c))
        for vid in self.ids.tolist():  # answer commands before announcing presence
            mesh.declare_vehicle(vid)

    # -- mesh (Zenoh threads) ------------------------------------------------------------------
    def _on_state(self, state: VehicleState, _recv_ns: int) -> None:
        if self.cfg.first_id <= state.vehicle_id < self.cfg.first_id + self.cfg.vehicles:
            return
        with self._lock:
            self._others[state.vehicle_id] = (state, self.clock_s())

    def handle_command(self, i: int, cmd: Command) -> CommandAck:
        with self._lock:
            result, reason = self._apply(i, cmd)
            mode = self.modes[i]
        return CommandAck(int(self.ids[i]), cmd.nonce, self.mesh.clock_ns(), result, reason, mode)

    def _apply(self, i: int, cmd: Command) -> tuple[AckResult, str]:
        trigger = COMMAND_TRIGGERS[cmd.kind]
        target = None
        if trigger is Trigger.GOTO:
            p = cmd.params
            target = np.array(
                self.cfg.origin.to_local(*p) if cmd.kind is CommandKind.GOTO_GLOBAL else p, float
            )
            problem = self.cfg.failsafe.check_target(target)
            if problem:
                return AckResult.REJECTED, problem
        if cmd.kind is CommandKind.TAKEOFF and cmd.params[0] > self.cfg.failsafe.max_alt_m:
            return (
                AckResult.REJECTED,
                f"takeoff altitude {cmd.params[0]:g} m is above the {self.cfg.failsafe.max_alt_m:g} m limit",
            )
        if cmd.kind is CommandKind.TAKEOFF and not (
            math.isfinite(cmd.params[0]) and cmd.params[0] > 0
        ):
            return (
                AckResult.FAILED,
                f"vehicle refused: takeoff altitude must be positive, got {cmd.params[0]}",
            )
        res = step(self.modes[i], trigger)
        if not res.accepted:
            return AckResult.REJECTED, res.reason
        self._enter(
            i, res.mode, trigger, target, cmd.params[0] if cmd.kind is CommandKind.TAKEOFF else None
        )
        return AckResult.ACCEPTED, ""

    def _enter(
        self, i: int, mode: Mode, trigger: Trigger, target=None, alt_m: float | None = None
    ) -> None:
        """Record `mode` for vehicle i and set what the physics and guidance need for it."""
        pos, previous = self.pos_m[i], self.modes[i]
        if mode is Mode.TAKING_OFF:
            if previous is Mode.LANDED:
                self.home_m[i] = pos
            self.takeoff_alt_m[i] = alt_m if alt_m is not None else self.takeoff_alt_m[i]
            self.armed[i] = True
            self.hold_m[i] = pos
        elif mode is Mode.HOLDING:
            self.hold_m[i] = self.goal_m[i] if trigger is Trigger.ARRIVED else pos
            if trigger is Trigger.REACHED_ALTITUDE:
                self.hold_m[i, 2] = -self.takeoff_alt_m[i]
        elif mode is Mode.GOTO:
            self.goal_m[i] = target
            if previous is not Mode.GOTO:
                d = target[:2] - pos[:2]
                if math.hypot(*d) > 1e-6:
                    self.heading_rad[i] = math.atan2(d[1], d[0])
        elif mode is Mode.RETURNING:
            home = self.home_m[i]
            self.goal_m[i] = (home[0], home[1], min(pos[2], -self.cfg.failsafe.min_alt_m))
        elif mode is Mode.LANDING:
            self.hold_m[i] = pos
        elif mode is Mode.KILLED:
            self.armed[i] = False
        self.modes[i] = mode

    # -- the loop ------------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """Physics, vehicle events, batched guidance, then every vehicle's state."""
        t0 = time.perf_counter()
        with self._lock:
            dt_s = min(
                max(now_s - self._now_s, 0.0), 0.5
            )  # a stalled process must not teleport vehicles
            self._now_s = now_s
            if dt_s > 0:
                self._integrate(dt_s)
            self._vehicle_events()
            snap = self._guidance_inputs(now_s)
        cmd = self._guidance(*snap, now_s=now_s) if snap is not None else None
        with self._lock:
            if cmd is not None:
                rows, v_h = cmd
                keep = [k for k, i in enumerate(rows) if self.modes[i] in (*FLYING, Mode.HOLDING)]
                self.cmd_vel_m_s[rows[keep], :2] = v_h[keep]
                fast = np.hypot(v_h[keep, 0], v_h[keep, 1]) > 0.05
                self.heading_rad[rows[keep][fast]] = np.arctan2(
                    v_h[keep][fast, 1], v_h[keep][fast, 0]
                )
            states = self._states()
        for s in states:
            try:
                self.mesh.publish_state(s)
            except Exception as exc:  # noqa: BLE001 - a full network buffer must not stop the fleet
                log.warning("state publish failed: %s", exc)
        self.stats.ticks += 1
        self.stats.tick_ms.append((time.perf_counter() - t0) * 1e3)

    def _integrate(self, dt_s: float) -> None:
        """SimBackend's point mass, for all vehicles at once."""
        sim, g = self.cfg.sim, self.cfg.guidance
        modes = np.array([int(m) for m in self.modes])
        pos, vel = self.pos_m, self.vel_m_s
        want = np.zeros_like(vel)
        held = np.isin(modes, (Mode.TAKING_OFF, Mode.LANDING))
        want[held] = sim.hold_gain_1_s * (self.hold_m[held] - pos[held])
        up = held & (modes == Mode.TAKING_OFF)
        want[up, 2] = np.where(
            -pos[up, 2] < self.takeoff_alt_m[up] - 0.05, -sim.climb_rate_m_s, 0.0
        )
        down = held & (modes == Mode.LANDING)
        want[down, 2] = np.where(-pos[down, 2] > 2.0, 1.0, 0.5) * sim.descent_rate_m_s
        guided = np.isin(modes, (Mode.GOTO, Mode.RETURNING, Mode.HOLDING)) & self.armed
        want[guided, :2] = self.cmd_vel_m_s[guided, :2]
        goal_d = np.where(modes == Mode.HOLDING, self.hold_m[:, 2], self.goal_m[:, 2])
        want[guided, 2] = np.clip(
            g.vertical_gain_1_s * (goal_d - pos[:, 2]),
            -g.max_vertical_speed_m_s,
            g.max_vertical_speed_m_s,
        )[guided]
        dv = want - vel
        norm = np.linalg.norm(dv, axis=1)
        dv *= (np.minimum(1.0, sim.max_accel_m_s2 * dt_s / np.maximum(norm, 1e-12)))[:, None]
        dv[~self.armed] = 0.0
        vel += dv
        falling = ~self.armed & (pos[:, 2] < 0)  # killed in the air: motors off
        vel[falling, :2] *= max(0.0, 1.0 - 0.5 * dt_s)  # drag
        vel[falling, 2] += GRAVITY_M_S2 * dt_s
        vel[~self.armed & ~falling] = 0.0
        pos += vel * dt_s
        touch = pos[:, 2] >= 0.0
        pos[touch, 2] = 0.0
        stop = touch & (vel[:, 2] > 0)
        vel[stop] = 0.0
        self.armed[stop & np.isin(modes, (Mode.LANDING, Mode.KILLED))] = False
        flying = (pos[:, 2] < -0.05) & self.armed
        self.battery_pct[flying] = np.maximum(
            0.0, self.battery_pct[flying] - sim.battery_drain_pct_s * dt_s
        )
        moving = (np.hypot(vel[:, 0], vel[:, 1]) > 0.2 * g.cruise_speed_m_s) & ~guided
        self.heading_rad[moving] = np.arctan2(vel[moving, 1], vel[moving, 0])

    def _vehicle_events(self) -> None:
        """Reached altitude, arrived, touched down: found with array masks, then each one goes
        through the mode machine like the agent's."""
        g = self.cfg.guidance
        modes = np.array([int(m) for m in self.modes])
        alt_m = -self.pos_m[:, 2]
        miss = self.goal_m - self.pos_m
        arrived = (np.hypot(miss[:, 0], miss[:, 1]) <= g.arrive_radius_m) & (
            np.abs(miss[:, 2]) <= g.arrive_alt_tol_m
        )
        events = (
            (
                Trigger.REACHED_ALTITUDE,
                (modes == Mode.TAKING_OFF) & (alt_m >= self.takeoff_alt_m - 0.3),
            ),
            (Trigger.ARRIVED, np.isin(modes, FLYING) & arrived),
            (
                Trigger.TOUCHED_DOWN,
                np.isin(modes, (Mode.LANDING, Mode.KILLED)) & (alt_m <= 0.05) & ~self.armed,
            ),
        )
        for trig, mask in events:
            for i in np.flatnonzero(mask).tolist():
                res = step(self.modes[i], trig)
                if res.accepted:
                    self._enter(i, res.mode, trig)

    def _guidance_inputs(self, now_s: float):
        """Copies of what guidance needs: our vehicles that fly by velocity, plus all airborne
        vehicles (ours and others') as the policy's world."""
        modes = self.modes
        airborne = np.array([m in AIRBORNE for m in modes]) & self.armed
        guided = np.flatnonzero(
            np.array([m in (*FLYING, Mode.HOLDING) for m in modes]) & self.armed
        )
        if guided.size == 0:
            return None
        for vid in [v for v, (_, t) in self._others.items() if now_s - t > self.cfg.drop_s]:
            del self._others[vid]
        ext = [
            (s, now_s - t)
            for s, t in self._others.values()
            if s.armed or s.mode not in (Mode.LANDED, Mode.KILLED)
        ]
        ext_pos = np.array(
            [np.add(s.pos_ned_m, np.multiply(s.vel_ned_m_s, age)) for s, age in ext]
        ).reshape(-1, 3)
        ext_vel = np.array([s.vel_ned_m_s for s, _ in ext]).reshape(-1, 3)
        ext_hdg = np.array([s.heading_rad for s, _ in ext]).reshape(-1)
        goal = np.where(np.array([m in FLYING for m in modes])[:, None], self.goal_m, self.hold_m)
        return (
            np.concatenate([self.pos_m, ext_pos]),
            np.concatenate([self.vel_m_s, ext_vel]),
            np.concatenate([self.heading_rad, ext_hdg]),
            np.concatenate([goal, ext_pos]),
            np.concatenate([airborne, np.ones(len(ext), bool)]),
            guided,
            np.array([m is Mode.HOLDING for m in modes]),
        )

    def _guidance(self, pos, vel, heading, goal, active, guided, holding, now_s: float = 0.0):
        """(rows, horizontal velocity commands (len(rows), 2)): the policy in goto and return
        (decided once per decision period and held in between), position hold otherwise, then
        the safety filter for everyone (as agent.guidance)."""
        g, s = self.cfg.guidance, self.policy.dist_scale_m
        n = len(holding)
        flying = np.zeros(n, bool)
        flying[guided] = True
        flying &= ~holding
        due = flying & (
            (now_s - self._decided_s >= DECISION_DUE_SHARE * self.decision_period_s)
            | ~np.all(self._held_goal_m == goal[:n], axis=1)  # new goal, or nothing held (NaN)
        )
        rows = np.flatnonzero(due)  # the network runs for these only; the others hold
        a, nbr = self.policy.action_batch(
            pos[:, :2] / s, heading, goal[:, :2] / s, active, rows=rows
        )
        self._held_pref_m_s[rows] = (
            features.action_to_velocity(a, heading[rows]) * g.cruise_speed_m_s
        )
        self._held_goal_m[rows] = goal[rows]
        self._decided_s[rows] = now_s
        self._held_goal_m[~flying] = np.nan  # a hold or landing forgets the decision
        hold = g.hold_gain_1_s * (goal[:, :2] - pos[:, :2])
        hold *= (
            g.cruise_speed_m_s / np.maximum(np.hypot(hold[:, 0], hold[:, 1]), g.cruise_speed_m_s)
        )[:, None]
        pref = np.zeros((len(pos), 2))
        pref[:n][flying] = self._held_pref_m_s[flying]
        pref[:n][holding] = hold[:n][holding]
        if g.safety_filter:
            pref = safety.filter_batch(pos[:, :2], vel[:, :2], pref, nbr, self.policy.safety_cfg)
        return guided, pref[guided]

    def _states(self) -> list[VehicleState]:
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        stamp_ns = self.mesh.clock_ns()
        # whole arrays to Python floats once: per-row numpy access costs more than the rest
        pos, vel, goal, hold = (
            a.tolist() for a in (self.pos_m, self.vel_m_s, self.goal_m, self.hold_m)
        )
        hdg = np.remainder(self.heading_rad + math.pi, 2 * math.pi) - math.pi
        out = []
        for i, (vid, h, armed, batt) in enumerate(
            zip(
                self.ids.tolist(),
                hdg.tolist(),
                self.armed.tolist(),
                self.battery_pct.tolist(),
                strict=True,
            )
        ):
            mode = self.modes[i]
            g = goal[i] if mode in FLYING else hold[i] if mode is Mode.HOLDING else None
            out.append(
                VehicleState(
                    vehicle_id=vid,
                    seq=self.seq,
                    stamp_ns=stamp_ns,
                    pos_ned_m=tuple(pos[i]),
                    vel_ned_m_s=tuple(vel[i]),
                    heading_rad=h,
                    mode=mode,
                    armed=armed,
                    battery_pct=batt,
                    flags=_HAS_GOAL if g is not None else StateFlag.OPEN_MODE,
                    goal_ned_m=tuple(g) if g is not None else (0.0, 0.0, 0.0),
                )
            )
        return out

    def run(self, stop: threading.Event) -> None:
        """Tick at `rate_hz` until `stop` is set; an overrun skips ahead instead of bunching up."""
        period_s = 1.0 / self.cfg.rate_hz
        next_s = self.clock_s()
        while not stop.is_set():
            try:
                self.tick(self.clock_s())
            except Exception:  # noqa: BLE001 - keep the fleet alive; the log has the traceback
                log.exception("fleet tick failed")
            next_s += period_s
            now = self.clock_s()
            if next_s < now:
                self.stats.overruns += 1
                next_s = now + period_s
            stop.wait(max(0.0, next_s - now))


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
        timer = threading.Timer(duration_s, stop.set) if duration_s is not None else None
        if timer is not None:
            timer.daemon = True
            timer.start()
        try:
            fleet.run(stop)
        finally:
            if timer is not None:
                timer.cancel()
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
