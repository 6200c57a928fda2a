"""Fixed-rate loops: the one schedule of an agent's and a host's ticks and of the ground
station's frames.

A tick that ends late by less than a period costs nothing: the next one is due at once and the
loop keeps its rate. One that ends more than a whole period behind drops the ticks it missed
(the next one is due now) instead of catching up with a burst.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


def next_due_s(last_due_s: float, now_s: float, period_s: float) -> float:
    """When the next tick is due, after the tick due at `last_due_s` ended at `now_s`: one
    period later, unless that is more than a whole period behind `now_s` (then now)."""
    due_s = last_due_s + period_s
    return due_s if due_s >= now_s - period_s else now_s


def run_ticks(
    tick: Callable[[float], None],
    rate_hz: float,
    clock_s: Callable[[], float],
    stop: threading.Event,
    on_overrun: Callable[[], None] | None = None,
    what: str = "tick",
    *,
    idle_hz: float | None = None,
    idle: Callable[[], bool] | None = None,
    wake: threading.Event | None = None,
    calm_every: int = 1,
    calm: Callable[[], bool] | None = None,
    calm_periods: Callable[[], int] | None = None,
) -> None:
    """Call `tick(now_s)` at `rate_hz` until `stop` is set, on the schedule of `next_due_s`;
    `on_overrun` is called for each tick that ended after the next one was due. A failing tick
    is logged (as `what` failed) and the loop goes on: keep flying, keep showing.

    While `idle()` says so after a tick, the next one is due at `idle_hz` instead (a landed
    vehicle waiting), unless `wake` is set first (a command came): then it runs at once. The
    caller sets `wake` when `stop` is set too (a resting loop waits on `wake` alone). A busy
    loop keeps its period whatever rings (its ticks stay evenly spaced: guidance traces
    replay them).

    While `calm()` says so after a tick (and the loop does not rest), the next one is due
    `calm_every` periods later (or `calm_periods()`, when given: a longer tier, a vehicle
    holding at rest), on the same grid (a vehicle with nothing near: agent/calm.py); `wake`
    rung meanwhile brings the next tick of the grid."""
    period_s = 1.0 / rate_hz
    idle_period_s = 1.0 / idle_hz if idle_hz else period_s
    due_s = clock_s()
    while not stop.is_set():
        try:
            tick(clock_s())
        except Exception:  # noqa: BLE001 - the log has the traceback
            log.exception("%s failed", what)
        now_s = clock_s()
        if on_overrun is not None and now_s > due_s + period_s:
            on_overrun()
        resting = wake is not None and idle is not None and idle_period_s > period_s and idle()
        calm_now = (
            not resting and wake is not None and calm is not None and calm_every > 1 and calm()
        )
        last_due_s = due_s
        every = max(1, calm_periods()) if calm_now and calm_periods is not None else calm_every
        step_s = idle_period_s if resting else period_s * (every if calm_now else 1)
        due_s = next_due_s(due_s, now_s, step_s)
        if calm_now:
            assert wake is not None
            if wake.wait(max(0.0, due_s - now_s)):
                wake.clear()
                rung_s = clock_s()  # rung: the next tick of the grid
                periods = max(1, math.ceil((rung_s - last_due_s) / period_s))
                due_s = min(due_s, last_due_s + periods * period_s)
                stop.wait(max(0.0, due_s - rung_s))
        elif not resting:
            if wake is not None:
                wake.clear()  # what rang is answered by the next tick, due anyway
            stop.wait(max(0.0, due_s - now_s))
        elif wake is not None and wake.wait(max(0.0, due_s - now_s)):
            wake.clear()
            due_s = min(due_s, clock_s())  # rung: tick now
