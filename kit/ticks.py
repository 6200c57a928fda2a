"""Fixed-rate loops: the one schedule of an agent's and a host's ticks and of the ground
station's frames.

A tick that ends late by less than a period costs nothing: the next one is due at once and the
loop keeps its rate. One that ends more than a whole period behind drops the ticks it missed
(the next one is due now) instead of catching up with a burst.
"""

from __future__ import annotations

import logging
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
) -> None:
    """Call `tick(now_s)` at `rate_hz` until `stop` is set, on the schedule of `next_due_s`;
    `on_overrun` is called for each tick that ended after the next one was due. A failing tick
    is logged (as `what` failed) and the loop goes on: keep flying, keep showing."""
    period_s = 1.0 / rate_hz
    due_s = clock_s()
    while not stop.is_set():
        try:
            tick(clock_s())
        except Exception:  # noqa: BLE001 - the log has the traceback
            log.exception("%s failed", what)
        now_s = clock_s()
        if on_overrun is not None and now_s > due_s + period_s:
            on_overrun()
        due_s = next_due_s(due_s, now_s, period_s)
        stop.wait(max(0.0, due_s - now_s))
