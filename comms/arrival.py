"""When a polled state arrived: its sender's stamp plus the smallest lag seen from that sender.

A state taken from a subscriber's queue at a tick (`CellSubscription.drain`) arrived some time
since the previous take. Its receive time feeds the neighbour table's dead reckoning
(p(t) = p + v (t - t_rx)), so taking "now" would make every state look up to a tick fresher
than it is. The lag `taken - stamp` of each state is transit, the two clocks' offset and its
wait in the queue; its minimum over the last `window_s` from one sender is transit plus offset
(some state is taken just after it came), so `stamp + min lag` estimates its arrival. The
estimate is clamped into [the previous take, this take]; a caller that counts only the states it
trusts (`note` after the checks, `estimate_ns` before) is not misled by forged stamps at all.
"""

from __future__ import annotations

import math


class ArrivalEstimate:
    """Per sender: the least lag `taken_ns - stamp_ns` seen in the last `window_s`."""

    def __init__(self, window_s: float = 10.0, max_senders: int = 4096) -> None:
        if not (math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"window_s must be a positive number of seconds, got {window_s}")
        self._window_ns = int(window_s * 1e9)
        self._max_senders = max_senders
        self._least: dict[int, tuple[int, int]] = {}  # sender -> (least lag, when it was seen)

    def arrived_ns(self, sender: int, stamp_ns: int, taken_ns: int, since_ns: int) -> int:
        """When the state of `sender` stamped `stamp_ns`, taken at `taken_ns` from a queue last
        emptied at `since_ns`, most likely arrived."""
        self.note(sender, taken_ns - stamp_ns, taken_ns)
        return self.estimate_ns(sender, stamp_ns, taken_ns, since_ns)

    def estimate_ns(self, sender: int, stamp_ns: int, taken_ns: int, since_ns: int) -> int:
        """As `arrived_ns`, from the lags counted so far only (this one not counted: a caller
        that counts only the states it trusts, `note`, is not misled by the others)."""
        return estimated_ns(self.least_ns(sender), stamp_ns, taken_ns, since_ns)

    def note(self, sender: int, lag_ns: int, taken_ns: int) -> int:
        """Count a lag of `sender`'s seen at `taken_ns`; returns its least lag now."""
        least = self._least.get(sender)
        if least is None or lag_ns <= least[0] or taken_ns - least[1] > self._window_ns:
            if least is None and len(self._least) >= self._max_senders:
                self._forget_old(taken_ns)
            least = self._least[sender] = (lag_ns, taken_ns)
        return least[0]

    def least_ns(self, sender: int) -> int | None:
        """`sender`'s least lag in the window, None if none was counted."""
        least = self._least.get(sender)
        return None if least is None else least[0]

    def _forget_old(self, now_ns: int) -> None:
        old = [s for s, (_, seen) in self._least.items() if now_ns - seen > self._window_ns]
        for s in old or list(self._least)[: len(self._least) // 2]:
            del self._least[s]


def estimated_ns(least_ns: int | None, stamp_ns: int, taken_ns: int, since_ns: int) -> int:
    """`ArrivalEstimate.estimate_ns` from the sender's least lag `least_ns` (None: none counted),
    for a caller that looked it up once for several of that sender's states."""
    if least_ns is None:
        return taken_ns
    return max(since_ns, min(taken_ns, stamp_ns + least_ns))
