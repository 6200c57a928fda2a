"""A process's fleet feed: its vehicles' latest states, batched at a bounded rate.

A ground station needs the whole fleet, not every state: at 1,000 vehicles and 10 Hz, receiving
(and, keyed, verifying) every state costs more than a core. So every process keeps the latest
state each of its vehicles published, already encoded and signed, and sends them together on
its feed key (comms/keys.py `feed`) at most `feed_hz` times a second; the station subscribes to
the feeds (Mesh.subscribe_feed). A process of N vehicles then sends one message per feed period
(or a few: a batch holds at most schema.MAX_FEED_BYTES) instead of N per tick.

No thread and no timer: `offer` is called after each state is published, and returns the
batches to send when the feed is due. Each batch carries the latest state of every vehicle that
published since the last one, so no vehicle is left out by timing; a process that stops
publishing stops feeding (`flush` sends what is left when it closes).

Each entry carries a per-vehicle entry number: the station counts the entries it missed from
its gaps (link loss), which the vehicles' own state seq cannot tell once the feed thins states.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import TypeVar

from comms.schema import MAX_FEED_BYTES, FeedBatch, FeedEntry

T = TypeVar("T")

DUE_SLACK = 0.1
"""A batch is due once (1 - DUE_SLACK) of a feed period has passed: a publisher ticking at a
multiple of the feed rate, with jitter, then feeds every k-th tick, not alternately k and k + 1.
The feed's rate is therefore at most feed_hz / (1 - DUE_SLACK)."""


class FeedBuffer:
    """The pending entries of one process's feed. Thread-safe; pure (the caller passes the time
    and puts the batches)."""

    def __init__(self, feed_hz: float) -> None:
        if not 0 < feed_hz <= 1000:
            raise ValueError(f"feed_hz={feed_hz} must be within (0, 1000]")
        self._due_after_ns = int((1.0 - DUE_SLACK) * 1e9 / feed_hz)
        self._lock = threading.Lock()
        self._pending: dict[int, bytes] = {}
        self._entries: dict[int, int] = {}  # vehicle id -> entries sent (this process's own)
        self._last_ns: int | None = None
        self._seq = 0

    def offer(self, vehicle_id: int, state: bytes, now_ns: int) -> list[bytes]:
        """Keep `state` (a VehicleState as published) as the vehicle's latest; return the encoded
        batches to send now (none unless the feed is due)."""
        with self._lock:
            self._pending[vehicle_id] = state
            last = self._last_ns
            # A clock stepped back (now < last) must not stop the feed until it catches up.
            if last is not None and 0 <= now_ns - last < self._due_after_ns:
                return []
            self._last_ns = now_ns
            return self._take()

    def flush(self) -> list[bytes]:
        """Whatever is pending, due or not (the process is closing)."""
        with self._lock:
            return self._take()

    def _take(self) -> list[bytes]:
        """Encode the pending entries into batches of at most MAX_FEED_BYTES (lock held)."""
        pending, self._pending = self._pending, {}
        entries = []
        for vid, state in pending.items():
            n = self._entries[vid] = (self._entries.get(vid, 0) + 1) & 0xFFFFFFFF
            entries.append(FeedEntry(n, state))
        return [self._batch(run) for run in split(entries)]

    def _batch(self, entries: tuple[FeedEntry, ...]) -> bytes:
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        return FeedBatch(self._seq, entries).encode()


def split(entries: list[FeedEntry]) -> list[tuple[FeedEntry, ...]]:
    """`entries`, in order, cut into runs that each fit one FeedBatch (filled greedily)."""
    return runs_within(
        entries, lambda e: len(e.state), FeedBatch.size, MAX_FEED_BYTES, FeedBatch.MAX_ENTRIES
    )


def runs_within(
    items: Sequence[T],
    length: Callable[[T], int],
    size: Callable[[tuple[int, ...]], int],
    max_bytes: int,
    max_items: int | None = None,
) -> list[tuple[T, ...]]:
    """`items`, in order, cut greedily into runs whose message `size(lengths)` stays within
    `max_bytes` (and `max_items`): the feed's batches and the cell relay's (comms/relay.py)."""
    runs: list[tuple[T, ...]] = []
    run: list[T] = []
    lengths: list[int] = []
    for item in items:
        n = length(item)
        full = max_items is not None and len(run) == max_items
        if run and (full or size((*lengths, n)) > max_bytes):
            runs.append(tuple(run))
            run, lengths = [], []
        run.append(item)
        lengths.append(n)
    if run:
        runs.append(tuple(run))
    return runs
