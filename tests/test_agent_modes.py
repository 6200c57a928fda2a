"""The command state machine, tested with a table over every (mode, command) pair."""

from __future__ import annotations

import pytest

from agent.modes import COMMAND_TRIGGERS, Trigger, step
from comms.schema import CommandKind, Mode

L, TO, H, G, LD, R, K = (
    Mode.LANDED,
    Mode.TAKING_OFF,
    Mode.HOLDING,
    Mode.GOTO,
    Mode.LANDING,
    Mode.RETURNING,
    Mode.KILLED,
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
}
COLUMNS = (Trigger.TAKEOFF, Trigger.LAND, Trigger.GOTO, Trigger.HOLD, Trigger.RETURN, Trigger.KILL)


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


def test_table_covers_every_mode_and_command_kind() -> None:
    assert set(EXPECTED) == set(Mode)
    assert set(COMMAND_TRIGGERS.values()) == set(COLUMNS)
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
