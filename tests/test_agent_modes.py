"""The command state machine, tested with a table over every (mode, command) pair."""

from __future__ import annotations

import pytest

from agent.modes import COMMAND_TRIGGERS, Trigger, step
from comms.schema import CommandKind, Mode

L, TO, H, G, LD, R, K, MI = (
    Mode.LANDED,
    Mode.TAKING_OFF,
    Mode.HOLDING,
    Mode.GOTO,
    Mode.LANDING,
    Mode.RETURNING,
    Mode.KILLED,
    Mode.MISSION,
)
X = None  # rejected

# rows: mode; columns: takeoff, land, goto, hold, return, kill
EXPECTED = {
    L: (TO, L, X, X, X, K),
    TO: (TO, LD, G, H, R, K),
    H: (X, LD, G, H, R, K),
    G: (X, LD, G, H, R, K),
    LD: (TO, LD, G, H, X, K),
    R: (X, LD, G, H, R, K),
    K: (X, X, X, X, X, K),
    MI: (X, LD, G, H, R, K),
}
COLUMNS = (Trigger.TAKEOFF, Trigger.LAND, Trigger.GOTO, Trigger.HOLD, Trigger.RETURN, Trigger.KILL)

# rows: mode; columns: mission start, pause, resume, abort, status (the flight core also
# refuses start without a mission, pause without one flying, resume without a paused one)
MISSION_EXPECTED = {
    L: (X, X, X, L, L),
    TO: (MI, X, X, TO, TO),
    H: (MI, H, MI, H, H),
    G: (MI, X, X, G, G),
    LD: (MI, X, X, LD, LD),
    R: (MI, X, X, R, R),
    K: (X, X, X, K, K),
    MI: (MI, H, MI, H, MI),
}
MISSION_COLUMNS = (
    Trigger.MISSION_START,
    Trigger.MISSION_PAUSE,
    Trigger.MISSION_RESUME,
    Trigger.MISSION_ABORT,
    Trigger.MISSION_STATUS,
)


@pytest.mark.parametrize("mode", list(Mode))
@pytest.mark.parametrize("col", range(len(COLUMNS)))
def test_every_mode_command_pair(mode: Mode, col: int) -> None:
    expected = EXPECTED[mode][col]
    result = step(mode, COLUMNS[col])
    if expected is None:
        assert not result.accepted
        assert result.mode is mode
        assert result.reason  # a rejection always says why
    else:
        assert result.accepted, result.reason
        assert result.mode is expected


@pytest.mark.parametrize("mode", list(Mode))
@pytest.mark.parametrize("col", range(len(MISSION_COLUMNS)))
def test_every_mode_mission_command_pair(mode: Mode, col: int) -> None:
    expected = MISSION_EXPECTED[mode][col]
    result = step(mode, MISSION_COLUMNS[col])
    if expected is None:
        assert not result.accepted and result.mode is mode and result.reason
    else:
        assert result.accepted, result.reason
        assert result.mode is expected


def test_table_covers_every_mode_and_command_kind() -> None:
    assert set(EXPECTED) == set(Mode) == set(MISSION_EXPECTED)
    assert set(COMMAND_TRIGGERS.values()) == set(COLUMNS) | set(MISSION_COLUMNS)
    assert set(COMMAND_TRIGGERS) == set(CommandKind)


@pytest.mark.parametrize(
    ("mode", "trigger", "expected"),
    [
        (TO, Trigger.REACHED_ALTITUDE, H),
        (G, Trigger.ARRIVED, H),
        (R, Trigger.ARRIVED, LD),
        (LD, Trigger.TOUCHED_DOWN, L),
        (G, Trigger.FAILSAFE_HOLD, H),
        (H, Trigger.FAILSAFE_LAND, LD),
        (G, Trigger.FAILSAFE_RETURN, R),
        (K, Trigger.TOUCHED_DOWN, K),
        (MI, Trigger.MISSION_DONE, H),
        (MI, Trigger.FAILSAFE_HOLD, H),
        (MI, Trigger.FAILSAFE_LAND, LD),
        (MI, Trigger.FAILSAFE_RETURN, R),
    ],
)
def test_vehicle_events(mode, trigger, expected) -> None:
    result = step(mode, trigger)
    assert result.accepted and result.mode is expected


def test_goto_while_landed_says_take_off_first() -> None:
    assert "take off first" in step(L, Trigger.GOTO).reason


def test_killed_is_final() -> None:
    assert "restart its agent" in step(K, Trigger.TAKEOFF).reason
    assert "under `covey demo`, stop and start the demo" in step(K, Trigger.TAKEOFF).reason
