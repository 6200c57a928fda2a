"""The state-rate rule (comms/state_rate.py): who is idle, when a state is due, what is refused."""

from __future__ import annotations

import numpy as np
import pytest

from comms.schema import Mode
from comms.state_rate import (
    MAX_IDLE_PERIOD_S,
    StatePacer,
    announces_idle,
    check_rates,
    idle_rows,
)


@pytest.mark.parametrize(
    ("mode", "armed", "in_air", "busy", "idle"),
    [
        (Mode.LANDED, False, False, False, True),
        (Mode.KILLED, False, False, False, True),
        (Mode.LANDED, True, False, False, False),  # armed: a take-off may be under way
        (Mode.LANDED, False, True, False, False),  # in the air, whatever the mode says
        (Mode.LANDED, False, False, True, False),  # an autopilot action waits or runs
        (Mode.KILLED, False, True, False, False),  # still falling
        (Mode.TAKING_OFF, False, False, False, False),  # a take-off accepted, not yet armed
        (Mode.HOLDING, True, True, False, False),
        (Mode.LANDING, True, False, False, False),
    ],
)
def test_idle_is_landed_or_killed_disarmed_on_the_ground_with_nothing_under_way(
    mode, armed, in_air, busy, idle
) -> None:
    assert bool(idle_rows(mode, armed, in_air, busy)[0]) is idle
    # what a receiver reads from the state (no in_air, no actions) never says less
    if idle:
        assert announces_idle(mode, armed)


def test_idle_rows_takes_arrays_and_agrees_with_the_scalar_rule() -> None:
    rng = np.random.default_rng(3)
    modes = rng.choice([int(m) for m in Mode], 200)
    armed, in_air, busy = (rng.random(200) < 0.3 for _ in range(3))
    rows = idle_rows(modes, armed, in_air, busy)
    for i in range(200):
        assert rows[i] == idle_rows(Mode(modes[i]), armed[i], in_air[i], busy[i])[0]


def test_an_idle_row_publishes_at_the_idle_rate_and_a_change_of_idleness_at_once() -> None:
    pacer = StatePacer(state_hz=10.0, idle_state_hz=1.0, tick_hz=10.0, n=2)
    idle = np.array([True, False])
    sent = np.zeros(2, int)
    first = None
    for k in range(30):  # 3 s: row 0 at 1 Hz, row 1 at 10 Hz
        due = pacer.due(0.1 * k, idle)
        sent += due
        if first is None:
            first = due.copy()
    assert first.all(), "every row publishes on its first tick"
    assert sent.tolist() == [3, 30]
    # the tick after a command wakes row 0 (and row 1 lands): both publish at once
    idle = np.array([False, True])
    assert pacer.due(3.0, idle).tolist() == [True, True]
    assert pacer.due(3.1, idle).tolist() == [True, False]
    assert pacer.due(3.9, idle).tolist() == [True, False]
    assert pacer.due(4.0, idle).tolist() == [True, True]  # one idle period after it landed


def test_jitter_does_not_skip_states_and_again_forces_one() -> None:
    pacer = StatePacer(10.0, 1.0, 10.0)
    assert pacer.due(0.0, [False])[0]
    assert pacer.due(0.096, [False])[0]  # a tick 4 ms early still publishes
    assert not pacer.due(0.096, [False])[0]
    pacer.again()
    assert pacer.due(0.096, [False])[0]


def test_the_idle_rate_is_capped_to_the_state_rate_and_the_floor_is_refused() -> None:
    slow = StatePacer(state_hz=0.5, idle_state_hz=1.0, tick_hz=10.0)
    assert slow.idle_period_s == slow.period_s == 2.0  # idle never says more than flying
    with pytest.raises(ValueError, match="idle_state_hz must be within"):
        check_rates(10.0, 0.5 / MAX_IDLE_PERIOD_S)
    with pytest.raises(ValueError, match="idle_state_hz"):
        check_rates(10.0, float("nan"))
    with pytest.raises(ValueError, match="state_hz must be within"):
        check_rates(0.0, 1.0)
    with pytest.raises(ValueError, match="tick_hz"):
        StatePacer(10.0, 1.0, 0.0)
