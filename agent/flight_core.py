"""The flight core: what every vehicle does, for N vehicles as arrays. Pure; no I/O, no clock.

One core serves every shell: `covey agent` is a core of one vehicle around one backend,
`covey fleet-sim` a core of hundreds around the vectorised simulator. The same command on the
same state gives the same result in both (tests/test_flight_core.py).

The core owns, per vehicle:
- the mode machine (agent/modes.py) and the one mode-entry table (`_enter`): what entering a
  mode sets (goal, hold point, home, take-off altitude) and which autopilot action it needs;
- command checks (geofence, altitude limits, take-off altitude, the zone goal rule for gotos and
  mission waypoints, whoever guides) and the goto-global conversion;
- vehicle events found from telemetry (reached altitude, arrived, touched down, disarmed);
- failsafes (agent/failsafe.py: ground station lost, battery, geofence);
- guidance (agent/guidance.py: the policy decides, its decision is held, the filter runs).

A command is answered as soon as the mode machine accepts it. What the autopilot must do for it
comes back as `Action`s, which the shell runs off the tick (agent/actions.py) and reports with
`action_done` / `action_failed`; a failed action rolls the vehicle's mode back. What the
operator should hear comes back as `Note`s, which the shell publishes as events.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from agent.failsafe import FailsafeConfig, Failsafes
from agent.guidance import BatchGuidance, GuidanceConfig, GuidanceStep, NeighbourViews
from agent.mission import Ending, LocalItem, MissionRun, RunStatus, resolve
from agent.modes import AIRBORNE, COMMAND_TRIGGERS, Trigger, step
from agent.neighbours import NeighbourSnapshot
from agent.returning import Returns
from comms.geo import GeoOrigin
from comms.one_row import NO_ROWS, ROW0
from comms.plan import FleetPlan, plan_refusal
from comms.schema import (
    AckResult,
    Command,
    CommandKind,
    EventKind,
    Mission,
    Mode,
    Severity,
    StateFlag,
)
from kit.masks import mode_mask
from policy.goal_rule import goal_rule
from policy.runtime import TOLD_SIGMA_FREE_M
from policy.safety import SafetyConfig

if TYPE_CHECKING:  # shapely and scipy load only with zones (`set_plan`)
    from policy.routes import Router

FLYING = (Mode.GOTO, Mode.RETURNING, Mode.MISSION)
AIRBORNE_MODES = [int(m) for m in AIRBORNE]
"""The airborne modes as integers, for `np.isin` on `FlightCore.mode`."""


def _xyz(values) -> tuple[float, float, float]:
    """The first three of `values` (a point: north, east, down or lat, lon, alt) as floats."""
    return (float(values[0]), float(values[1]), float(values[2]))


_FLYING = mode_mask(FLYING)
_GUIDED = mode_mask((Mode.GOTO, Mode.RETURNING, Mode.HOLDING, Mode.MISSION))
_ARRIVING = mode_mask((Mode.GOTO, Mode.RETURNING))
"""Modes whose arrival is a mode event (a mission's arrivals are its items', `_missions`)."""
_MISSION = int(Mode.MISSION)
MISSION_KINDS = frozenset(
    {
        CommandKind.MISSION_START,
        CommandKind.MISSION_PAUSE,
        CommandKind.MISSION_RESUME,
        CommandKind.MISSION_ABORT,
        CommandKind.MISSION_STATUS,
    }
)
_TOUCHING_DOWN = mode_mask((Mode.LANDING, Mode.KILLED))
_DOWN_UNASKED = mode_mask(AIRBORNE - {Mode.TAKING_OFF, Mode.LANDING})
_TAKING_OFF = int(Mode.TAKING_OFF)
_RETURNING = int(Mode.RETURNING)
TAKEOFF_DONE_M = 0.3
"""Take-off is complete within this distance below the take-off altitude."""
SPEED_FOR_HEADING = 0.2
"""Share of the cruise speed above which the heading follows the velocity."""
# The masks as lists, for one vehicle's mode as a Python int (`_observe_one`, `guided_rows`).
_ARRIVING_ONE = _ARRIVING.tolist()
_GROUNDING_ONE = (_TOUCHING_DOWN | _DOWN_UNASKED).tolist()
_GUIDED_ONE = _GUIDED.tolist()
_TIE_M = 1e-9
"""`_observe_one` leaves a tick to the rows' path where a distance or speed lies this near its
bound: math.hypot and np.hypot each come within an ulp (1e-15 m at a few metres), so they may
round apart only there."""


@dataclass(frozen=True)
class CoreConfig:
    """What every vehicle of a core shares."""

    takeoff_alt_m: float = 10.0
    """Default take-off altitude when a takeoff command gives none."""
    origin: GeoOrigin = GeoOrigin()
    """Fleet origin: goto-global targets are converted to local NED around it."""
    guidance: GuidanceConfig = GuidanceConfig()
    failsafe: FailsafeConfig = FailsafeConfig()

    def __post_init__(self) -> None:
        if not (math.isfinite(self.takeoff_alt_m) and self.takeoff_alt_m > 0):
            raise ValueError(f"takeoff_alt_m must be positive, got {self.takeoff_alt_m}")


GNSS_WARN_SHARE = 1.2
"""A vehicle is told poor once its 1-sigma is this share of TOLD_SIGMA_FREE_M (0.6 m), and good
again within it: GNSS accuracy wanders, and a warning a second is noise."""
GNSS_POOR_M = TOLD_SIGMA_FREE_M * GNSS_WARN_SHARE
"""Beyond this 1-sigma a vehicle is told poor (`FlightCore._watch_gnss`)."""


class ActionKind(enum.Enum):
    """What an autopilot is asked to do (velocity setpoints are not actions: the tick sends them)."""

    TAKEOFF = "takeoff"
    LAND = "land"
    HOLD = "hold"
    KILL = "kill"
    GOTO = "goto"


@dataclass(frozen=True)
class _Undo:
    mode: Mode
    goal_m: np.ndarray
    hold_m: np.ndarray
    resume_goal_m: np.ndarray


@dataclass(frozen=True)
class Action:
    """One autopilot call for vehicle row `index`, and what to do if it fails."""

    index: int
    kind: ActionKind
    alt_m: float = math.nan
    """TAKEOFF: the altitude."""
    target_ned_m: tuple[float, float, float] | None = None
    """GOTO: the local target."""
    target_global: tuple[float, float, float] | None = None
    """GOTO from a goto-global command: (lat_deg, lon_deg, alt_m) as commanded, for autopilots
    that take global targets (no round trip through local coordinates)."""
    nonce: int | None = None
    """The command that asked for it; None for the core's own (vehicle events, failsafes)."""
    epoch: int = 0
    """The vehicle's mode epoch after entering the mode; a rollback applies only if unchanged."""
    undo: _Undo | None = field(default=None, repr=False, compare=False)

    def describe(self) -> str:
        if self.kind is ActionKind.TAKEOFF:
            return f"takeoff to {self.alt_m:g} m"
        if self.kind is ActionKind.GOTO and self.target_ned_m is not None:
            n, e, d = self.target_ned_m
            return f"goto ({n:.1f}, {e:.1f}, {d:.1f})"
        return self.kind.value


@dataclass(frozen=True)
class Note:
    """Something the operator should hear about vehicle row `index` (the shell publishes it)."""

    index: int
    text: str
    kind: EventKind = EventKind.STATUS
    severity: Severity = Severity.INFO


@dataclass(frozen=True)
class Decision:
    """The answer to a command: the ack's result, reason and mode, and the autopilot's part."""

    result: AckResult
    reason: str
    mode: Mode
    actions: tuple[Action, ...] = ()


@dataclass(frozen=True)
class Observed:
    """Telemetry of the core's vehicles, one row each (the shell fills it from its backends)."""

    pos_m: np.ndarray
    """(N, 3) NED"""
    vel_m_s: np.ndarray
    """(N, 3) NED"""
    armed: np.ndarray
    in_air: np.ndarray
    battery_pct: np.ndarray
    link_ok: np.ndarray
    """(N,) bool each (battery (N,) float)."""
    pos_sigma_m: np.ndarray | None = None
    """(N,) each position estimate's 1-sigma (m), the assumed one where the autopilot reports
    none (ShellConfig.assumed_pos_sigma_m); None: unchanged (0 until given)."""
    onboard_separation_m: np.ndarray | None = None
    """(N,) the separation each autopilot's own filter keeps (relay: the PX4 module's
    CVY_SEP_M), NaN where not known; None: none reported."""


def _nan3(n: int) -> np.ndarray:
    return np.full((n, 3), np.nan)


def _opt(a: np.ndarray) -> np.ndarray | None:
    return None if np.isnan(a[0]) else a.copy()


class FlightCore:
    """N vehicles' flight logic. Not thread-safe: the shell serialises calls (one lock)."""

    def __init__(
        self,
        cfg: CoreConfig,
        n: int,
        *,
        now_s: float,
        velocity_mode: bool = True,
        guidance: BatchGuidance | None = None,
        vehicle_ids: Sequence[int] | None = None,
    ) -> None:
        """`vehicle_ids`: the rows' vehicle ids (their return layers); default 1..n."""
        if n < 1:
            raise ValueError(f"a core needs at least one vehicle, got {n}")
        ids = np.arange(1, n + 1) if vehicle_ids is None else np.asarray(vehicle_ids, np.int64)
        self.returns = Returns(cfg.failsafe.returning, ids)
        """Each vehicle's return phase, landing spot and layer (agent/returning.py)."""
        self.cfg = cfg
        self.n = n
        self.velocity_mode = velocity_mode
        """The shell flies velocity setpoints (companion); False: the autopilot guides itself."""
        self.guidance = (guidance or BatchGuidance(cfg.guidance, n)) if velocity_mode else guidance
        self.mode = np.full(n, int(Mode.LANDED), np.int8)
        self.epoch = np.zeros(n, np.int64)
        self.goal_m = _nan3(n)
        self.hold_m = _nan3(n)
        self._targets: tuple[tuple[bytes, bytes, bytes], np.ndarray] | None = None
        """`targets()`'s last answer and what it was made of."""
        self.home_m = _nan3(n)
        self.resume_goal_m = _nan3(n)
        self.takeoff_alt_m = np.full(n, cfg.takeoff_alt_m)
        self.heading_rad = np.zeros(n)
        self.failsafes = [Failsafes(cfg.failsafe, now_s) for _ in range(n)]
        self.battery_pct = np.full(n, np.nan)
        """(N,) the battery as last observed (NaN: not yet); commands are checked against it."""
        self.pos_sigma_m = np.zeros(n)
        """(N,) the position 1-sigma as last observed: a goto's goal keeps the filter's zone
        clearance, 1.8 m + sigma_k x it (`_clear_goal`)."""
        self.gnss_poor = np.zeros(n, bool)
        """(N,) the position 1-sigma is beyond what the separation is rated for (`_watch_gnss`)."""
        self.notes: list[Note] = []
        """Events for the shell to publish (it drains the list)."""
        self.missions: list[MissionRun | None] = [None] * n
        """Each vehicle's uploaded mission and its progress (agent/mission.py), or None."""
        self.mission_waiting = np.zeros(n, bool)
        """(N,) a vehicle in MISSION mode waits at a reached item (guidance holds it there)."""
        self.mission_plan: FleetPlan | None = None
        """The fleet plan mission items are checked against (fence, keep-out zones, ceiling);
        None: the circular geofence and altitude limits alone."""
        self._own_router: Router | None = None
        """Without guidance (the autopilot guides itself): the plan's router, for the goal rule
        alone (`set_plan`, `router`)."""
        self.onboard_separation_m: float | None = None
        """The separation the autopilot's own filter keeps, once reported (relay: CVY_SEP_M);
        None: the configured one is assumed."""
        self._own_router_key: tuple | None = None
        """What `_own_router` was built from: the plan's polygons and the filter's radius and
        margin (a plan applied again with the same zones is not built again)."""
        self.now_s = now_s
        """The latest time the shell gave the core (`observe`): a pause keeps the rest of a
        wait from it."""

    # -- reading -------------------------------------------------------------------------------
    def mode_of(self, i: int) -> Mode:
        return Mode(int(self.mode[i]))

    @property
    def modes(self) -> list[Mode]:
        return [Mode(int(m)) for m in self.mode]

    def target_of(self, i: int) -> np.ndarray | None:
        """Where vehicle i is going (goto, return) or holding; None otherwise."""
        mode = self.mode_of(i)
        if mode in FLYING:
            return _opt(self.goal_m[i])
        if mode is Mode.HOLDING:
            return _opt(self.hold_m[i])
        return None

    def targets(self) -> np.ndarray:
        """(N, 3) `target_of` for every vehicle, NaN rows for none (read only: a tick asks
        several times, and it is made again only when a mode, goal or hold point changed)."""
        key = (self.mode.tobytes(), self.goal_m.tobytes(), self.hold_m.tobytes())
        if self._targets is not None and self._targets[0] == key:
            return self._targets[1]
        flying = _FLYING[self.mode]
        holding = self.mode == int(Mode.HOLDING)
        out = _nan3(self.n)
        out[flying] = self.goal_m[flying]
        out[holding] = self.hold_m[holding]
        out.flags.writeable = False
        self._targets = (key, out)
        return out

    @property
    def safety_cfg(self) -> SafetyConfig:
        """The separation filter's settings: guidance's own, or without guidance (the autopilot
        runs the filter: relay) what the configuration flies (`GuidanceConfig.safety_config`),
        at the separation the autopilot reports its filter keeps once it has (`observe`)."""
        if self.guidance is not None:
            return self.guidance.safety_cfg
        cfg = self.cfg.guidance.safety_config()
        if self.onboard_separation_m is not None:
            cfg = replace(cfg, radius_m=self.onboard_separation_m)
        return cfg

    @property
    def router(self) -> Router | None:
        """Routes around the plan's keep-out zones and fence (policy.routes.Router), None
        without any: guidance's own, or without guidance one built the same way (`set_plan`)
        for the goal rule (`_clear_goal`)."""
        if self.guidance is not None:
            return self.guidance.router
        return self._own_router

    def flags_of(self, i: int) -> StateFlag:
        return self.failsafes[i].flags

    def _watch_gnss(self) -> None:
        """Tell the operator when a vehicle's position 1-sigma goes beyond the preset's 0.5 m
        (policy.runtime.TOLD_SIGMA_FREE_M) by GNSS_WARN_SHARE, where the 3 m on true positions
        is no longer measured to hold (docs/sky.md, "GNSS worse than the preset"), and when it
        is back within 0.5 m: once each way, not every tick."""
        sigma = self.pos_sigma_m
        worse = ~self.gnss_poor & (sigma > GNSS_POOR_M)
        better = self.gnss_poor & (sigma <= TOLD_SIGMA_FREE_M)
        if not (worse.any() or better.any()):
            return
        cfg = self.safety_cfg
        for i in np.flatnonzero(worse).tolist():
            berth_m = cfg.radius_m * (1 + cfg.margin) + cfg.sigma_k * math.sqrt(2) * sigma[i]
            self.notes.append(
                Note(
                    i,
                    f"GNSS 1-sigma {sigma[i]:.2f} m is beyond the {TOLD_SIGMA_FREE_M:g} m the "
                    f"{cfg.radius_m:g} m separation is rated for: the filter keeps {berth_m:.1f} m "
                    "between estimates and dense groups slow down; fly RTK or a wider "
                    "--separation-m",
                    EventKind.STATUS,
                    Severity.WARNING,
                )
            )
        for i in np.flatnonzero(better).tolist():
            self.notes.append(
                Note(i, f"GNSS 1-sigma {sigma[i]:.2f} m: back within {TOLD_SIGMA_FREE_M:g} m")
            )
        self.gnss_poor = (self.gnss_poor | worse) & ~better

    def drain_notes(self) -> list[Note]:
        notes, self.notes = self.notes, []
        return notes

    # -- commands ------------------------------------------------------------------------------
    def command(
        self,
        i: int,
        cmd: Command,
        pos_m: np.ndarray | None,
        link_ok: bool = True,
        takeoff_problem: str | None = None,
    ):
        """Check `cmd` for vehicle i at `pos_m` (None: no telemetry yet) and enter its mode.
        `takeoff_problem`: why the shell's ground facts rule out leaving the ground now (no
        station on the mesh, the clock off: trust/heartbeat.py `takeoff_problem`); it refuses a
        take-off of a landed vehicle."""
        mode = self.mode_of(i)
        if cmd.kind is CommandKind.MISSION_STATUS:
            run = self.missions[i]
            return Decision(AckResult.ACCEPTED, run.describe() if run else "no mission", mode)
        if pos_m is None:
            return Decision(AckResult.REJECTED, "no telemetry from the vehicle yet", mode)
        if not link_ok and cmd.kind is not CommandKind.KILL:
            return Decision(AckResult.REJECTED, "autopilot link lost", mode)
        if cmd.kind in MISSION_KINDS:
            return self._mission_command(i, cmd, np.asarray(pos_m, float))
        trigger = COMMAND_TRIGGERS[cmd.kind]
        fs = self.cfg.failsafe
        target = target_global = None
        moved = ""  # a goto's goal moved out of a zone's clearance (`_clear_goal`)
        if trigger is Trigger.GOTO:
            if cmd.kind is CommandKind.GOTO_GLOBAL:
                target_global = _xyz(cmd.params)
                target = np.array(self.cfg.origin.to_local(*target_global))
            else:
                target = np.array(cmd.params[:3], dtype=float)
            target, moved, refused = self.check_target(i, target)
            if refused:
                return Decision(AckResult.REJECTED, refused, mode)
        alt_m = None
        if cmd.kind is CommandKind.TAKEOFF:
            alt_m = float(cmd.params[0])
            if not (math.isfinite(alt_m) and alt_m > 0):
                return Decision(
                    AckResult.REJECTED, f"takeoff altitude must be positive, got {alt_m}", mode
                )
            if alt_m > fs.max_alt_m:
                return Decision(
                    AckResult.REJECTED,
                    f"takeoff altitude {alt_m:g} m is above the {fs.max_alt_m:g} m limit",
                    mode,
                )
            here = (float(pos_m[0]), float(pos_m[1]))
            problem = plan_refusal(self.mission_plan, here, alt_m)
            if problem:
                return Decision(AckResult.REJECTED, f"cannot take off here: {problem}", mode)
        res = step(mode, trigger)
        if not res.accepted:
            return Decision(AckResult.REJECTED, res.reason, mode)
        if takeoff_problem and cmd.kind is CommandKind.TAKEOFF and mode is Mode.LANDED:
            return Decision(AckResult.REJECTED, takeoff_problem, mode)
        low_battery = fs.battery_refusal(cmd.kind, float(self.battery_pct[i]))
        if low_battery:
            return Decision(AckResult.REJECTED, low_battery, mode)
        actions = self._enter(i, res.mode, trigger, np.asarray(pos_m, float), target, alt_m)
        decided = tuple(
            replace(
                a,
                nonce=cmd.nonce,
                target_global=target_global if a.kind is ActionKind.GOTO else None,
            )
            for a in actions
        )
        return Decision(AckResult.ACCEPTED, moved, self.mode_of(i), decided)

    def check_target(self, i: int, target: np.ndarray) -> tuple[np.ndarray, str, str]:
        """(target to fly, what was moved, why refused) for vehicle i sent to `target` (a goto,
        a mission waypoint): the limits and the plan (`target_problem`), then the goal rule
        (`_clear_goal`)."""
        problem = self.target_problem(target)
        if problem:
            return target, "", problem
        return self._clear_goal(i, target)

    def _clear_goal(self, i: int, target: np.ndarray) -> tuple[np.ndarray, str, str]:
        """(target, what was moved, why refused) for a goto of vehicle i: a goal nearer a zone
        (or the fence) than the clearance its filter keeps, 1.8 m + sigma_k x its position
        1-sigma, is flown to the nearest point outside that clearance, where the vehicle can
        arrive, if that point is within the arrival radius of it; else the goto is refused,
        naming the zone and the distances (policy/goal_rule.py; the station's pre-checks word it
        alike). The same whether guidance or the autopilot flies (`router`, `safety_cfg`);
        without zones, the target as it is. Guided with zones that have a floor or ceiling: the
        zones active at the target's altitude alone (policy/zone_bands.py `at_alt`: a goal
        under an overhang is flown, as guidance flies it there); relay mode (the autopilot's
        filter knows no altitudes): every zone, at every altitude (the conservative reading)."""
        router = self.router
        plan = self.mission_plan
        names = [] if plan is None else [z.name for z in plan.keep_out]
        bands = None if self.guidance is None else self.guidance.bands
        if bands is not None:
            router, names = bands.goal_router(-float(target[2]), names)
        if router is None:
            return target, "", ""
        rule = goal_rule(
            router,
            target[:2],
            float(self.pos_sigma_m[i]),
            self.safety_cfg.sigma_k,
            self.cfg.guidance.arrive_radius_m,
            names,
        )
        if rule.refused:
            return target, "", f"target: {rule.refused}"
        if not rule.moved:
            return target, "", ""
        out = target.copy()
        out[:2] = rule.goal_ne_m
        return out, rule.moved, ""

    def _enter(
        self,
        i: int,
        mode: Mode,
        trigger: Trigger,
        pos_m: np.ndarray,
        target: np.ndarray | None = None,
        alt_m: float | None = None,
    ) -> list[Action]:
        """The mode-entry table: set what `mode` means for vehicle i; return the autopilot's
        actions for it."""
        previous = self.mode_of(i)
        undo = _Undo(
            previous, self.goal_m[i].copy(), self.hold_m[i].copy(), self.resume_goal_m[i].copy()
        )
        kind: ActionKind | None = None
        action_kw: dict = {}
        if mode is Mode.KILLED:
            kind = ActionKind.KILL
        elif mode is Mode.TAKING_OFF:
            if previous is Mode.LANDED:
                self.home_m[i] = pos_m
            if alt_m is not None:
                self.takeoff_alt_m[i] = alt_m
            kind, action_kw = ActionKind.TAKEOFF, {"alt_m": float(self.takeoff_alt_m[i])}
            self.hold_m[i] = pos_m
        elif mode is Mode.HOLDING:
            arrived = trigger is Trigger.ARRIVED and not np.isnan(self.goal_m[i, 0])
            self.hold_m[i] = self.goal_m[i] if arrived else pos_m
            if trigger is Trigger.REACHED_ALTITUDE:
                self.hold_m[i, 2] = -self.takeoff_alt_m[i]
            if trigger is Trigger.FAILSAFE_HOLD and previous is Mode.GOTO:
                self.resume_goal_m[i] = self.goal_m[i]
            if not self.velocity_mode:
                kind = ActionKind.HOLD
        elif mode is Mode.GOTO:
            assert target is not None
            if previous is not Mode.GOTO:
                self.heading_rad[i] = heading_towards(pos_m, target, self.heading_rad[i])
            self.goal_m[i] = target
            self.resume_goal_m[i] = np.nan
            if not self.velocity_mode:
                kind, action_kw = ActionKind.GOTO, {"target_ned_m": tuple(map(float, target))}
        elif mode is Mode.RETURNING:
            # its landing spot (home or the nearest rally point) on its layer (agent/returning.py)
            plan = self.mission_plan
            self.goal_m[i] = self.returns.enter(
                i,
                pos_m,
                self.home_m[i],
                [(r.n_m, r.e_m) for r in plan.rally] if plan is not None else [],
                self.cfg.failsafe.min_alt_m,
                self.cfg.guidance.arrive_alt_tol_m,
                self.return_ceiling_m(),
            )
            self.heading_rad[i] = heading_towards(pos_m, self.goal_m[i], self.heading_rad[i])
            if not self.velocity_mode:
                kind, action_kw = (
                    ActionKind.GOTO,
                    {"target_ned_m": tuple(map(float, self.goal_m[i]))},
                )
        elif mode is Mode.LANDING:
            kind = ActionKind.LAND
            self.hold_m[i] = pos_m
        elif mode is Mode.MISSION:
            run = self.missions[i]
            assert run is not None and run.target is not None
            self.goal_m[i] = run.target
            self.heading_rad[i] = heading_towards(pos_m, run.target, self.heading_rad[i])
            self.resume_goal_m[i] = np.nan
            self.mission_waiting[i] = not math.isnan(run.wait_until_s)  # resumed mid-wait
            if not self.velocity_mode:
                kind, action_kw = ActionKind.GOTO, {"target_ned_m": tuple(map(float, run.target))}
        if previous is Mode.MISSION and mode is not Mode.MISSION:
            # Whatever takes a vehicle out of its mission (a command, a failsafe) pauses it
            # there: resume continues the item; a failsafe's hold resumes it once it ends.
            run = self.missions[i]
            if run is not None:
                run.pause(self.now_s, by_failsafe=trigger is Trigger.FAILSAFE_HOLD)
            self.mission_waiting[i] = False
        if mode is not previous:
            self.notes.append(
                Note(
                    i,
                    f"{previous.name.lower()} -> {mode.name.lower()} ({trigger.value})",
                    EventKind.MODE_CHANGE,
                )
            )
        self.mode[i] = int(mode)
        self.epoch[i] += 1
        if mode not in FLYING and mode is not Mode.HOLDING:
            self.goal_m[i] = np.nan
        if self.guidance is not None and mode not in FLYING:
            self.guidance.forget(np.array([i]))
        if kind is None:
            return []
        return [Action(i, kind, epoch=int(self.epoch[i]), undo=undo, **action_kw)]

    def _internal(self, i: int, trigger: Trigger, pos_m: np.ndarray, why: str = "") -> list[Action]:
        res = step(self.mode_of(i), trigger)
        if not res.accepted:
            return []
        actions = self._enter(i, res.mode, trigger, pos_m, _opt(self.goal_m[i]))
        if why:
            self.notes.append(Note(i, why, EventKind.FAILSAFE, Severity.WARNING))
        return actions

    def _take_onboard_separation(self, reported_m: np.ndarray) -> None:
        """The separation the autopilots' own filters keep (relay: CVY_SEP_M), the largest
        reported: the goal rule's clearance follows it (`safety_cfg`, the router rebuilt), and
        the operator hears when it differs from the configured --separation-m."""
        known = reported_m[np.isfinite(reported_m)]
        if not known.size:
            return
        sep = float(known.max())
        if sep == self.onboard_separation_m:
            return
        self.onboard_separation_m = sep
        configured = self.cfg.guidance.separation_m
        if not math.isclose(sep, configured, rel_tol=1e-6):
            text = (
                f"the autopilot's filter keeps {sep:g} m (CVY_SEP_M), not the configured "
                f"--separation-m {configured:g} m: goals keep the clearance of {sep:g} m"
            )
            self.notes.append(Note(0, text, EventKind.STATUS, Severity.WARNING))
        self.set_plan(self.mission_plan)  # the router at the new separation

    # -- the fleet plan -------------------------------------------------------------------------
    def set_plan(self, plan: FleetPlan | None) -> None:
        """Check every goto, take-off and mission target against `plan` from now on (the shell
        calls it when comms/plan_sync.py applies a newer plan); None: no plan. Guidance then
        routes every goto around the plan's keep-out zones and its filter keeps their edges
        (and the fence's) as hard lines (agent/guidance.py set_zones, policy/routes.py), a zone
        with a floor or ceiling only for vehicles whose altitudes reach it (policy/zone_bands.py).
        Without guidance (relay: the autopilot's own filter keeps the zones, knowing no
        altitudes) the core builds the router guidance would for every zone at every altitude,
        with the same function and filter settings, for the goal rule alone (`_clear_goal`): a
        goal the autopilot's filter keeps it from is moved or refused here, not flown at for
        ever."""
        self.mission_plan = plan
        fence = None if plan is None or plan.fence is None else plan.fence.vertices_ne_m
        zones = [] if plan is None else plan.keep_out_polygons_ne_m()
        if self.guidance is not None:
            bands = (
                [] if plan is None else [(z.floor_alt_m, z.ceiling_alt_m) for z in plan.keep_out]
            )
            self.guidance.set_zones(zones, fence, bands)
            return
        cfg = self.safety_cfg
        key = (tuple(zones), fence, cfg.radius_m, cfg.margin)
        if key != self._own_router_key:
            from policy.routes import zones_for  # shapely and scipy: only with zones

            self._own_router = zones_for(cfg, zones, fence)[1]
            self._own_router_key = key

    def target_problem(self, target_ned_m: np.ndarray) -> str | None:
        """Why a goto target is refused, or None: the altitude limits (agent/failsafe.py), then
        the fleet plan (keep-out zones, its fence and floor/ceiling, comms/plan.py), whose
        polygon fence replaces the circular geofence; without a plan fence, the circle."""
        fs = self.cfg.failsafe
        plan = self.mission_plan
        if plan is not None and plan.fence is not None and fs.geofence_radius_m:
            fs = replace(fs, geofence_radius_m=0.0)
        problem = fs.check_target(target_ned_m)
        if problem:
            return problem
        why = plan_refusal(
            plan, (float(target_ned_m[0]), float(target_ned_m[1])), -float(target_ned_m[2])
        )
        return f"target {why}" if why else None

    # -- the autopilot's answers ---------------------------------------------------------------
    def action_failed(self, action: Action, reason: str) -> bool:
        """Roll vehicle `action.index` back to the mode before the action, unless something has
        changed its mode since; True if it was rolled back."""
        i, undo = action.index, action.undo
        text = f"{action.describe()} failed: {reason}"
        if action.nonce is None:
            self.notes.append(Note(i, text, EventKind.FAILSAFE, Severity.ERROR))
        if undo is None or self.epoch[i] != action.epoch:
            return False
        now = self.mode_of(i)
        self.mode[i] = int(undo.mode)
        self.goal_m[i], self.hold_m[i], self.resume_goal_m[i] = (
            undo.goal_m,
            undo.hold_m,
            undo.resume_goal_m,
        )
        self.epoch[i] += 1
        if now is not undo.mode:
            self.notes.append(
                Note(
                    i,
                    f"{now.name.lower()} -> {undo.mode.name.lower()} ({action.kind.value} failed)",
                    EventKind.MODE_CHANGE,
                    Severity.WARNING,
                )
            )
        return True

    # -- each tick -----------------------------------------------------------------------------
    def observe(
        self,
        now_s: float,
        obs: Observed,
        gcs_alive: bool,
        others: NeighbourSnapshot | None = None,
    ) -> list[Action]:
        """Vehicle events and failsafes from this tick's telemetry; returns the actions they need.
        `others`: vehicles outside the core (the neighbour table), which a returning vehicle
        lets land first when they are below it near its spot (agent/returning.py).

        One vehicle's quiet tick (an agent's every tick in flight) is taken in Python floats
        (`_observe_one`), any other by the rows' path (`_observe_rows`, the reference): the same
        either way (tests/test_observe_one_row.py)."""
        if self.n == 1 and self._observe_one(now_s, obs, gcs_alive):
            return []
        return self._observe_rows(now_s, obs, gcs_alive, others)

    def _observe_one(self, now_s: float, obs: Observed, gcs_alive: bool) -> bool:
        """`_observe_rows` for one vehicle whose tick only takes in its telemetry: no vehicle
        event, not returning or on a mission, no failsafe active or able to act
        (`FailsafeConfig.calm_one`, `Failsafes.settled`). True once taken; False, with nothing
        changed, for the rows' path to take the tick (also where a distance or speed lies on
        its bound, `_TIE_M`). An agent's cold tick pays several microseconds for each small
        numpy call, and most of this one's cost was theirs (docs/companion.md)."""
        mode = self.mode.item(0)
        fs = self.failsafes[0]
        if mode in (_RETURNING, _MISSION) or not fs.settled:
            return False
        pn, pe, pd = obs.pos_m[0].tolist()
        if not self.cfg.failsafe.calm_one(gcs_alive, obs.battery_pct.item(0), pn, pe):
            return False
        # the rows' four events, none near
        if mode == _TAKING_OFF and -pd >= self.takeoff_alt_m.item(0) - TAKEOFF_DONE_M:
            return False
        if _GROUNDING_ONE[mode] and not (obs.in_air.item(0) or obs.armed.item(0)):
            return False
        g = self.cfg.guidance
        if _ARRIVING_ONE[mode]:
            gn, ge, gd = self.goal_m[0].tolist()
            if (
                math.hypot(gn - pn, ge - pe) <= g.arrive_radius_m + _TIE_M
                and abs(gd - pd) <= g.arrive_alt_tol_m
            ):
                return False
        vn, ve = obs.vel_m_s[0, :2].tolist()
        speed, heading_above = math.hypot(vn, ve), SPEED_FOR_HEADING * g.cruise_speed_m_s
        if abs(speed - heading_above) <= _TIE_M:
            return False
        # quiet: what the rows' path does on it, in its order
        self.now_s = now_s
        self.battery_pct[0] = obs.battery_pct.item(0)
        if obs.pos_sigma_m is not None:
            sigma = obs.pos_sigma_m.item(0)
            self.pos_sigma_m[0] = sigma
            poor = self.gnss_poor.item(0)
            if (sigma <= TOLD_SIGMA_FREE_M) if poor else (sigma > GNSS_POOR_M):  # a note is due
                self._watch_gnss()
        if obs.onboard_separation_m is not None and self.guidance is None:
            sep = obs.onboard_separation_m.item(0)
            if math.isfinite(sep) and sep != self.onboard_separation_m:
                self._take_onboard_separation(obs.onboard_separation_m)
        if speed > heading_above:
            self.heading_rad[0] = math.atan2(ve, vn)
        fs.saw_gcs(now_s)
        return True

    def _observe_rows(
        self,
        now_s: float,
        obs: Observed,
        gcs_alive: bool,
        others: NeighbourSnapshot | None = None,
    ) -> list[Action]:
        """`observe` for any number of vehicles, as arrays: the reference `_observe_one` is
        tested against."""
        actions: list[Action] = []
        pos, vel = obs.pos_m, obs.vel_m_s
        self.now_s = now_s
        self.battery_pct[:] = obs.battery_pct
        if obs.pos_sigma_m is not None:
            self.pos_sigma_m[:] = obs.pos_sigma_m
            self._watch_gnss()
        if obs.onboard_separation_m is not None and self.guidance is None:
            self._take_onboard_separation(obs.onboard_separation_m)
        cruise = self.cfg.guidance.cruise_speed_m_s
        speed = np.hypot(vel[:, 0], vel[:, 1])
        moving = speed > SPEED_FOR_HEADING * cruise
        self.heading_rad[moving] = np.arctan2(vel[moving, 1], vel[moving, 0])
        g = self.cfg.guidance
        miss = self.goal_m - pos
        arrived = (np.hypot(miss[:, 0], miss[:, 1]) <= g.arrive_radius_m) & (
            np.abs(miss[:, 2]) <= g.arrive_alt_tol_m
        )
        returning = self.mode == _RETURNING
        if returning.any():
            arrived, turned = self.returns.arrivals(
                returning,
                arrived,
                pos,
                self.goal_m,
                None if others is None else others.pos_ned_m,
                None if others is None else np.array(others.ids, np.int64),
            )
            if not self.velocity_mode:  # the autopilot flies the new leg itself
                actions += [
                    Action(i, ActionKind.GOTO, target_ned_m=_xyz(self.goal_m[i])) for i in turned
                ]
        mode = self.mode
        on_ground = ~obs.in_air & ~obs.armed
        events = (
            (mode == _TAKING_OFF) & (-pos[:, 2] >= self.takeoff_alt_m - TAKEOFF_DONE_M),
            _ARRIVING[mode] & arrived,
            _TOUCHING_DOWN[mode] & on_ground,
            _DOWN_UNASKED[mode] & on_ground,
        )
        triggers = (Trigger.REACHED_ALTITUDE, Trigger.ARRIVED, Trigger.TOUCHED_DOWN, None)
        done = np.zeros(self.n, bool)
        # most ticks have no event at all: one test, not four scans
        some = events[0] | events[1] | events[2] | events[3]
        for trigger, mask in zip(triggers, events if some.any() else (), strict=False):
            for i in np.flatnonzero(mask & ~done).tolist():
                done[i] = True
                if trigger is None:
                    self.mode[i] = int(Mode.LANDED)
                    self.epoch[i] += 1
                    if self.guidance is not None:
                        self.guidance.forget(np.array([i]))
                    self.notes.append(
                        Note(
                            i,
                            "vehicle is on the ground and disarmed",
                            EventKind.MODE_CHANGE,
                            Severity.WARNING,
                        )
                    )
                else:
                    actions += self._internal(i, trigger, pos[i])
        for i in np.flatnonzero(mode == _MISSION).tolist():
            actions += self._mission_step(i, now_s, pos[i], bool(arrived[i]))
        calm = self.cfg.failsafe.calm_rows(gcs_alive, obs.battery_pct, pos).tolist()
        for i, fs in enumerate(self.failsafes):
            # most ticks, most vehicles: evaluate would only note the station
            if calm[i] and fs.settled:
                fs.saw_gcs(now_s)
                continue
            if gcs_alive and fs.gcs_failsafe_active:
                fs.gcs_back(now_s)
                self.notes.append(Note(i, "ground station back", EventKind.FAILSAFE))
                resume = _opt(self.resume_goal_m[i])
                if self.mode_of(i) is Mode.HOLDING and resume is not None:
                    self.resume_goal_m[i] = np.nan
                    actions += self._enter(i, Mode.GOTO, Trigger.GOTO, pos[i], resume)
                run = self.missions[i]
                if self.mode_of(i) is Mode.HOLDING and run is not None and run.by_failsafe:
                    run.resume(now_s)
                    actions += self._enter(i, Mode.MISSION, Trigger.MISSION_RESUME, pos[i])
            act = fs.evaluate(now_s, self.mode_of(i), gcs_alive, float(obs.battery_pct[i]), pos[i])
            if act is not None:
                actions += self._internal(i, act.trigger, pos[i], act.reason)
        return actions

    def return_ceiling_m(self) -> float:
        """The highest a return layer may be: the failsafe's maximum or the plan's ceiling."""
        fence = self.mission_plan.fence if self.mission_plan is not None else None
        top = self.cfg.failsafe.max_alt_m
        if fence is not None and fence.ceiling_alt_m is not None:
            top = min(top, fence.ceiling_alt_m)
        return top

    # -- missions ------------------------------------------------------------------------------
    def mission_alt_problem(self, alt_m: float) -> str | None:
        """Why a mission take-off altitude (above the origin) is refused."""
        fs = self.cfg.failsafe
        if not fs.min_alt_m <= alt_m <= fs.max_alt_m:
            return f"altitude {alt_m:.1f} m is outside [{fs.min_alt_m:g}, {fs.max_alt_m:g}] m"
        fence = self.mission_plan.fence if self.mission_plan is not None else None
        if fence is not None and fence.ceiling_alt_m is not None and alt_m > fence.ceiling_alt_m:
            return f"altitude {alt_m:.1f} m is above the {fence.ceiling_alt_m:g} m ceiling"
        return None

    def load_mission(self, i: int, mission: Mission) -> Decision:
        """Check vehicle i's uploaded mission item by item and keep it (not flown before a
        start). Refused with the first bad item's reason; a mission being flown is not replaced
        (pause or abort it first)."""
        mode = self.mode_of(i)
        if mode is Mode.KILLED:
            return Decision(AckResult.REJECTED, step(mode, Trigger.MISSION_START).reason, mode)
        run = self.missions[i]
        if mode is Mode.MISSION and run is not None:
            k, n = run.progress()
            return Decision(
                AckResult.REJECTED,
                f"flying mission {run.mission_id} (item {k}/{n}): pause or abort it first",
                mode,
            )
        asked, problem = resolve(
            mission, self.cfg.origin, self.target_problem, self.mission_alt_problem
        )
        if problem:
            return Decision(AckResult.REJECTED, problem, mode)
        cruise = self.cfg.guidance.cruise_speed_m_s
        for k, item in enumerate(asked, 1):
            if item.speed_m_s > cruise:
                problem = (
                    f"item {k}: speed {item.speed_m_s:g} m/s is above the {cruise:g} m/s cruise "
                    "speed (guidance flies at most that)"
                )
                return Decision(AckResult.REJECTED, problem, mode)
        items, moved, problem = self._clear_items(i, asked)
        if problem:
            return Decision(AckResult.REJECTED, problem, mode)
        self.missions[i] = MissionRun(mission.mission_id, mission.mission_version, items, asked)
        self.notes.append(
            Note(
                i,
                f"mission {mission.mission_id} v{mission.mission_version} loaded: {len(items)} items",
            )
        )
        return Decision(AckResult.ACCEPTED, "; ".join([f"{len(items)} items", *moved]), mode)

    def _clear_items(
        self, i: int, asked: tuple[LocalItem, ...]
    ) -> tuple[tuple[LocalItem, ...], list[str], str]:
        """(items to fly, what was moved, why refused) for vehicle i's mission items as uploaded:
        every waypoint checked as a goto's target (`check_target`: the limits, the plan, the goal
        rule), each move and the first refusal named by the item's number."""
        out, moved = [], []
        for k, item in enumerate(asked, 1):
            if item.target_ned_m is None:
                out.append(item)
                continue
            target, what, problem = self.check_target(i, np.array(item.target_ned_m, float))
            if problem:
                return (), [], f"item {k} ({item.kind.name.lower()}): {problem}"
            if what:
                moved.append(f"item {k}: {what}")
            out.append(replace(item, target_ned_m=_xyz(target)))
        return tuple(out), moved, ""

    def mission_progress(self, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(k, n) per row (`MissionRun.progress`): k the item flown, n the items; 0, 0 for no
        mission."""
        rows = np.arange(self.n) if rows is None else np.asarray(rows)
        k, n = np.zeros(len(rows), np.int64), np.zeros(len(rows), np.int64)
        for j, r in enumerate(rows.tolist()):
            run = self.missions[r]
            if run is not None:
                k[j], n[j] = run.progress()
        return k, n

    def _mission_command(self, i: int, cmd: Command, pos_m: np.ndarray) -> Decision:
        mode, run = self.mode_of(i), self.missions[i]
        kind = cmd.kind
        trigger = COMMAND_TRIGGERS[kind]
        res = step(mode, trigger)
        if not res.accepted:
            return Decision(AckResult.REJECTED, res.reason, mode)
        if kind is CommandKind.MISSION_ABORT:
            if run is None or run.status is RunStatus.LOADED:
                return Decision(AckResult.ACCEPTED, "no mission flying", mode)
            run.abort()
            self.notes.append(Note(i, f"mission {run.mission_id} aborted", EventKind.COMMAND))
            actions = self._enter(i, res.mode, trigger, pos_m) if mode is Mode.MISSION else []
            return self._decided(i, cmd, actions)
        if run is None:
            return Decision(AckResult.REJECTED, "no mission uploaded", mode)
        low_battery = self.cfg.failsafe.battery_refusal(kind, float(self.battery_pct[i]))
        if low_battery and kind in (CommandKind.MISSION_START, CommandKind.MISSION_RESUME):
            return Decision(AckResult.REJECTED, low_battery, mode)
        if kind is CommandKind.MISSION_PAUSE:
            if run.status is RunStatus.PAUSED and mode is Mode.HOLDING:
                return Decision(AckResult.ACCEPTED, run.describe(), mode)
            if mode is not Mode.MISSION:
                return Decision(
                    AckResult.REJECTED, f"not flying a mission ({run.describe()})", mode
                )
            run.pause(self.now_s)
            self.notes.append(Note(i, f"mission {run.mission_id} paused", EventKind.COMMAND))
            return self._decided(i, cmd, self._enter(i, Mode.HOLDING, trigger, pos_m))
        if kind is CommandKind.MISSION_RESUME:
            if mode is Mode.MISSION:
                return Decision(AckResult.ACCEPTED, run.describe(), mode)
            if run.status is not RunStatus.PAUSED:
                return Decision(AckResult.REJECTED, f"no paused mission ({run.describe()})", mode)
            run.resume(self.now_s)
            self.notes.append(Note(i, f"mission {run.mission_id} resumed", EventKind.COMMAND))
            return self._decided(i, cmd, self._enter(i, Mode.MISSION, trigger, pos_m))
        # MISSION_START: from item 1, whatever the progress; the items as uploaded are checked
        # again, against the plan and the position sigma of now (either may have changed)
        items, moved, problem = self._clear_items(i, run.asked)
        if problem:
            return Decision(AckResult.REJECTED, problem, mode)
        run.items = items
        tick = run.start(pos_m)
        self.mission_waiting[i] = False
        self.notes.append(
            Note(i, f"mission {run.mission_id} started: {run.n} items", EventKind.COMMAND)
        )
        return self._decided(i, cmd, self._mission_begun(i, tick, pos_m, trigger), "; ".join(moved))

    def _decided(self, i: int, cmd: Command, actions: list[Action], reason: str = "") -> Decision:
        actions = [replace(a, nonce=cmd.nonce) for a in actions]
        return Decision(AckResult.ACCEPTED, reason, self.mode_of(i), tuple(actions))

    def _mission_begun(self, i: int, tick, pos_m: np.ndarray, trigger: Trigger) -> list[Action]:
        """Enter what the item just begun asks: fly to its target (MISSION), or the mission's
        end (land, return)."""
        run = self.missions[i]
        assert run is not None
        if tick.started:
            n = run.n
            item = run.items[tick.started - 1]
            self.notes.append(
                Note(
                    i, f"mission {run.mission_id}: item {tick.started}/{n} {item.kind.name.lower()}"
                )
            )
        if tick.ending is Ending.LAND:
            return self._enter(i, Mode.LANDING, Trigger.LAND, pos_m)
        if tick.ending is Ending.RETURN:
            return self._enter(i, Mode.RETURNING, Trigger.RETURN, pos_m)
        if tick.ending is Ending.HOLD:
            self.notes.append(Note(i, f"mission {run.mission_id} done", EventKind.STATUS))
            return self._enter(i, Mode.HOLDING, Trigger.MISSION_DONE, pos_m)
        if self.mode_of(i) is Mode.MISSION:  # the next item: a new goal, same mode
            self.goal_m[i] = run.target
            self.mission_waiting[i] = False
            if not self.velocity_mode:
                target = _xyz(run.target)
                return [Action(i, ActionKind.GOTO, target_ned_m=target, epoch=int(self.epoch[i]))]
            return []
        return self._enter(i, Mode.MISSION, trigger, pos_m)

    def _mission_step(self, i: int, now_s: float, pos_m: np.ndarray, arrived: bool) -> list[Action]:
        run = self.missions[i]
        if run is None or run.status is not RunStatus.ACTIVE:
            return []
        tick = run.step(now_s, pos_m, arrived)
        if tick.reached:
            self.mission_waiting[i] = True
            self.notes.append(
                Note(i, f"mission {run.mission_id}: reached item {tick.reached}/{run.n}")
            )
        if not (tick.started or tick.ending):
            return []
        return self._mission_begun(i, tick, pos_m, Trigger.MISSION_START)

    def guided_rows(self, armed: np.ndarray, link_ok: np.ndarray) -> np.ndarray:
        """Rows the shell should fly with velocity setpoints this tick (read only). One
        vehicle's (an agent's every tick) in Python bools, the same as `_guided_rows`'s
        (tests/test_observe_one_row.py)."""
        if self.n == 1 and self.velocity_mode:
            ok = (
                _GUIDED_ONE[self.mode.item(0)]
                and armed.item(0)
                and link_ok.item(0)
                and not math.isnan(self.targets().item(0, 0))
            )
            return ROW0 if ok else NO_ROWS
        return self._guided_rows(armed, link_ok)

    def _guided_rows(self, armed: np.ndarray, link_ok: np.ndarray) -> np.ndarray:
        """`guided_rows` for any number of rows, as arrays: the reference of its one-row path."""
        if not self.velocity_mode:
            return NO_ROWS
        ok = _GUIDED[self.mode] & armed & link_ok
        if ok.any():  # targets() only when something may fly (not on a landed vehicle's tick)
            ok &= ~np.isnan(self.targets()[:, 0])
        return np.flatnonzero(ok)

    def guide(
        self,
        now_s: float,
        rows: np.ndarray,
        pos_m: np.ndarray,
        vel_m_s: np.ndarray,
        views: NeighbourViews,
        decide: np.ndarray | None = None,
    ) -> GuidanceStep:
        """Velocity setpoints for `rows` (from `guided_rows`); pos/vel/views are those rows'."""
        on_mission = self.mode[rows] == _MISSION
        holding = (self.mode[rows] == int(Mode.HOLDING)) | (self.mission_waiting[rows] & on_mission)
        cap = None
        if on_mission.any():
            cap = np.array(
                [
                    self.missions[r].speed_m_s if m else 0.0
                    for r, m in zip(rows.tolist(), on_mission.tolist(), strict=True)
                ]
            )
            cap = cap if cap.any() else None
        if self.guidance is None:
            raise RuntimeError("guide() flies velocity mode; this core has no guidance")
        out = self.guidance.step(
            now_s,
            rows,
            pos_m,
            vel_m_s,
            self.heading_rad[rows],
            self.targets()[rows],
            holding,
            views,
            decide,
            speed_cap_m_s=cap,
        )
        self.heading_rad[rows] = out.heading_rad
        return out


def heading_towards(pos_m: np.ndarray, goal_m: np.ndarray, fallback_rad: float) -> float:
    d = goal_m[:2] - pos_m[:2]
    if float(np.hypot(*d)) < 1e-6:
        return float(fallback_rad)
    return math.atan2(float(d[1]), float(d[0]))
