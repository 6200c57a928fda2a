"""One summary per cause per period: how a process reports a flood without becoming one.

A refused command, a forged state or a decode error is worth a log line and a SECURITY event,
but an attacker can send a thousand a second. `Summarizer.hit(cause)` says when to report: the
first hit of a cause is reported at once, later ones are counted and reported together once
`period_s` has passed (on the next hit, or by `due()`, which a periodic loop calls so that the
tail of a flood is reported too). Memory is bounded: at most `max_causes` causes are tracked, a
new cause beyond that is folded into "other".
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

OTHER = "other"


@dataclass(frozen=True)
class Report:
    """What to say about one cause: `count` hits over the last `span_s` seconds."""

    cause: str
    count: int
    span_s: float

    def text(self, what: str) -> str:
        if self.count == 1 and self.span_s == 0.0:
            return f"{what}: {self.cause}"
        return f"{what} ×{self.count} in {self.span_s:.1f} s: {self.cause}"


class Summarizer:
    """Thread-safe. `clock_s` is injected (monotonic seconds)."""

    def __init__(self, period_s: float = 1.0, max_causes: int = 64,
                 clock_s: Callable[[], float] = time.monotonic) -> None:  # fmt: skip
        if not period_s > 0 or not max_causes >= 1:
            raise ValueError("period_s must be > 0 and max_causes >= 1")
        self.period_s = period_s
        self.max_causes = max_causes
        self._clock_s = clock_s
        self._lock = threading.Lock()
        self._since: dict[str, float] = {}  # cause -> when its current period started
        self._pending: dict[str, int] = {}  # cause -> hits not reported yet
        self.total = 0
        """Every hit, reported or not."""

    def hit(self, cause: str) -> Report | None:
        """Count one occurrence; a Report when it is time to say something, else None."""
        now = self._clock_s()
        with self._lock:
            self.total += 1
            if cause not in self._since and len(self._since) >= self.max_causes:
                cause = OTHER
            started = self._since.get(cause)
            if started is None:
                self._since[cause] = now
                return Report(cause, 1, 0.0)
            self._pending[cause] = self._pending.get(cause, 0) + 1
            if now - started < self.period_s:
                return None
            return self._report(cause, now)

    def due(self) -> list[Report]:
        """Reports for causes whose period has passed with hits not yet reported."""
        now = self._clock_s()
        with self._lock:
            reports = []
            for cause in [c for c, t in self._since.items() if now - t >= self.period_s]:
                if self._pending.get(cause):
                    reports.append(self._report(cause, now))
                else:  # quiet for a whole period: its next hit is reported at once
                    del self._since[cause]
            return reports

    def _report(self, cause: str, now: float) -> Report:
        count = self._pending.pop(cause, 0)
        span_s = now - self._since[cause]
        self._since[cause] = now
        return Report(cause, count, span_s)
