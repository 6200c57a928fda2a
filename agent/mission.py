"""Flying a mission: its items in local NED, where the vehicle is in them, and what comes next.

Pure and per vehicle: no clock (every call takes `now_s`), no I/O, no modes. The flight core
(agent/flight_core.py) owns one `MissionRun` per vehicle that has a mission, resolves the
uploaded items to local targets once (`resolve`: global items through the fleet origin, every
target checked as a goto's), moves a waypoint out of a zone's clearance as a goto's goal is moved
(at upload and again at each start), points guidance at `MissionRun.target` while the vehicle is
in MISSION mode, and calls `step` each tick with whether guidance has arrived; `step` says which
item was reached, which one is next and how the mission ends (hold, land or return).

    item k:  fly to its target (guidance, avoidance on)  ->  arrived  ->  wait hold_s  ->  k+1
    TAKEOFF: climb to its altitude where the item starts; HOLD: stay where it starts
    LAND / RETURN: end the mission in that mode; after the last item: hold there

Pause keeps the current item (and what is left of its wait); resume continues it; abort drops
the progress (a start flies from item 1 again).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from comms.geo import GeoOrigin
from comms.schema import Mission, MissionFrame, MissionItemKind

K = MissionItemKind


@dataclass(frozen=True)
class LocalItem:
    """One mission item resolved to the local frame."""

    kind: MissionItemKind
    target_ned_m: tuple[float, float, float] | None = None
    """WAYPOINT: where to fly (NED, down = -altitude above origin); None for the other kinds."""
    alt_m: float = math.nan
    """TAKEOFF: the altitude above the origin to climb to."""
    speed_m_s: float = 0.0
    """Horizontal speed on the way; 0: cruise."""
    hold_s: float = 0.0


class RunStatus(enum.Enum):
    LOADED = "loaded"
    """Uploaded, not started (or aborted: a start flies it from item 1)."""
    ACTIVE = "active"
    PAUSED = "paused"
    DONE = "done"


class Ending(enum.Enum):
    """How a finished mission leaves the vehicle."""

    HOLD = "hold"
    LAND = "land"
    RETURN = "return"


@dataclass(frozen=True)
class MissionTick:
    """What one `step` did."""

    reached: int = 0
    """1-based number of the item reached (its wait begins) this tick; 0: none."""
    started: int = 0
    """1-based number of the item begun this tick; 0: none."""
    ending: Ending | None = None
    """The mission finished this tick, and this is what the vehicle does now."""


def resolve(
    mission: Mission,
    origin: GeoOrigin,
    target_problem: Callable[[np.ndarray], str | None],
    alt_problem: Callable[[float], str | None],
) -> tuple[tuple[LocalItem, ...], str | None]:
    """The mission's items in the local frame, or the first reason to refuse it, named by its
    item's number: a waypoint whose target `target_problem` refuses (the geofence, the fleet
    plan's fence and keep-out zones, altitude limits: the checks a goto gets), a take-off
    altitude `alt_problem` refuses (where it climbs is known only when the item begins)."""
    out: list[LocalItem] = []
    for k, item in enumerate(mission.items, 1):
        if item.kind is K.WAYPOINT:
            if item.frame is MissionFrame.GLOBAL:
                target = np.array(origin.to_local(item.x, item.y, item.alt_m))
            else:
                target = np.array([item.x, item.y, -item.alt_m])
            problem = target_problem(target)
            if problem:
                return (), f"item {k} (waypoint): {problem}"
            out.append(
                LocalItem(
                    K.WAYPOINT,
                    tuple(float(v) for v in target),  # type: ignore[arg-type]
                    speed_m_s=float(item.speed_m_s),
                    hold_s=float(item.hold_s),
                )
            )
        elif item.kind is K.TAKEOFF:
            problem = alt_problem(float(item.alt_m))
            if problem:
                return (), f"item {k} (takeoff): {problem}"
            out.append(LocalItem(K.TAKEOFF, alt_m=float(item.alt_m)))
        else:
            out.append(LocalItem(item.kind, hold_s=float(item.hold_s)))
    return tuple(out), None


class MissionRun:
    """One vehicle's mission and its progress."""

    def __init__(
        self,
        mission_id: int,
        version: int,
        items: tuple[LocalItem, ...],
        asked: tuple[LocalItem, ...] | None = None,
    ) -> None:
        """`items`: as flown; `asked`: as uploaded (default: the same)."""
        if not items:
            raise ValueError("a mission needs at least one item")
        if asked is not None and len(asked) != len(items):
            raise ValueError(f"{len(items)} items flown for {len(asked)} uploaded")
        self.mission_id = mission_id
        self.version = version
        self.items = items
        """The items as flown: the flight core may have moved a waypoint out of a zone's
        clearance (agent/flight_core.py `_clear_items`), within the arrival radius."""
        self.asked = items if asked is None else asked
        """The items as uploaded; each start checks them again (the plan, the position sigma)."""
        self.status = RunStatus.LOADED
        self.index = 0
        """0-based current item (meaningful while ACTIVE or PAUSED)."""
        self.target: np.ndarray | None = None
        """Where guidance flies for the current item (NED)."""
        self.wait_until_s = math.nan
        """End of the current item's wait (NaN: not waiting yet)."""
        self._paused_wait_s = math.nan
        self.by_failsafe = False
        """Paused by a failsafe hold (the core resumes it when the failsafe ends)."""

    # -- reading -----------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.items)

    def progress(self) -> tuple[int, int]:
        """(k, n): the 1-based item flown or paused at, of n; k = 0 before a start or after an
        abort, k = n + 1 once done."""
        if self.status is RunStatus.LOADED:
            return 0, self.n
        if self.status is RunStatus.DONE:
            return self.n + 1, self.n
        return self.index + 1, self.n

    @property
    def speed_m_s(self) -> float:
        """The current item's speed (0: cruise)."""
        if self.status is not RunStatus.ACTIVE:
            return 0.0
        return self.items[self.index].speed_m_s

    def describe(self) -> str:
        k, n = self.progress()
        where = (
            "not started"
            if k == 0
            else "done"
            if k > n
            else f"item {k}/{n} ({self.items[k - 1].kind.name.lower()})"
        )
        return f"mission {self.mission_id} v{self.version}: {where}, {self.status.value}"

    # -- control -----------------------------------------------------------------------------
    def start(self, pos_ned_m: np.ndarray) -> MissionTick:
        """Fly from item 1."""
        self.status = RunStatus.ACTIVE
        self.by_failsafe = False
        return self._begin(0, pos_ned_m)

    def pause(self, now_s: float, by_failsafe: bool = False) -> None:
        if self.status is RunStatus.ACTIVE:
            self.status = RunStatus.PAUSED
            self.by_failsafe = by_failsafe
            self._paused_wait_s = (
                max(0.0, self.wait_until_s - now_s)
                if not math.isnan(self.wait_until_s)
                else math.nan
            )

    def resume(self, now_s: float) -> None:
        if self.status is RunStatus.PAUSED:
            self.status = RunStatus.ACTIVE
            self.by_failsafe = False
            if not math.isnan(self._paused_wait_s):
                self.wait_until_s = now_s + self._paused_wait_s
            self._paused_wait_s = math.nan

    def abort(self) -> None:
        self.status = RunStatus.LOADED
        self.index = 0
        self.target = None
        self.wait_until_s = math.nan
        self.by_failsafe = False

    # -- each tick -----------------------------------------------------------------------------
    def step(self, now_s: float, pos_ned_m: np.ndarray, arrived: bool) -> MissionTick:
        """Advance the current item: `arrived` is guidance's verdict on `target` this tick."""
        if self.status is not RunStatus.ACTIVE:
            return MissionTick()
        item = self.items[self.index]
        reached = 0
        if math.isnan(self.wait_until_s):
            if self.target is not None and not arrived:
                return MissionTick()
            self.wait_until_s = now_s + item.hold_s
            reached = self.index + 1
        if now_s < self.wait_until_s:
            return MissionTick(reached=reached)
        if self.index + 1 >= self.n:
            self.status = RunStatus.DONE
            self.target = None
            return MissionTick(reached=reached, ending=Ending.HOLD)
        nxt = self._begin(self.index + 1, pos_ned_m)
        return MissionTick(reached=reached, started=nxt.started, ending=nxt.ending)

    def _begin(self, index: int, pos_ned_m: np.ndarray) -> MissionTick:
        self.index = index
        self.wait_until_s = math.nan
        item = self.items[index]
        pos = np.asarray(pos_ned_m, float)
        if item.kind in (K.LAND, K.RETURN):
            self.status = RunStatus.DONE
            self.target = None
            return MissionTick(
                started=index + 1, ending=Ending.LAND if item.kind is K.LAND else Ending.RETURN
            )
        if item.kind is K.WAYPOINT:
            self.target = np.array(item.target_ned_m, float)
        elif item.kind is K.TAKEOFF:
            self.target = np.array([pos[0], pos[1], -item.alt_m])
        else:  # HOLD: where it begins
            self.target = pos.copy()
        return MissionTick(started=index + 1)
