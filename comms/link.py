"""Radio link emulation at the transport boundary: rate, loss, latency and range, per sender.

A receiving process keeps one channel per sender (vehicle id). Every state the mesh receives is
offered to the link (`Mesh.subscribe_states(..., link=emulator)`), which decides whether and when
it reaches the application:

    rate gate  -> a 3 Hz link transmits the first state after each 1/3 s slot, drops the rest
    loss       -> Bernoulli, or bursty Gilbert-Elliott (a good and a bad state, each with a loss)
    range      -> extra loss growing linearly from 0 at `range_m` to 1 at `range_m + falloff_m`
    latency    -> delivered latency_s +- jitter_s later, in order per sender

The decision is the pure `decide()`, fed with uniform draws, so tests drive it with an injected
clock. `LinkEmulator` adds randomness, a delivery queue (drain it by hand in tests) and a
scheduler thread (use it as a context manager) for real processes.
"""

from __future__ import annotations

import heapq
import itertools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from comms.schema import VehicleState

Deliver = Callable[[VehicleState, int], None]
"""Called with (state, receive stamp at delivery in ns)."""


class LinkSpecError(ValueError):
    """A --link spec that cannot be parsed; the message says what is wrong and what is allowed."""


def _check_prob(name: str, p: Any) -> None:
    if not (isinstance(p, int | float) and math.isfinite(p) and 0.0 <= p <= 1.0):
        raise LinkSpecError(f"{name}={p!r} must be a probability within [0, 1]")


@dataclass(frozen=True)
class GilbertElliott:
    """Bursty loss: a two-state Markov chain stepped once per transmitted state."""

    p_good_bad: float
    """Probability of going from the good to the bad state at a transmission."""
    p_bad_good: float
    """Probability of going from the bad to the good state at a transmission."""
    loss_good: float = 0.0
    """Loss probability while good."""
    loss_bad: float = 1.0
    """Loss probability while bad."""

    def __post_init__(self) -> None:
        for name in ("p_good_bad", "p_bad_good", "loss_good", "loss_bad"):
            _check_prob(f"ge {name}", getattr(self, name))
        if self.p_good_bad + self.p_bad_good == 0.0:
            raise LinkSpecError(
                "ge: p_good_bad and p_bad_good cannot both be 0 (the chain never moves)"
            )

    @property
    def mean_loss(self) -> float:
        # Stationary: pi_bad = p_gb / (p_gb + p_bg); loss = pi_good loss_good + pi_bad loss_bad.
        pi_bad = self.p_good_bad / (self.p_good_bad + self.p_bad_good)
        return (1.0 - pi_bad) * self.loss_good + pi_bad * self.loss_bad


@dataclass(frozen=True)
class LinkProfile:
    """What one sender->receiver radio link does to a stream of states."""

    name: str = "custom"
    """Label for logs and LINK_STATS events."""
    rate_hz: float = 0.0
    """Most states transmitted per second per sender; 0 = unlimited."""
    loss: float = 0.0
    """Bernoulli loss probability of a transmitted state (unused when `ge` is set)."""
    ge: GilbertElliott | None = None
    """Bursty Gilbert-Elliott loss instead of Bernoulli."""
    latency_s: float = 0.0
    """Mean one-way delay added to every delivered state, in seconds."""
    jitter_s: float = 0.0
    """Delay varies uniformly within latency_s +- jitter_s (never below 0), in seconds."""
    range_m: float = 0.0
    """Distance beyond which loss grows; 0 = no range effect. Needs the receiver's position."""
    falloff_m: float = 0.0
    """Distance beyond range_m at which range loss reaches 1 (0 = a hard cut at range_m)."""

    def __post_init__(self) -> None:
        for name in ("rate_hz", "latency_s", "jitter_s", "range_m", "falloff_m"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise LinkSpecError(f"{name}={v!r} must be a finite number >= 0")
        if self.rate_hz and self.rate_hz > 10_000:
            raise LinkSpecError(f"rate_hz={self.rate_hz} is above 10000 Hz; use 0 for unlimited")
        _check_prob("loss", self.loss)
        if self.ge is not None and self.loss:
            raise LinkSpecError("give either loss= (Bernoulli) or ge= (Gilbert-Elliott), not both")

    @property
    def mean_loss(self) -> float:
        return self.ge.mean_loss if self.ge is not None else self.loss


PROFILES: dict[str, LinkProfile] = {
    "perfect": LinkProfile(name="perfect"),
    "xbee": LinkProfile(name="xbee", rate_hz=3.0, loss=0.2, latency_s=0.1, jitter_s=0.03),
    "wifi": LinkProfile(name="wifi", rate_hz=20.0, loss=0.02, latency_s=0.01, jitter_s=0.005),
}
"""Named profiles for --link. xbee follows the paper's 3 Hz XBee relay."""

_SPEC = {  # key: (LinkProfile fields it sets, how many numbers it takes, help)
    "rate": (("rate_hz",), (1,), "rate_hz (Hz, 0 = unlimited)"),
    "loss": (("loss",), (1,), "Bernoulli loss probability 0..1"),
    "latency": (("latency_s",), (1,), "latency_s (seconds)"),
    "jitter": (("jitter_s",), (1,), "jitter_s (seconds)"),
    "ge": (("ge",), (2, 4), "Gilbert-Elliott p_good_bad:p_bad_good[:loss_good:loss_bad]"),
    "range": (("range_m", "falloff_m"), (1, 2), "range_m[:falloff_m] (metres)"),
}


def _number(key: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise LinkSpecError(f"--link {key}={text!r}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise LinkSpecError(f"--link {key}={text!r} must be finite")
    return v


def parse_link_spec(spec: str) -> LinkProfile:
    """`xbee`, `wifi,loss=0.1`, or `rate=3,loss=0.2,latency=0.1,jitter=0.03,ge=0.05:0.3`."""
    help_text = "; ".join(f"{k}= {v[2]}" for k, v in _SPEC.items())
    if not isinstance(spec, str) or not spec.strip():
        raise LinkSpecError(
            f"empty --link spec: give a profile ({', '.join(PROFILES)}) or {help_text}"
        )
    tokens = [t.strip() for t in spec.split(",")]
    base = LinkProfile(name=spec)
    if "=" not in tokens[0]:
        name = tokens.pop(0)
        if name not in PROFILES:
            raise LinkSpecError(f"unknown link profile {name!r}: known are {', '.join(PROFILES)}")
        base = PROFILES[name] if not tokens else replace(PROFILES[name], name=spec)
    fields: dict[str, Any] = {}
    seen: set[str] = set()
    for tok in tokens:
        key, sep, value = (x.strip() for x in tok.partition("="))
        if not sep or not value:
            raise LinkSpecError(f"--link item {tok!r} must look like key=value ({help_text})")
        if key not in _SPEC:
            raise LinkSpecError(f"--link: unknown key {key!r}; known keys: {help_text}")
        if key in seen:
            raise LinkSpecError(f"--link: {key}= given twice")
        seen.add(key)
        names, counts, text = _SPEC[key]
        nums = [_number(key, p) for p in value.split(":")]
        if len(nums) not in counts:
            need = " or ".join(map(str, counts)) + " numbers" if len(counts) > 1 else "one number"
            raise LinkSpecError(f"--link {key}={value!r} needs {need}: {text}")
        if key == "ge":
            fields["ge"] = GilbertElliott(*nums)
        else:
            fields.update(zip(names, nums + [0.0] * (len(names) - len(nums)), strict=True))
    if "loss" in seen and "ge" in seen:
        raise LinkSpecError("give either loss= (Bernoulli) or ge= (Gilbert-Elliott), not both")
    if "ge" in seen:
        fields["loss"] = 0.0  # a profile's Bernoulli loss is replaced by the bursty model
    if "loss" in seen:
        fields["ge"] = None
    return replace(base, **fields)


# -- the pure core ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ChannelState:
    """What a link remembers about one sender between states."""

    next_slot_ns: int | None = None
    """Earliest time the rate gate lets the next state through; None before the first one."""
    bad: bool = False
    """Gilbert-Elliott chain is in the bad state."""
    last_deliver_ns: int = 0
    """Delivery time of the previous state: a radio delivers in order."""


@dataclass(frozen=True)
class Decision:
    deliver_ns: int | None
    """When to deliver, or None when dropped."""
    reason: str = ""
    """Why it was dropped: "rate", "loss" or "range"; empty when delivered."""


def range_loss(profile: LinkProfile, distance_m: float | None) -> float:
    """Extra loss probability at `distance_m`: 0 inside range_m, then linear to 1 over falloff_m."""
    if not profile.range_m or distance_m is None:
        return 0.0
    if distance_m <= profile.range_m:
        return 0.0
    if profile.falloff_m <= 0.0:
        return 1.0
    return min(1.0, (distance_m - profile.range_m) / profile.falloff_m)


def decide(
    profile: LinkProfile,
    chan: ChannelState,
    recv_ns: int,
    u_loss: float,
    u_ge: float,
    u_jitter: float,
    u_range: float,
    distance_m: float | None = None,
) -> tuple[Decision, ChannelState]:
    """Fate of one state received at `recv_ns`, from uniform draws u_* in [0, 1)."""
    # Rate gate on a slot grid: over time exactly min(input rate, rate_hz) pass, while a state
    # never passes before its slot (slots restart after a pause longer than one period).
    if profile.rate_hz:
        period_ns = round(1e9 / profile.rate_hz)
        if chan.next_slot_ns is not None and recv_ns < chan.next_slot_ns:
            return Decision(None, "rate"), chan
        slot = chan.next_slot_ns
        nxt = (
            slot + period_ns
            if slot is not None and recv_ns - slot < period_ns
            else recv_ns + period_ns
        )
        chan = replace(chan, next_slot_ns=nxt)
    if profile.ge is not None:
        ge = profile.ge
        flip = ge.p_bad_good if chan.bad else ge.p_good_bad
        chan = replace(chan, bad=chan.bad != (u_ge < flip))
        p_loss = ge.loss_bad if chan.bad else ge.loss_good
    else:
        p_loss = profile.loss
    if u_loss < p_loss:
        return Decision(None, "loss"), chan
    if u_range < range_loss(profile, distance_m):
        return Decision(None, "range"), chan
    delay_s = max(0.0, profile.latency_s + (2.0 * u_jitter - 1.0) * profile.jitter_s)
    deliver_ns = max(recv_ns + round(delay_s * 1e9), chan.last_deliver_ns)
    return Decision(deliver_ns), replace(chan, last_deliver_ns=deliver_ns)


# -- statistics ------------------------------------------------------------------------------
@dataclass(frozen=True)
class LinkStats:
    """One sender's channel, as seen by this receiver."""

    vehicle_id: int
    offered: int = 0
    """States that arrived from the wire."""
    transmitted: int = 0
    """States that passed the rate gate (the radio sent them)."""
    delivered: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    """Drops by reason: rate, loss, range."""
    mean_age_s: float = 0.0
    """Mean of (delivery time - state.stamp_ns) over delivered states."""
    max_age_s: float = 0.0
    mean_delay_s: float = 0.0
    """Mean delay the link added (delivery time - receive time)."""
    max_delay_s: float = 0.0

    @property
    def loss_fraction(self) -> float:
        """Share of transmitted states lost (loss and range), 0 when none were sent."""
        lost = self.dropped.get("loss", 0) + self.dropped.get("range", 0)
        return lost / self.transmitted if self.transmitted else 0.0


@dataclass
class _Counters:
    offered: int = 0
    transmitted: int = 0
    delivered: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    age_sum_s: float = 0.0
    age_max_s: float = 0.0
    delay_sum_s: float = 0.0
    delay_max_s: float = 0.0

    def snapshot(self, vid: int) -> LinkStats:
        n = max(self.delivered, 1)
        return LinkStats(
            vid,
            self.offered,
            self.transmitted,
            self.delivered,
            dict(self.dropped),
            self.age_sum_s / n,
            self.age_max_s,
            self.delay_sum_s / n,
            self.delay_max_s,
        )


class _Uniform(Protocol):
    def random(self) -> float: ...


class LinkEmulator:
    """Per-sender radio channels for one receiver; pass it as `link=` to Mesh.subscribe_states.

    Without the scheduler thread (not entered as a context manager), delayed states wait in a
    queue until `drain(now_ns)`; tests drive it that way with an injected clock.
    """

    def __init__(
        self,
        profile: LinkProfile,
        rng: _Uniform,
        clock_ns: Callable[[], int] = time.time_ns,
        receiver_pos: Callable[[], tuple[float, float, float] | None] | None = None,
        own_id: int | None = None,
    ) -> None:
        """`rng`: numpy Generator or random.Random. `clock_ns` must be the mesh's clock (the
        one that stamps recv_ns). `receiver_pos()` gives this receiver's NED position for
        range loss (None = unknown, no range loss). States of `own_id` (the receiver's own,
        echoed by the mesh) pass straight through and are not counted."""
        self.profile = profile
        self.own_id = own_id
        self._rng = rng
        self._clock_ns = clock_ns
        self._receiver_pos = receiver_pos
        self._lock = threading.Condition()
        self._channels: dict[int, ChannelState] = {}
        self._counters: dict[int, _Counters] = {}
        self._queue: list[tuple[int, int, VehicleState, int, Deliver]] = []
        self._tie = itertools.count()
        self._thread: threading.Thread | None = None
        self._stop = False

    # -- offering -------------------------------------------------------------------------
    def _distance_m(self, state: VehicleState) -> float | None:
        if self._receiver_pos is None or not self.profile.range_m:
            return None
        me = self._receiver_pos()
        if me is None:
            return None
        return math.dist(me, state.pos_ned_m)

    def offer(self, state: VehicleState, recv_ns: int, deliver: Deliver) -> None:
        """Decide the fate of `state`; `deliver(state, t_ns)` is called now, later or never."""
        if state.vehicle_id == self.own_id:
            deliver(state, recv_ns)
            return
        distance = self._distance_m(state)
        with self._lock:
            draws = [self._rng.random() for _ in range(4)]
            vid = state.vehicle_id
            chan = self._channels.get(vid, ChannelState())
            decision, chan = decide(
                self.profile,
                chan,
                recv_ns,
                draws[0],
                draws[1],
                draws[2],
                draws[3],
                distance_m=distance,
            )
            self._channels[vid] = chan
            c = self._counters.setdefault(vid, _Counters())
            c.offered += 1
            if decision.reason != "rate":
                c.transmitted += 1
            if decision.deliver_ns is None:
                c.dropped[decision.reason] = c.dropped.get(decision.reason, 0) + 1
                return
            immediate = decision.deliver_ns <= recv_ns and not self._queue
            if not immediate:
                heapq.heappush(
                    self._queue, (decision.deliver_ns, next(self._tie), state, recv_ns, deliver)
                )
                self._lock.notify_all()
                return
            self._account(c, state, recv_ns, recv_ns)
        deliver(state, recv_ns)

    def _account(self, c: _Counters, state: VehicleState, recv_ns: int, at_ns: int) -> None:
        age_s = (at_ns - state.stamp_ns) / 1e9
        delay_s = (at_ns - recv_ns) / 1e9
        c.delivered += 1
        c.age_sum_s += age_s
        c.age_max_s = max(c.age_max_s, age_s)
        c.delay_sum_s += delay_s
        c.delay_max_s = max(c.delay_max_s, delay_s)

    # -- delivering -----------------------------------------------------------------------
    def drain(self, now_ns: int) -> int:
        """Deliver every queued state due by `now_ns` (stamped with its due time); returns how
        many. The scheduler thread calls this; tests call it by hand."""
        due = []
        with self._lock:
            while self._queue and self._queue[0][0] <= now_ns:
                at_ns, _, state, recv_ns, deliver = heapq.heappop(self._queue)
                self._account(self._counters[state.vehicle_id], state, recv_ns, at_ns)
                due.append((deliver, state, at_ns))
        for deliver, state, at_ns in due:
            deliver(state, at_ns)
        return len(due)

    def pending(self) -> int:
        with self._lock:
            return len(self._queue)

    def _run(self) -> None:
        while True:
            with self._lock:
                if self._stop:
                    return
                if not self._queue:
                    self._lock.wait()
                    continue
                wait_s = (self._queue[0][0] - self._clock_ns()) / 1e9
                if wait_s > 0:
                    self._lock.wait(min(wait_s, 1.0))
                    continue
            self.drain(self._clock_ns())

    def __enter__(self) -> LinkEmulator:
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="covey-link", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the scheduler; states still queued are dropped (the receiver is going away)."""
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    # -- statistics -----------------------------------------------------------------------
    def stats(self) -> dict[int, LinkStats]:
        """A snapshot of every sender's channel statistics."""
        with self._lock:
            return {vid: c.snapshot(vid) for vid, c in sorted(self._counters.items())}

    def stats_text(self, max_bytes: int = 120) -> str:
        """A compact line for a LINK_STATS event: `link xbee 2:8/10 d20%l 0.11s ...`."""
        parts = [f"link {self.profile.name}"]
        for s in self.stats().values():
            parts.append(
                f"{s.vehicle_id}:{s.delivered}/{s.offered} l{100 * s.loss_fraction:.0f}% a{s.mean_age_s:.2f}s"
            )
        text = ""
        for p in parts:
            if len((text + " " + p).encode()) > max_bytes:
                break
            text = f"{text} {p}" if text else p
        return text


def emulator_from_spec(
    spec: str,
    seed: int | None = None,
    clock_ns: Callable[[], int] = time.time_ns,
    receiver_pos: Callable[[], tuple[float, float, float] | None] | None = None,
    own_id: int | None = None,
) -> LinkEmulator:
    """A LinkEmulator for a --link spec, seeded (e.g. with the vehicle id) for repeatable runs.
    Enter it as a context manager to run its scheduler thread."""
    import numpy as np

    profile = parse_link_spec(spec)
    return LinkEmulator(profile, np.random.default_rng(seed), clock_ns, receiver_pos, own_id)
