"""Fleet events as the station keeps and shows them: one bounded buffer per kind, and a filtered
view per browser tab.

One buffer per event kind means a flood of one kind (refused commands' SECURITY events, say)
can only push out older events of that kind: a mode change or a failsafe during the flood still
reaches every operator. Each tab filters by kind and by lowest severity for itself.
"""

from __future__ import annotations

import heapq
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import viser

from comms.schema import EventKind, EventMessage, Severity
from groundstation.tables import event_log

ALL_KINDS = "all kinds"


@dataclass(frozen=True)
class EventsConfig:
    """How many events the station keeps and shows."""

    per_kind: int = 50
    """Newest events kept for each kind."""
    shown: int = 12
    """Lines shown in a tab's event panel."""

    def __post_init__(self) -> None:
        if not 1 <= self.per_kind <= 10_000 or not 1 <= self.shown <= 1_000:
            raise ValueError("per_kind must be within 1..10000 and shown within 1..1000")


class EventBuffer:
    """Thread-safe: Zenoh threads add, the render thread reads."""

    def __init__(
        self,
        cfg: EventsConfig | None = None,
        clock_text: Callable[[], str] = lambda: time.strftime("%H:%M:%S"),
    ) -> None:
        self.cfg = cfg or EventsConfig()
        self._clock_text = clock_text
        self._lock = threading.Lock()
        self._by_kind: dict[EventKind, deque[tuple[int, str, EventMessage]]] = {
            kind: deque(maxlen=self.cfg.per_kind) for kind in EventKind
        }
        self._n = 0
        self.version = 0
        """Bumped on every event (a view redraws only when it moved)."""

    def add(self, event: EventMessage, _recv_ns: int = 0) -> None:
        """An event, or an autopilot outcome (kept and shown with the ACTION kind)."""
        with self._lock:
            self._n += 1
            self._by_kind[event.kind].append((self._n, self._clock_text(), event))
            self.version += 1

    def latest(
        self,
        kind: EventKind | None = None,
        min_severity: Severity = Severity.DEBUG,
        n: int | None = None,
    ) -> list[tuple[str, EventMessage]]:
        """The newest `n` events of `kind` (None: any) at `min_severity` or above, oldest first.
        Across all kinds, each kind fills at most a third of the lines, so a flood of one kind
        cannot push a rarer one (a mode change, a failsafe) off the panel."""
        n = self.cfg.shown if n is None else n
        per_kind = n if kind is not None else max(2, n // 3)
        with self._lock:
            kinds = [self._by_kind[kind]] if kind is not None else list(self._by_kind.values())
            rows = [
                r
                for q in kinds
                for r in heapq.nlargest(per_kind, (r for r in q if r[2].severity >= min_severity))
            ]
        newest = heapq.nlargest(n, rows, key=lambda r: r[0])
        return [(when, ev) for _, when, ev in reversed(newest)]


class EventsView:
    """One tab's event panel with its own filters."""

    def __init__(
        self,
        gui: viser.GuiApi,
        buffer: EventBuffer,
        name_command: Callable[[int], str | None] | None = None,
        order: float | None = None,
    ) -> None:
        """`name_command`: nonce -> the command as the command log names it (autopilot outcomes
        name their command, not its nonce). `order`: where the panel goes (viser GUI order)."""
        self.buffer = buffer
        self._name_command = name_command
        self._shown = (-1, "", "")
        with gui.add_folder("Events", expand_by_default=True, order=order):
            self.kind = gui.add_dropdown(
                "Event kind",
                (ALL_KINDS, *(k.name.lower() for k in EventKind)),
                initial_value=ALL_KINDS,
            )
            self.severity = gui.add_dropdown(
                "Min severity", tuple(s.name.lower() for s in Severity), initial_value="debug"
            )
            self.html = gui.add_html(event_log([]))

    def render(self) -> None:
        """Redraw if an event arrived or a filter changed since the last call."""
        key = (self.buffer.version, self.kind.value, self.severity.value)
        if key == self._shown:
            return
        self._shown = key
        kind = None if self.kind.value == ALL_KINDS else EventKind[self.kind.value.upper()]
        events = self.buffer.latest(kind, Severity[self.severity.value.upper()])
        self.html.content = event_log(events, self._name_command)
