"""The state-rate rule (comms/state_rate.py): who is idle, when a state is due, what is refused."""

from __future__ import annotations

import numpy as np
import pytest

from comms.schema import Mode
from comms.state_rate import (
    MAX_IDLE_PERIOD_S,
    StatePacer,
    SteadyConfig,
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


@pytest.mark.parametrize("seed", range(12))
def test_one_row_equals_row_0_of_the_array_path(seed: int) -> None:
    """`StatePacer.due` of one vehicle (on Python floats) says what row 0 of two says, with
    and without the steady rule, over random ticks: idleness coming and going, hovering and
    manoeuvring (near and past the tolerances), mode and arming changes, jitter, repeats;
    seeds 8-11 hover near rest (the hold rate, in and out of HOLD_REST_M_S)."""
    rng = np.random.default_rng(seed)
    steady = None if seed % 4 == 0 else SteadyConfig(state_hz=float(rng.choice([3.0, 5.0])))
    state_hz, tick_hz = float(rng.choice([10.0, 5.0, 3.3])), float(rng.choice([10.0, 20.0]))
    idle_hz = float(rng.choice([1.0, 2.0]))
    one = StatePacer(state_hz, idle_hz, tick_hz, 1, steady)
    two = StatePacer(state_hz, idle_hz, tick_hz, 2, steady)
    now, idle = float(rng.uniform(0.0, 5.0)), bool(rng.random() < 0.5)
    pos, vel, hdg = rng.normal(0.0, 50.0, 3), rng.normal(0.0, 1.0, 3), float(rng.uniform(-4, 4))
    mode, armed = int(Mode.HOLDING), True
    saw = set()
    for _ in range(1500):
        now += float(rng.choice([0.0, 1.0 / tick_hz, rng.uniform(0.0, 0.3)], p=[0.05, 0.8, 0.15]))
        if rng.random() < 0.02:
            idle = not idle
        if rng.random() < 0.02:
            mode = int(rng.choice([Mode.HOLDING, Mode.GOTO, Mode.LANDED]))
        if rng.random() < 0.02:
            armed = not armed
        scale = float(rng.choice([0.0, 0.01, 0.05, 0.3]))  # within the tolerances, or not
        vel = vel + rng.normal(0.0, scale, 3)
        if seed >= 8:  # hovering: pulled back to rest
            vel *= 0.3
        pos = pos + vel / tick_hz + rng.normal(0.0, scale, 3)
        hdg += float(rng.normal(0.0, scale)) + float(rng.choice([0.0, 2 * np.pi]))
        other = rng.normal(0.0, 5.0, (2, 3))
        args = (
            np.array([pos, other[0]]),
            np.array([vel, other[1]]),
            np.array([hdg, 0.3]),
            np.array([mode, int(Mode.GOTO)]),
            np.array([armed, True]),
        )
        if rng.random() < 0.1:
            got = one.due(now, np.array([idle]))
            want = two.due(now, np.array([idle, False]))
        else:
            got = one.due(now, np.array([idle]), *(a[:1] for a in args))
            want = two.due(now, np.array([idle, False]), *args)
        assert got.shape == (1,) and got.dtype == bool
        assert bool(got[0]) == bool(want[0])
        saw.add(bool(got[0]))
        for name in ("last_s", "last_idle", "last_pos", "last_vel", "last_hdg", "last_sig"):
            np.testing.assert_array_equal(getattr(one, name)[0], getattr(two, name)[0])
        if rng.random() < 0.01:
            one.again()
            two.again()
    assert saw == {True, False}


def test_the_array_path_holds_at_rest_like_the_one_row_path() -> None:
    """Two rows at rest, one HOLDING and one in a GOTO: the holder at the hold rate (0.5 Hz), the
    other at the steady rate; row 0 of two equals a pacer of one."""
    two = StatePacer(10.0, 1.0, 10.0, 2, SteadyConfig())
    one = StatePacer(10.0, 1.0, 10.0, 1, SteadyConfig())
    z = np.zeros((2, 3))
    modes = np.array([int(Mode.HOLDING), int(Mode.GOTO)])
    sent = []
    for k in range(60):
        due = two.due(k * 0.1, np.array([False, False]), z, z, np.zeros(2), modes, np.ones(2, bool))
        got = one.due(k * 0.1, np.array([False]), z[:1], z[:1], np.zeros(1), modes[:1], [True])
        assert bool(got[0]) == bool(due[0])
        sent.append(due)
    sent = np.array(sent)
    assert set(np.diff(np.flatnonzero(sent[:, 0])).tolist()) == {20}
    assert set(np.diff(np.flatnonzero(sent[:, 1]))[1:].tolist()) == {3}
