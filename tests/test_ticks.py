"""kit.ticks.run_ticks: the one fixed-rate loop (agent, host, ground station), on an
injected clock."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from kit.ticks import next_due_s, run_ticks


class FakeTime:
    """A clock and a stop event in one: waiting moves the clock; stops after `ticks` ticks."""

    def __init__(self, ticks: int) -> None:
        self.now_s, self.left = 0.0, ticks

    def clock_s(self) -> float:
        return self.now_s

    def is_set(self) -> bool:
        return self.left <= 0

    def wait(self, timeout_s: float) -> bool:
        self.now_s += timeout_s
        return self.is_set()


def _run(work_s, ticks: int, rate_hz: float = 10.0, fail=lambda k: False):
    t = FakeTime(ticks)
    starts: list[float] = []
    overruns = [0]

    def tick(now_s: float) -> None:
        k = len(starts)
        starts.append(now_s)
        t.left -= 1
        t.now_s += work_s(k)
        if fail(k):
            raise RuntimeError(f"tick {k} broke")

    run_ticks(tick, rate_hz, t.clock_s, t, lambda: overruns.__setitem__(0, overruns[0] + 1))
    return np.array(starts), overruns[0]


def test_the_next_tick_is_due_one_period_on_unless_a_whole_period_behind() -> None:
    assert next_due_s(1.0, 1.02, 0.1) == pytest.approx(1.1)  # on time: one period on
    assert next_due_s(1.0, 1.15, 0.1) == pytest.approx(1.1)  # late: due at once, kept
    assert next_due_s(1.0, 1.25, 0.1) == pytest.approx(1.25)  # a tick behind: dropped


def test_on_time_ticks_keep_the_period() -> None:
    starts, overruns = _run(lambda k: 0.02, 50)
    assert np.allclose(np.diff(starts), 0.1) and overruns == 0


def test_late_ticks_cost_no_tick_and_are_counted() -> None:
    # every 7th tick takes 150 ms (a busy machine), the rest 15 ms: still 100 ticks in 10 s
    starts, overruns = _run(lambda k: 0.15 if k % 7 == 6 else 0.015, 100)
    assert starts[-1] < 9.95, starts[-1]
    assert overruns == len([k for k in range(100) if k % 7 == 6])


def test_a_stall_drops_the_missed_ticks_instead_of_a_burst() -> None:
    starts, overruns = _run(lambda k: 0.45 if k == 20 else 0.015, 40)
    after = starts[starts > starts[20]]
    assert after[0] == pytest.approx(starts[20] + 0.45)  # the next tick at once, then the period
    assert np.diff(after).min() >= 0.1 - 1e-9, np.diff(after)
    assert overruns == 1


def test_a_failing_tick_is_logged_and_the_loop_goes_on(caplog) -> None:
    with caplog.at_level(logging.ERROR, logger="kit.ticks"):
        starts, _ = _run(lambda k: 0.01, 10, fail=lambda k: k == 3)
    assert len(starts) == 10
    assert "tick failed" in caplog.text and "tick 3 broke" in caplog.text
