"""The ground station's fleet model: latest state per vehicle, trails, link health, separation.

Pure and thread-safe: no viser, no Zenoh, no clock. Mesh callbacks feed it (`on_state`,
`on_presence`) with the receive stamps they carry; the renderer asks for a `snapshot(now_ns)`.
The replay tool and the benchmark drive it the same way.

Bounded: ids come from the network, so the table holds at most `max_vehicles` (states of new
ids beyond that are refused and counted in `refused_states`; a present vehicle may take the place
of one that never held a liveliness token), and it forgets vehicles that are not present on the
mesh: one that never held a liveliness token `unconfirmed_expire_s` after its first state, one
that lost its token `lost_expire_s` after the loss. A phantom flood therefore leaves the table
within `unconfirmed_expire_s` of its end.

Keyed mode: the mesh drops states that do not verify and tells `on_state_refused`; a vehicle
whose claimed states were refused lately is marked `unverified` (a forger speaks for it, or its
own key is revoked or wrong). Refusals for ids the model does not know (phantoms) only bump a
counter: they never create a vehicle. Made-up ids in open mode expire as above.

Presence is not signed (anyone on the mesh can declare a vehicle's liveliness token), so with
`FleetConfig.verified_only` (the station and tools in keyed mode) the table lists only vehicles
that something signed proved: a verified state, or a verified clock report (`on_clock`). A
token of a vehicle with neither is counted apart, in a set of at most `max_unverified` ids (a
counter beyond); it never takes a row, so 2,000 fake tokens cannot push a real vehicle out.
When the vehicle's first verified state arrives, it is listed as present (its agent declared
its token before its first state, though the token may have been only counted).

Clock: a vehicle whose clock is off reports it in a signed ClockReport (trust/heartbeat.py);
the view carries the offset (`VehicleView.clock_offset_s`) while the report is recent, so that
the station shows "clock +10.0 s" instead of the last state it could accept.

Link health per vehicle, over a sliding window of `rate_window_s`:
    rate_hz  = (received - 1) / (t_last - t_first)
    loss     = 1 - received / (n_last - n_first + 1)
where n is the state's entry number in its feed (Mesh.subscribe_feed, the station's default: the
rate is then the updates reaching the station, at most the publisher's feed rate, and the loss
counts feed entries lost on the way), or VehicleState.seq for a station that hears every state.
A vehicle's seq grows by one per state it publishes, so an idle vehicle's lower rate (1 Hz,
comms/state_rate.py) is a lower rate, not loss. Staleness follows what the latest state announces:
an idle vehicle (landed or killed, disarmed) is stale after `idle_stale_after_s`, one holding at
rest (`announces_hold`: it publishes every MAX_HOLD_PERIOD_S) after `hold_stale_after_s`, any
other after `stale_after_s`.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections import OrderedDict, deque
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np

from comms.schema import ClockReport, Mode, StateFlag, VehicleState
from comms.state_rate import MAX_HOLD_PERIOD_S, MAX_IDLE_PERIOD_S, announces_hold, announces_idle

_HAS_GOAL = StateFlag.HAS_GOAL.value

NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class FleetConfig:
    """What the fleet model keeps and how it judges link health."""

    trail_s: float = 60.0
    """How much history each vehicle's trail keeps, in seconds."""
    trail_min_step_s: float = 0.2
    """A trail point is kept at most this often (bounds memory at trail_s / step points)."""
    rate_window_s: float = 3.0
    """Window over which the state rate and the loss estimate are computed, in seconds."""
    separation_m: float = 3.0
    """Two vehicles closer than this (3D distance) raise a separation alert."""
    stale_after_s: float = 1.0
    """A vehicle whose last state is older than this is shown as stale."""
    idle_stale_after_s: float = 3.5 * MAX_IDLE_PERIOD_S
    """... unless that state announces an idle vehicle (landed or killed, disarmed), which
    publishes only every MAX_IDLE_PERIOD_S (comms/state_rate.py): stale after three missed idle
    states, and half a period for the jitter."""
    hold_stale_after_s: float = 3.5 * MAX_HOLD_PERIOD_S
    """... or one holding at rest (mode HOLDING, at rest: comms/state_rate.py `announces_hold`),
    which publishes every MAX_HOLD_PERIOD_S: likewise three missed states and half a period."""
    unconfirmed_expire_s: float = 10.0
    """A vehicle that never held a liveliness token is forgotten this long after its first state."""
    lost_expire_s: float = 60.0
    """A vehicle that lost its liveliness token is shown LOST this long, then forgotten."""
    max_vehicles: int = 2000
    """The most vehicles the table holds; states of new ids beyond it are refused (counted)."""
    unverified_window_s: float = 3.0
    """A vehicle stays marked unverified this long after a state claiming it was refused."""
    verified_only: bool = False
    """Keyed mode: list only vehicles proved by a verified state or clock report; presence
    tokens of others are only counted (`FleetModel.unverified_present`)."""
    max_unverified: int = 256
    """The most presence tokens without a verified vehicle kept apart (verified_only); more are
    only counted."""
    clock_shown_s: float = 15.0
    """A vehicle's clock report is shown this long after it arrived (it repeats every 5 s
    while its clock is off)."""

    def __post_init__(self) -> None:
        if not 1 <= self.max_vehicles <= 1_000_000:
            raise ValueError(f"max_vehicles={self.max_vehicles} must be within 1..1000000")
        if not 0 <= self.max_unverified <= 1_000_000:
            raise ValueError(f"max_unverified={self.max_unverified} must be within 0..1000000")
        for name in (
            "trail_s",
            "trail_min_step_s",
            "rate_window_s",
            "separation_m",
            "stale_after_s",
            "idle_stale_after_s",
            "hold_stale_after_s",
            "unconfirmed_expire_s",
            "lost_expire_s",
            "unverified_window_s",
            "clock_shown_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value} must be a positive finite number")

    def stale_after(self, state: VehicleState | None) -> float:
        """How long the station waits after `state` before it calls the vehicle stale: what the
        state announces says how soon the next one is due."""
        if state is None:
            return self.stale_after_s
        if announces_idle(state.mode, state.armed):
            return self.idle_stale_after_s
        if announces_hold(state.mode, state.vel_ned_m_s):
            return self.hold_stale_after_s
        return self.stale_after_s


@dataclass
class _Track:
    """Everything the model keeps about one vehicle (internal, guarded by the model's lock)."""

    state: VehicleState | None = None
    last_recv_ns: int = 0
    alive: bool = False
    lost_ns: int | None = None
    first_ns: int = 0
    ever_alive: bool = False
    window: deque[tuple[int, int]] = field(default_factory=deque)  # (recv_ns, seq)
    trail: deque[tuple[int, tuple[float, float, float]]] = field(default_factory=deque)
    duplicates: int = 0
    refused: int = 0
    refused_ns: int | None = None
    refused_cause: str = ""
    stale_after_s: float = 0.0
    """FleetConfig.stale_after(state), set with each state (the snapshot reads it per frame)."""
    clock: ClockReport | None = None
    clock_ns: int = 0
    """The vehicle's latest clock report and when it arrived."""


@dataclass(frozen=True)
class VehicleView:
    """One vehicle as the ground station shows it, at one instant."""

    vehicle_id: int
    alive: bool
    """Its liveliness token is present (the agent process is up and reachable)."""
    state: VehicleState | None
    """The latest state received, or None if none yet."""
    age_s: float
    """Seconds since the latest state arrived (inf if none)."""
    rate_hz: float
    """States received per second over the rate window."""
    loss_pct: float
    """Estimated loss over the rate window, from sequence-number gaps, in percent."""
    trail_ned_m: np.ndarray
    """(K, 3) trail positions, oldest first."""
    too_close: bool
    """Closer than the separation distance to another vehicle."""
    stale: bool
    """No state for longer than FleetConfig.stale_after_s (idle_stale_after_s if the latest
    announced an idle vehicle)."""
    unverified: bool = False
    """A state claiming to be this vehicle was refused (forged, replayed, unsigned, or signed by a
    revoked key) within FleetConfig.unverified_window_s. With `stale` as well, the vehicle's own
    states do not verify. The station shows it in red with `refused_cause`."""
    refused_states: int = 0
    """States claiming this vehicle that the mesh refused, since the station started."""
    refused_cause: str = ""
    """Why the latest one was refused ("forged", "replayed", "unknown signer", ...)."""
    clock_offset_s: float | None = None
    """The vehicle's clock minus a station's, as its latest clock report said (within
    FleetConfig.clock_shown_s, until a report says it is back); None: no clock problem. Its
    states are then likely refused as stale: the station shows this, not the last state."""

    @property
    def speed_m_s(self) -> float:
        if self.state is None:
            return 0.0
        return math.sqrt(sum(v * v for v in self.state.vel_ned_m_s))

    @property
    def alt_m(self) -> float:
        return -self.state.pos_ned_m[2] + 0.0 if self.state is not None else 0.0  # + 0.0: no '-0.0'

    @property
    def mode(self) -> Mode | None:
        return self.state.mode if self.state is not None else None

    @property
    def has_goal(self) -> bool:
        # the flag's int value: enum arithmetic costs 4x more, once per vehicle per frame
        return self.state is not None and bool(self.state.flags.value & _HAS_GOAL)


@dataclass(frozen=True)
class FleetSnapshot:
    """The whole fleet at one instant, sorted by vehicle id."""

    now_ns: int
    vehicles: tuple[VehicleView, ...]
    close_pairs: tuple[tuple[int, int, float], ...]
    """(id_a, id_b, distance_m) for every pair closer than the separation distance."""
    unverified_present: int = 0
    """Presence tokens of vehicles not listed: nothing signed proved them (verified_only)."""


class FleetModel:
    """Latest-wins fleet state fed from the mesh. Every method is safe from any thread."""

    def __init__(self, cfg: FleetConfig | None = None) -> None:
        self.cfg = cfg or FleetConfig()
        self._lock = threading.Lock()
        self._tracks: dict[int, _Track] = {}
        self.refused_states = 0
        """States of new vehicle ids refused because the table was full."""
        self.expired = 0
        """Vehicles forgotten because they were not present on the mesh (see the module doc)."""
        self.phantom_refusals = 0
        """Refused states for ids this model does not know (never created a vehicle)."""
        self._unverified: OrderedDict[int, int] = OrderedDict()  # id -> since (verified_only)
        self.unverified_dropped = 0
        """Presence tokens without a verified vehicle beyond `max_unverified` (only counted; a
        leave of an id not kept takes one off; a vehicle listed later may stay counted)."""

    def _track(self, vehicle_id: int, now_ns: int, present: bool) -> _Track | None:
        """The track of `vehicle_id`, made if there is room (lock held). A present vehicle may
        push out one that never held a token; anything else waits for room."""
        track = self._tracks.get(vehicle_id)
        if track is not None:
            return track
        if len(self._tracks) >= self.cfg.max_vehicles:
            victim = next((v for v, t in self._tracks.items() if not t.ever_alive), None)
            if not present or victim is None:
                return None
            del self._tracks[victim]
        track = self._tracks[vehicle_id] = _Track(first_ns=now_ns)
        return track

    def _expire(self, now_ns: int) -> None:
        """Forget vehicles that are not present on the mesh for too long (lock held)."""
        cfg = self.cfg
        unconfirmed_ns, lost_ns = (
            int(cfg.unconfirmed_expire_s * NS_PER_S),
            int(cfg.lost_expire_s * NS_PER_S),
        )
        gone = [
            vid
            for vid, t in self._tracks.items()
            if not t.alive
            and (
                (not t.ever_alive and now_ns - t.first_ns > unconfirmed_ns)
                or (t.ever_alive and t.lost_ns is not None and now_ns - t.lost_ns > lost_ns)
            )
        ]
        for vid in gone:
            del self._tracks[vid]
        self.expired += len(gone)

    # -- inputs ------------------------------------------------------------------------------
    def on_state(self, state: VehicleState, recv_ns: int, entry_seq: int | None = None) -> None:
        """Record one received state (a Mesh.subscribe_feed or subscribe_states callback).
        `entry_seq`: its entry number in its feed, on which loss is counted; None: its seq."""
        cfg = self.cfg
        with self._lock:
            track = self._verified_track(state.vehicle_id, recv_ns)
            if track is None:
                self.refused_states += 1
                return
            prev = track.state
            if prev is not None:
                if state.seq == prev.seq:
                    track.duplicates += 1
                    return
                if state.seq < prev.seq:
                    # An older state arriving late is dropped; a big jump back is an agent restart.
                    if prev.seq - state.seq < 100:
                        return
                    track.window.clear()
            n = state.seq if entry_seq is None else entry_seq
            if track.window and n <= track.window[-1][1]:
                track.window.clear()  # a restarted publisher, or another feed: count from here
            track.state = state
            track.stale_after_s = cfg.stale_after(state)
            track.last_recv_ns = recv_ns
            track.window.append((recv_ns, n))
            horizon_ns = recv_ns - int(cfg.rate_window_s * NS_PER_S)
            while track.window and track.window[0][0] < horizon_ns:
                track.window.popleft()
            if not track.trail or recv_ns - track.trail[-1][0] >= cfg.trail_min_step_s * NS_PER_S:
                track.trail.append((recv_ns, state.pos_ned_m))
            trail_horizon_ns = recv_ns - int(cfg.trail_s * NS_PER_S)
            while track.trail and track.trail[0][0] < trail_horizon_ns:
                track.trail.popleft()

    def on_state_refused(self, vehicle_id: int, cause: str, recv_ns: int) -> None:
        """Record a state the mesh refused (keyed mode: passed to Mesh.subscribe_* as `on_refused`).
        Never creates a vehicle: an unknown id only bumps `phantom_refusals`."""
        with self._lock:
            track = self._tracks.get(vehicle_id)
            if track is None:
                self.phantom_refusals += 1
                return
            track.refused += 1
            track.refused_ns = recv_ns
            track.refused_cause = cause

    def on_clock(self, report: ClockReport, recv_ns: int) -> None:
        """Record a vehicle's clock report (from a CLOCK event, verified in keyed mode: it
        proves the vehicle as a verified state does)."""
        with self._lock:
            track = self._verified_track(report.vehicle_id, recv_ns)
            if track is None:
                self.refused_states += 1
                return
            track.clock, track.clock_ns = report, recv_ns

    def _verified_track(self, vehicle_id: int, now_ns: int) -> _Track | None:
        """The track of a vehicle that something signed (or, open mode, anything) just proved,
        made if there is room; its presence token, kept apart until now, moves over (lock held)."""
        track = self._tracks.get(vehicle_id)
        if track is not None:
            return track
        token_ns = self._unverified.pop(vehicle_id, None)
        track = self._track(vehicle_id, now_ns, present=token_ns is not None)
        if track is None:
            if token_ns is not None:
                self._unverified[vehicle_id] = token_ns
            return None
        if token_ns is not None or self.cfg.verified_only:
            # A member that signs states runs its agent, which declared its token before its
            # first state: present (its token may have been only counted, beyond the bound).
            track.alive = track.ever_alive = True
        return track

    def on_presence(self, vehicle_id: int, alive: bool, now_ns: int) -> None:
        """Record a liveliness change (a Mesh.presence on_change callback, vehicles only).
        With `verified_only`, the token of a vehicle not listed yet is only kept apart."""
        with self._lock:
            if self.cfg.verified_only and vehicle_id not in self._tracks:
                if not alive:
                    if self._unverified.pop(vehicle_id, None) is None and self.unverified_dropped:
                        self.unverified_dropped -= 1  # one of those only counted has gone
                elif vehicle_id in self._unverified:
                    pass
                elif len(self._unverified) < self.cfg.max_unverified:
                    self._unverified[vehicle_id] = now_ns
                else:
                    self.unverified_dropped += 1
                return
            track = self._track(vehicle_id, now_ns, present=alive)
            if track is None:
                return
            track.alive = alive
            track.ever_alive |= alive
            track.lost_ns = None if alive else now_ns

    def forget(self, vehicle_id: int) -> None:
        with self._lock:
            self._tracks.pop(vehicle_id, None)

    # -- outputs -----------------------------------------------------------------------------
    def ids(self) -> list[int]:
        with self._lock:
            return sorted(self._tracks)

    def present_ids(self) -> set[int]:
        """The listed vehicles whose presence token is up: who should answer a command to all
        (with `verified_only`, never a vehicle that nothing signed proved)."""
        with self._lock:
            return {vid for vid, t in self._tracks.items() if t.alive}

    @property
    def unverified_present(self) -> int:
        """Presence tokens of vehicles that are not listed (verified_only): kept apart plus
        those only counted beyond `max_unverified`."""
        with self._lock:
            return len(self._unverified) + self.unverified_dropped

    def positions(self) -> dict[int, tuple[float, float, float]]:
        """Latest NED position of every vehicle with a state."""
        with self._lock:
            return {
                vid: t.state.pos_ned_m for vid, t in self._tracks.items() if t.state is not None
            }

    def pos_sigmas(self) -> dict[int, float]:
        """Latest reported position 1-sigma (m) of every vehicle with a state (0: exact or not
        reported; the assumed one where its autopilot reports none)."""
        with self._lock:
            return {
                vid: t.state.pos_sigma_m for vid, t in self._tracks.items() if t.state is not None
            }

    def snapshot(self, now_ns: int, trails: bool | Collection[int] = True) -> FleetSnapshot:
        """The fleet at `now_ns`. Trails are the costly part: `trails` is True (all), False
        (none: every trail empty), or the ids whose trails to include.

        O(1) per vehicle besides its trail: the rate window is read at its ends (the entries
        older than the window are at its front, and `on_state` keeps few of them), not copied.
        """
        want = (lambda _vid: trails) if isinstance(trails, bool) else trails.__contains__
        cfg = self.cfg
        horizon_ns = now_ns - int(cfg.rate_window_s * NS_PER_S)
        with self._lock:
            self._expire(now_ns)
            raw = []
            for vid in sorted(self._tracks):
                t = self._tracks[vid]
                window = t.window
                old = 0
                while old < len(window) and window[old][0] < horizon_ns:
                    old += 1
                recent = len(window) - old
                health = _health(recent, window[old], window[-1]) if recent >= 2 else (0.0, 0.0)
                raw.append(
                    (
                        vid,
                        t.state,
                        t.alive,
                        t.last_recv_ns,
                        health,
                        _trail_array(t.trail) if t.trail and want(vid) else None,
                        (t.refused, t.refused_ns, t.refused_cause),
                        t.stale_after_s,
                        _clock_offset(t, now_ns, cfg.clock_shown_s),
                    )
                )
            unverified_present = len(self._unverified) + self.unverified_dropped
        with_pos = [(vid, s.pos_ned_m) for vid, s, *_ in raw if s is not None]
        pairs = close_pairs(with_pos, cfg.separation_m)
        close_ids = {a for a, _, _ in pairs} | {b for _, b, _ in pairs}
        views = []
        unverified_ns = int(cfg.unverified_window_s * NS_PER_S)
        for vid, state, alive, last_ns, health, trail, refusal, stale_after_s, clock in raw:
            rate_hz, loss_pct = health
            refused, refused_ns, cause = refusal
            age_s = (now_ns - last_ns) / NS_PER_S if state is not None else math.inf
            views.append(
                VehicleView(
                    vehicle_id=vid,
                    alive=alive,
                    state=state,
                    age_s=age_s,
                    rate_hz=rate_hz,
                    loss_pct=loss_pct,
                    trail_ned_m=_NO_TRAIL if trail is None else trail,
                    too_close=vid in close_ids,
                    stale=age_s > stale_after_s,  # no state yet: age inf, stale
                    unverified=refused_ns is not None and now_ns - refused_ns <= unverified_ns,
                    refused_states=refused,
                    refused_cause=cause,
                    clock_offset_s=clock,
                )
            )
        return FleetSnapshot(
            now_ns=now_ns,
            vehicles=tuple(views),
            close_pairs=tuple(pairs),
            unverified_present=unverified_present,
        )


def _clock_offset(track: _Track, now_ns: int, shown_s: float) -> float | None:
    """The clock offset a track's latest report shows now, or None (none, old, or 'ok')."""
    report = track.clock
    if report is None or report.ok or now_ns - track.clock_ns > shown_s * NS_PER_S:
        return None
    return report.offset_s


def _trail_array(trail: deque[tuple[int, tuple[float, float, float]]]) -> np.ndarray:
    """(K, 3) float32 positions of a trail of (recv_ns, pos) points: one flat pass (twice as
    fast as np.array of a list of tuples, and the snapshot makes a tenth of the fleet's)."""
    flat = itertools.chain.from_iterable(p for _, p in trail)
    return np.fromiter(flat, np.float32, count=3 * len(trail)).reshape(-1, 3)


_NO_TRAIL = np.zeros((0, 3), dtype=np.float32)
_NO_TRAIL.setflags(write=False)
"""The trail of a vehicle whose trail was not asked for (or has none): one shared, read-only."""


def _health(count: int, first: tuple[int, int], last: tuple[int, int]) -> tuple[float, float]:
    """(rate_hz, loss_pct) of `count` >= 2 samples from `first` to `last` (recv_ns, seq)."""
    span_s = (last[0] - first[0]) / NS_PER_S
    rate_hz = (count - 1) / span_s if span_s > 0 else 0.0
    expected = last[1] - first[1] + 1
    loss_pct = 100.0 * max(0.0, 1.0 - count / expected) if expected > 0 else 0.0
    return rate_hz, loss_pct


def link_health(window: list[tuple[int, int]] | tuple[tuple[int, int], ...]) -> tuple[float, float]:
    """(rate_hz, loss_pct) from (recv_ns, seq) samples in arrival order, seq increasing."""
    if len(window) < 2:
        return 0.0, 0.0
    return _health(len(window), window[0], window[-1])


def close_pairs(
    positions: list[tuple[int, tuple[float, float, float]]], separation_m: float
) -> list[tuple[int, int, float]]:
    """Every pair of vehicles closer than `separation_m` (3D), as (id_a, id_b, distance_m), id_a < id_b,
    sorted; `positions` holds each id once.

    A grid of separation-sized (north, east) cells, vectorised: a close pair lies in the same or
    a neighbouring cell, so each vehicle is compared with the vehicles of its own cell and of four
    neighbouring ones (the other four see it from their side), found by binary search in the
    cell-sorted list, never with all n. tests/test_gcs_fleet.py checks it against the plain loop.
    """
    n = len(positions)
    if n < 2:
        return []
    ids = np.fromiter((vid for vid, _ in positions), dtype=np.int64, count=n)
    p = np.array([pos for _, pos in positions], dtype=np.float64).reshape(n, 3)
    cells = np.floor(p[:, :2] / separation_m).astype(np.int64)
    cells -= cells.min(axis=0)
    span = int(cells[:, 1].max()) + 3  # an east offset of +-1 never wraps into another row
    key = cells[:, 0] * span + cells[:, 1] + 1
    order = np.argsort(key, kind="stable")
    key, p, ids = key[order], p[order], ids[order]
    rows = np.arange(n)
    found_a, found_b = [], []
    for dn, de in ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1)):
        target = key + dn * span + de
        lo = np.searchsorted(key, target, side="left")
        hi = np.searchsorted(key, target, side="right")
        if dn == 0 and de == 0:
            lo = np.maximum(lo, rows + 1)  # own cell: each pair once
        counts = np.maximum(hi - lo, 0)
        total = int(counts.sum())
        if not total:
            continue
        a = np.repeat(rows, counts)
        starts = np.cumsum(counts) - counts
        b = np.repeat(lo, counts) + (np.arange(total) - np.repeat(starts, counts))
        found_a.append(a)
        found_b.append(b)
    if not found_a:
        return []
    a, b = np.concatenate(found_a), np.concatenate(found_b)
    d = p[a] - p[b]
    d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
    close = d2 < separation_m * separation_m
    ia, ib, dist = ids[a[close]], ids[b[close]], np.sqrt(d2[close])
    lo_id, hi_id = np.minimum(ia, ib), np.maximum(ia, ib)
    return sorted(zip(lo_id.tolist(), hi_id.tolist(), dist.tolist(), strict=True))
