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


class Doorbell:
    """A wake event on the fake clock: rings (returns True, time moved to the ring) when a
    ring is due before the timeout; `clear` as threading.Event."""

    def __init__(self, t: FakeTime, rings_s: list[float]) -> None:
        self.t, self.rings_s, self.rung = t, sorted(rings_s), False

    def wait(self, timeout_s: float) -> bool:
        end_s = self.t.now_s + timeout_s
        if self.rings_s and self.rings_s[0] <= end_s:
            self.t.now_s = max(self.t.now_s, self.rings_s.pop(0))
            self.rung = True
            return True
        self.t.now_s = end_s
        return self.t.is_set()

    def clear(self) -> None:
        self.rung = False


def _run_resting(ticks: int, idle_until_s: float, rings_s: list[float], calm_until_s: float = 0.0):
    """Ticks at 10 Hz, resting at 2 Hz while the clock is before `idle_until_s`, calm (every
    3rd tick) while it is before `calm_until_s`."""
    t = FakeTime(ticks)
    starts: list[float] = []
    bell = Doorbell(t, rings_s)

    def tick(now_s: float) -> None:
        starts.append(now_s)
        t.left -= 1
        t.now_s += 0.005

    run_ticks(
        tick,
        10.0,
        t.clock_s,
        t,
        idle_hz=2.0,
        idle=lambda: t.now_s < idle_until_s,
        wake=bell,  # type: ignore[arg-type]
        calm_every=3,
        calm=lambda: t.now_s < calm_until_s,
    )
    return np.array(starts)


def test_an_idle_loop_rests_at_the_idle_rate_and_comes_back() -> None:
    starts = _run_resting(30, idle_until_s=5.0, rings_s=[])
    gaps = np.diff(starts)
    assert np.allclose(gaps[starts[:-1] < 4.5], 0.5)  # resting: 2 Hz
    assert np.allclose(gaps[starts[:-1] > 5.0], 0.1)  # busy again: 10 Hz


def test_a_ring_ticks_at_once_while_resting() -> None:
    # idle throughout; a command at 1.23 s: its tick runs then, not at the next 0.5 s slot
    starts = _run_resting(6, idle_until_s=100.0, rings_s=[1.23])
    assert 1.23 in [round(s, 6) for s in starts], starts
    assert np.diff(starts).min() > 0.2  # no burst after the ring: resting again


def test_a_calm_loop_ticks_every_third_period_on_the_grid_and_comes_back() -> None:
    starts = _run_resting(30, idle_until_s=0.0, rings_s=[], calm_until_s=3.0)
    gaps = np.diff(starts)
    assert np.allclose(gaps[starts[:-1] < 2.9], 0.3)  # calm: 3.3 Hz
    assert np.allclose(gaps[starts[:-1] > 3.0], 0.1)  # busy again: 10 Hz
    # every tick on the 10 Hz grid of the first one
    assert np.allclose((starts - starts[0]) * 10, np.round((starts - starts[0]) * 10))


def test_a_ring_while_calm_brings_the_next_tick_of_the_grid() -> None:
    # calm throughout; a command at 0.63 s: its tick runs at 0.7 s (the grid), not at 0.9 s
    starts = _run_resting(6, idle_until_s=0.0, rings_s=[0.63], calm_until_s=100.0)
    assert np.allclose(starts, [0.0, 0.3, 0.6, 0.7, 1.0, 1.3]), starts  # calm again from there
