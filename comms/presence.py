"""Presence: which vehicles and ground stations are alive, from Zenoh liveliness tokens.

A killed process's token disappears within milliseconds (its TCP link drops); a hung process's
disappears after the transport lease (MeshConfig.lease_ms).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import zenoh

from comms import keys

log = logging.getLogger(__name__)


class Presence:
    """Live sets of vehicle ids and ground-station ids, updated from liveliness samples."""

    def __init__(
        self,
        fleet: str,
        on_change: Callable[[str, int, bool], None] | None = None,
        clock_ns: Callable[[], int] | None = None,
    ) -> None:
        self.fleet = fleet
        self._on_change = on_change
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._vehicles: dict[int, int] = {}
        self._gcs: dict[int, int] = {}
        self._changed = threading.Condition(self._lock)

    @property
    def vehicles(self) -> set[int]:
        with self._lock:
            return set(self._vehicles)

    @property
    def ground_stations(self) -> set[int]:
        with self._lock:
            return set(self._gcs)

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        alive = sample.kind == zenoh.SampleKind.PUT
        stamp = self._clock_ns() if self._clock_ns else 0
        parsed_v = keys.parse_vehicle_key(key)
        if parsed_v and parsed_v[0] == self.fleet and parsed_v[2] == "alive":
            kind, ident, table = "vehicle", parsed_v[1], self._vehicles
        else:
            parsed_g = keys.parse_gcs_key(key)
            if not parsed_g or parsed_g[0] != self.fleet:
                log.warning("ignoring liveliness on unexpected key %s", key)
                return
            kind, ident, table = "gcs", parsed_g[1], self._gcs
        with self._changed:
            was = ident in table
            if alive:
                table[ident] = stamp
            else:
                table.pop(ident, None)
            self._changed.notify_all()
        if was != alive and self._on_change is not None:
            try:
                self._on_change(kind, ident, alive)
            except Exception:  # noqa: BLE001 - a callback bug must not kill Zenoh's thread
                log.exception("presence callback failed")

    def wait_for(self, predicate: Callable[[set[int], set[int]], bool], timeout_s: float) -> bool:
        """Block until predicate(vehicles, ground_stations) holds, or the timeout passes."""
        with self._changed:
            return self._changed.wait_for(
                lambda: predicate(set(self._vehicles), set(self._gcs)), timeout=timeout_s
            )
