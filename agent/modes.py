"""The agent's command state machine: an enum (comms.schema.Mode), a table of allowed
transitions, and a pure `step(mode, trigger)`.

    LANDED -> TAKING_OFF -> HOLDING <-> GOTO -> LANDING -> LANDED, plus RETURNING
    MISSION (an uploaded mission's items, agent/mission.py): entered by mission start (or
    resume of a paused one) from any airborne mode; pause and abort hold in place, and every
    command and failsafe leaves it as it leaves a goto. Mission status changes nothing anywhere.
    KILL is allowed from every state and is final for this agent process: a killed vehicle
    needs a person to look at it before it flies again (restart its agent).

Commands that make no sense in a mode are rejected with the reason in the ack (e.g. goto while
landed). Repeating the current mode's command (hold while holding, land while landing or
landed) is accepted and changes nothing, so that fleet-wide commands don't fail on vehicles
that are already there.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from comms.schema import CommandKind, Mode


class Trigger(enum.Enum):
    """Everything that can move the state machine: ground-station commands and vehicle events."""

    TAKEOFF = "takeoff"
    LAND = "land"
    GOTO = "goto"
    HOLD = "hold"
    RETURN = "return"
    KILL = "kill"
    MISSION_START = "mission start"
    MISSION_PAUSE = "mission pause"
    MISSION_RESUME = "mission resume"
    MISSION_ABORT = "mission abort"
    MISSION_STATUS = "mission status"
    # Vehicle events (not from the ground station):
    REACHED_ALTITUDE = "reached_altitude"
    ARRIVED = "arrived"
    TOUCHED_DOWN = "touched_down"
    FAILSAFE_HOLD = "failsafe_hold"
    FAILSAFE_LAND = "failsafe_land"
    FAILSAFE_RETURN = "failsafe_return"
    MISSION_DONE = "mission_done"
    """The mission's last item is done (a land or return item ends it in that mode instead)."""


COMMAND_TRIGGERS: dict[CommandKind, Trigger] = {
    CommandKind.TAKEOFF: Trigger.TAKEOFF,
    CommandKind.LAND: Trigger.LAND,
    CommandKind.GOTO_LOCAL: Trigger.GOTO,
    CommandKind.GOTO_GLOBAL: Trigger.GOTO,
    CommandKind.HOLD: Trigger.HOLD,
    CommandKind.RETURN: Trigger.RETURN,
    CommandKind.KILL: Trigger.KILL,
    CommandKind.MISSION_START: Trigger.MISSION_START,
    CommandKind.MISSION_PAUSE: Trigger.MISSION_PAUSE,
    CommandKind.MISSION_RESUME: Trigger.MISSION_RESUME,
    CommandKind.MISSION_ABORT: Trigger.MISSION_ABORT,
    CommandKind.MISSION_STATUS: Trigger.MISSION_STATUS,
}

M, T = Mode, Trigger
AIRBORNE = frozenset({M.TAKING_OFF, M.HOLDING, M.GOTO, M.LANDING, M.RETURNING, M.MISSION})

# (mode, trigger) -> next mode. Anything missing is rejected (see REJECT_REASONS).
TRANSITIONS: dict[tuple[Mode, Trigger], Mode] = {
    (M.LANDED, T.TAKEOFF): M.TAKING_OFF,
    (M.LANDED, T.LAND): M.LANDED,
    (M.TAKING_OFF, T.TAKEOFF): M.TAKING_OFF,
    (M.TAKING_OFF, T.REACHED_ALTITUDE): M.HOLDING,
    (M.TAKING_OFF, T.HOLD): M.HOLDING,
    (M.TAKING_OFF, T.GOTO): M.GOTO,
    (M.TAKING_OFF, T.LAND): M.LANDING,
    (M.TAKING_OFF, T.RETURN): M.RETURNING,
    (M.HOLDING, T.HOLD): M.HOLDING,
    (M.HOLDING, T.GOTO): M.GOTO,
    (M.HOLDING, T.LAND): M.LANDING,
    (M.HOLDING, T.RETURN): M.RETURNING,
    (M.GOTO, T.GOTO): M.GOTO,
    (M.GOTO, T.ARRIVED): M.HOLDING,
    (M.GOTO, T.HOLD): M.HOLDING,
    (M.GOTO, T.LAND): M.LANDING,
    (M.GOTO, T.RETURN): M.RETURNING,
    (M.RETURNING, T.RETURN): M.RETURNING,
    (M.RETURNING, T.ARRIVED): M.LANDING,
    (M.RETURNING, T.HOLD): M.HOLDING,
    (M.RETURNING, T.GOTO): M.GOTO,
    (M.RETURNING, T.LAND): M.LANDING,
    (M.LANDING, T.LAND): M.LANDING,
    (M.LANDING, T.TOUCHED_DOWN): M.LANDED,
    (M.LANDING, T.HOLD): M.HOLDING,
    (M.LANDING, T.GOTO): M.GOTO,
    (M.LANDING, T.TAKEOFF): M.TAKING_OFF,
    (M.MISSION, T.HOLD): M.HOLDING,
    (M.MISSION, T.GOTO): M.GOTO,
    (M.MISSION, T.LAND): M.LANDING,
    (M.MISSION, T.RETURN): M.RETURNING,
    (M.MISSION, T.MISSION_PAUSE): M.HOLDING,
    (M.MISSION, T.MISSION_RESUME): M.MISSION,
    (M.MISSION, T.MISSION_DONE): M.HOLDING,
    (M.HOLDING, T.MISSION_PAUSE): M.HOLDING,
    (M.HOLDING, T.MISSION_RESUME): M.MISSION,
}
# Start (again, from item 1) from any airborne mode; the flight core refuses it without a mission.
for _mode in AIRBORNE:
    TRANSITIONS[(_mode, T.MISSION_START)] = M.MISSION
# Abort holds a vehicle flying a mission and changes nothing elsewhere (a fleet-wide abort must
# not stop a return or a landing); status changes nothing anywhere.
for _mode in Mode:
    TRANSITIONS[(_mode, T.MISSION_ABORT)] = M.HOLDING if _mode is M.MISSION else _mode
    TRANSITIONS[(_mode, T.MISSION_STATUS)] = _mode
for _mode in Mode:
    if _mode is not M.KILLED:
        TRANSITIONS[(_mode, T.KILL)] = M.KILLED
for _mode in (M.TAKING_OFF, M.GOTO, M.RETURNING, M.MISSION):
    TRANSITIONS[(_mode, T.FAILSAFE_HOLD)] = M.HOLDING
for _mode in AIRBORNE - {M.LANDING}:
    TRANSITIONS[(_mode, T.FAILSAFE_LAND)] = M.LANDING
for _mode in (M.TAKING_OFF, M.HOLDING, M.GOTO, M.MISSION):
    TRANSITIONS[(_mode, T.FAILSAFE_RETURN)] = M.RETURNING
TRANSITIONS[(M.KILLED, T.KILL)] = M.KILLED  # killing twice is harmless
TRANSITIONS[(M.KILLED, T.TOUCHED_DOWN)] = M.KILLED


def _reason(mode: Mode, trigger: Trigger) -> str:
    if mode is M.KILLED:
        return (
            "vehicle was killed; inspect it and restart its agent before flying again "
            "(its `covey agent` process; under `covey demo`, stop and start the demo)"
        )
    if mode is M.LANDED:
        return f"{trigger.value} needs the vehicle airborne; it is landed (take off first)"
    if trigger is T.TAKEOFF:
        return f"already airborne ({mode.name.lower()}); use goto to change altitude"
    return f"{trigger.value} is not allowed while {mode.name.lower()}"


@dataclass(frozen=True)
class StepResult:
    accepted: bool
    mode: Mode
    reason: str = ""


def step(mode: Mode, trigger: Trigger) -> StepResult:
    """The next mode for `trigger` in `mode`, or a rejection with its reason. Pure."""
    nxt = TRANSITIONS.get((mode, trigger))
    if nxt is None:
        return StepResult(False, mode, _reason(mode, trigger))
    return StepResult(True, nxt)
