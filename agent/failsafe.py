"""Failsafes: ground station lost, low battery, geofence. Pure logic with injected time.

`Failsafes.evaluate()` is called every guidance tick and returns what should happen; the agent
applies it through the mode machine and publishes each transition as an Event.

- Ground station lost for `gcs_lost_hold_s`: stop and hold; still lost after
  `gcs_lost_land_s`: land. If a station comes back while the vehicle holds, it resumes the goto
  it was flying. "A station" is a verified, fresh heartbeat from a station of the roster
  (trust/heartbeat.py: the shell asks `StationHeartbeats.alive`), never a liveliness token,
  which anyone on the mesh can declare (open mode only: a token counts too). With the failsafe
  on, a take-off without a station is refused (`StationHeartbeats.takeoff_problem`): the
  failsafe would hold the vehicle as soon as it climbed.
- Battery below `low_battery_return_pct`: return home; below `critical_battery_land_pct`: land.
  The battery failsafe re-arms: it acts whenever an airborne vehicle is below a threshold and
  not already doing what the threshold asks (returning or landing; landing), and a vehicle
  below it refuses the commands the failsafe would undo (`FailsafeConfig.battery_refusal`).
- Outside the geofence while flying a goto: hold (the fence also rejects gotos outside it).
The autopilot-link failsafe lives in the autopilot (PX4 has its own); the agent flags it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.modes import AIRBORNE, Trigger
from agent.returning import ReturnConfig
from comms.schema import CommandKind, Mode, StateFlag

FENCE_TIE_M = 1e-9
"""`FailsafeConfig.calm_one` is not calm this near inside the fence's edge (`calm_rows` may be)."""


@dataclass(frozen=True)
class FailsafeConfig:
    """Thresholds of the agent's failsafes."""

    require_gcs: bool = True
    """Hold, then land, when no ground station is on the mesh; refuse take-off without one."""
    gcs_lost_hold_s: float = 5.0
    gcs_lost_land_s: float = 30.0
    low_battery_return_pct: float = 25.0
    """At or below: airborne vehicles return home, and take-off, goto and hold are refused."""
    critical_battery_land_pct: float = 10.0
    """At or below: airborne vehicles land, and only land and kill are accepted."""
    battery_retry_s: float = 5.0
    """A battery failsafe whose mode did not stick (its autopilot action failed) acts again
    after this long, not every tick."""
    geofence_radius_m: float = 500.0
    """Horizontal radius around the fleet origin; 0 switches the fence off."""
    max_alt_m: float = 120.0
    """Highest goto or takeoff altitude above the origin."""
    min_alt_m: float = 1.0
    """Lowest goto altitude above the origin (landing is a command of its own)."""
    returning: ReturnConfig = ReturnConfig()
    """How a vehicle returns, commanded or by a failsafe: its altitude layer and landing order
    (agent/returning.py; default on: layers 4 m apart from 10 m, landing one at a time within
    8 m)."""

    def __post_init__(self) -> None:
        if not 0 < self.gcs_lost_hold_s <= self.gcs_lost_land_s:
            raise ValueError("need 0 < gcs_lost_hold_s <= gcs_lost_land_s")
        if self.geofence_radius_m < 0 or not math.isfinite(self.geofence_radius_m):
            raise ValueError(f"geofence_radius_m must be >= 0, got {self.geofence_radius_m}")
        if not 0 <= self.min_alt_m < self.max_alt_m:
            raise ValueError("need 0 <= min_alt_m < max_alt_m")

    @property
    def battery_acts_pct(self) -> float:
        """At or below: a battery failsafe may act (the higher of its two thresholds)."""
        return max(self.low_battery_return_pct, self.critical_battery_land_pct)

    def battery_refusal(self, kind: CommandKind, battery_pct: float) -> str | None:
        """Why a command is refused at this battery level (what the battery failsafe would
        undo at once), or None. An unknown battery (NaN) refuses nothing."""
        if kind in (CommandKind.LAND, CommandKind.KILL) or not battery_pct <= self.battery_acts_pct:
            return None
        if battery_pct <= self.critical_battery_land_pct:
            return (
                f"battery {battery_pct:.0f} % below the {self.critical_battery_land_pct:g} % "
                "landing threshold: only land and kill are accepted"
            )
        if kind is CommandKind.RETURN:
            return None
        return (
            f"battery {battery_pct:.0f} % below the {self.low_battery_return_pct:g} % return "
            "threshold: only return, land and kill are accepted"
        )

    def check_target(self, target_ned_m: np.ndarray) -> str | None:
        """Why a goto target is refused, or None if it is fine."""
        alt_m = -float(target_ned_m[2])
        if not self.min_alt_m <= alt_m <= self.max_alt_m:
            return f"target altitude {alt_m:.1f} m is outside [{self.min_alt_m:g}, {self.max_alt_m:g}] m"
        if self.geofence_radius_m:
            r_m = float(np.hypot(target_ned_m[0], target_ned_m[1]))
            if r_m > self.geofence_radius_m:
                return f"target is {r_m:.0f} m from the origin, outside the {self.geofence_radius_m:g} m geofence"
        return None

    def inside_fence(self, pos_ned_m: np.ndarray) -> bool:
        return (
            not self.geofence_radius_m
            or float(np.hypot(pos_ned_m[0], pos_ned_m[1])) <= self.geofence_radius_m
        )

    def calm_rows(
        self, gcs_alive: bool, battery_pct: np.ndarray, pos_ned_m: np.ndarray
    ) -> np.ndarray:
        """(N,) True where no failsafe can act this tick whatever the mode, for every vehicle at
        once: a station is there, the battery is above both thresholds, the vehicle is inside
        the fence. For such a vehicle whose `Failsafes.settled`, `Failsafes.evaluate` would only
        note the station (`Failsafes.saw_gcs`). tests/test_agent_failsafe.py checks the shortcut
        against evaluate."""
        if not gcs_alive:
            return np.zeros(len(battery_pct), bool)
        calm = battery_pct > self.battery_acts_pct
        if self.geofence_radius_m:
            calm &= np.hypot(pos_ned_m[:, 0], pos_ned_m[:, 1]) <= self.geofence_radius_m
        return calm

    def calm_one(self, gcs_alive: bool, battery_pct: float, n_m: float, e_m: float) -> bool:
        """`calm_rows` for one vehicle at (`n_m`, `e_m`), in Python floats (an agent's every
        tick). Not calm within FENCE_TIE_M inside the fence's edge, where math.hypot and
        np.hypot may round apart (each within an ulp: 1e-13 m at 500 m): "not calm" only has
        `evaluate` run. tests/test_observe_one_row.py checks it against `calm_rows`."""
        if not (gcs_alive and battery_pct > self.battery_acts_pct):
            return False
        r_m = self.geofence_radius_m
        return not r_m or math.hypot(n_m, e_m) <= r_m - FENCE_TIE_M


@dataclass(frozen=True)
class FailsafeAction:
    trigger: Trigger
    reason: str
    flag: StateFlag


class Failsafes:
    def __init__(self, cfg: FailsafeConfig, now_s: float) -> None:
        self.cfg = cfg
        self._gcs_seen_s = now_s
        self._gcs_failsafe = 0  # 0 none, 1 holding, 2 landing
        self._battery_acted: tuple[Trigger | None, float] = (None, -math.inf)  # what, when
        self._fence_tripped = False
        self.flags = StateFlag.NONE

    @property
    def settled(self) -> bool:
        """No failsafe of this vehicle is active or tripped (see `FailsafeConfig.calm_rows`)."""
        return not self._gcs_failsafe and not self._fence_tripped and not self.flags

    def saw_gcs(self, now_s: float) -> None:
        """What `evaluate` does for a settled vehicle in a calm row: note the station."""
        self._gcs_seen_s = now_s

    def gcs_back(self, now_s: float) -> bool:
        """Record a station's presence; True if this ends a ground-station failsafe hold."""
        self._gcs_seen_s = now_s
        resumed = self._gcs_failsafe == 1
        self._gcs_failsafe = 0
        self.flags &= ~StateFlag.FAILSAFE_GCS_LOST
        return resumed

    def evaluate(
        self, now_s: float, mode: Mode, gcs_alive: bool, battery_pct: float, pos_ned_m: np.ndarray
    ) -> FailsafeAction | None:
        cfg = self.cfg
        if gcs_alive:
            self._gcs_seen_s = now_s
        airborne = mode in AIRBORNE
        if cfg.require_gcs and not gcs_alive and airborne:
            lost_s = now_s - self._gcs_seen_s
            if (
                lost_s >= cfg.gcs_lost_land_s
                and self._gcs_failsafe < 2
                and mode is not Mode.LANDING
            ):
                self._gcs_failsafe = 2
                self.flags |= StateFlag.FAILSAFE_GCS_LOST
                return FailsafeAction(
                    Trigger.FAILSAFE_LAND,
                    f"no ground station for {lost_s:.0f} s: landing",
                    StateFlag.FAILSAFE_GCS_LOST,
                )
            if lost_s >= cfg.gcs_lost_hold_s and self._gcs_failsafe < 1:
                self._gcs_failsafe = 1
                self.flags |= StateFlag.FAILSAFE_GCS_LOST
                if mode in (Mode.GOTO, Mode.RETURNING, Mode.TAKING_OFF, Mode.MISSION):
                    return FailsafeAction(
                        Trigger.FAILSAFE_HOLD,
                        f"no ground station for {lost_s:.0f} s: holding",
                        StateFlag.FAILSAFE_GCS_LOST,
                    )
        # Level-triggered, not once per flight: whenever an airborne vehicle is below a
        # threshold and not already doing what it asks. Once the mode is entered the condition
        # is false, so nothing repeats; a mode that did not stick is retried after a pause.
        if airborne and mode is not Mode.LANDING:
            act = None
            if battery_pct <= cfg.critical_battery_land_pct:
                act = FailsafeAction(
                    Trigger.FAILSAFE_LAND,
                    f"battery critical ({battery_pct:.0f} %): landing",
                    StateFlag.NONE,
                )
            elif battery_pct <= cfg.low_battery_return_pct and mode is not Mode.RETURNING:
                act = FailsafeAction(
                    Trigger.FAILSAFE_RETURN,
                    f"battery low ({battery_pct:.0f} %): returning home",
                    StateFlag.NONE,
                )
            last, when_s = self._battery_acted
            if act is not None and (
                act.trigger is not last or now_s - when_s >= cfg.battery_retry_s
            ):
                self._battery_acted = (act.trigger, now_s)
                return act
        inside = self.cfg.inside_fence(pos_ned_m)
        if inside:
            self._fence_tripped = False
            self.flags &= ~StateFlag.GEOFENCE
        elif mode in (Mode.GOTO, Mode.MISSION) and not self._fence_tripped:
            self._fence_tripped = True
            self.flags |= StateFlag.GEOFENCE
            return FailsafeAction(
                Trigger.FAILSAFE_HOLD, "left the geofence: holding", StateFlag.GEOFENCE
            )
        return None

    @property
    def gcs_failsafe_active(self) -> bool:
        return self._gcs_failsafe > 0
