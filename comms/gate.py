"""The receive-side gate for signed states and events: what a keyed process lets in.

Per state, cheapest check first, so that junk costs no signature verification:

    1. signed at all                               else UNSIGNED
    2. |recv - stamp_ns| <= max_skew_s             else STALE       (a recording re-sent later)
    3. stamp_ns newer than the last accepted one   else REPLAYED (same stamp) / OUT_OF_ORDER
    4. [thinning] at least min_interval_s since the last accepted state of that vehicle, else
       skipped unverified (not a refusal: an agent does not need every 10 Hz state; the neighbour
       table dead-reckons in between)
    4b. [reach] `worth_checking(state)`, if given, else skipped unverified: a state whose own
       position is beyond the receiver's reach (agent/neighbours.py `NeighbourTable.worth_checking`)
       could change nothing it does. The verdict rests on that state's own claims only, so a
       forged state can get itself skipped but never another one, nor a real one refused.
    5. signer in the roster, signature verifies    else UNKNOWN / FORGED

Only a state that passed 5 moves the vehicle's "last accepted" stamp and time, so a forger can
neither push a vehicle's states out (3) nor make real ones skipped (4). The per-vehicle table
holds roster members only (5 comes before any insert), so phantom ids never grow it.

Refusals are counted per cause; `on_summary(text)` gets at most one line per cause per
`summary_period_s`, which the agent publishes as a SECURITY event and the station logs.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from comms.schema import (
    ActionOutcome,
    Command,
    Event,
    EventMessage,
    Mission,
    Role,
    Roster,
    VehicleState,
)


class Refusal(enum.Enum):
    UNSIGNED = "unsigned"
    STALE = "stale"
    REPLAYED = "replayed"
    OUT_OF_ORDER = "out of order"
    UNKNOWN = "unknown signer"
    FORGED = "forged"


SKIPPED = "skipped"
"""admit() result for a state thinned before verification (neither accepted nor refused)."""


@dataclass(frozen=True)
class GateConfig:
    """How strict a receiver is, and how often it reports."""

    max_skew_s: float = 5.0
    """A state or event stamped further than this from the receiver's clock is refused as stale
    (clocks agree within this: NTP or GPS time)."""
    min_interval_s: float = 0.0
    """Skip (without verifying) a vehicle's state arriving sooner than this after its last
    accepted one. 0: verify every state (the ground station); agents use 0.15 (about 5 Hz)."""
    summary_period_s: float = 1.0
    """At most one summary line per refusal cause per this many seconds."""
    batch_budget_s: float = 0.03
    """A polled subscription (an agent's tick takes its states at once, comms/mesh.py) tries
    each vehicle's most plausible state, then the others only while it has spent less than this
    on them; what is left is dropped unchecked (`states_unchecked`), so that a flood of forged
    states cannot stall the tick."""

    def __post_init__(self) -> None:
        for name in ("max_skew_s", "min_interval_s", "summary_period_s", "batch_budget_s"):
            value = getattr(self, name)
            if not 0.0 <= value <= 3600.0:
                raise ValueError(f"{name}={value} must be within [0, 3600]")


class Summaries:
    """At most one line per cause per `period_s`: the first refusal of a quiet cause at once, then
    a count of what happened since. Thread-safe. `emit(line)` exceptions are swallowed."""

    def __init__(self, emit: Callable[[str], None] | None, period_s: float = 1.0) -> None:
        self.emit = emit
        self._period_ns = int(period_s * 1e9)
        self._lock = threading.Lock()
        self._pending: dict[object, int] = {}
        self._emitted_ns: dict[object, int] = {}

    def note(self, cause: object, now_ns: int, describe: Callable[[int], str]) -> None:
        """Count one `cause`; if its line is due, emit `describe(count since the last line)`."""
        with self._lock:
            count = self._pending.get(cause, 0) + 1
            last = self._emitted_ns.get(cause)
            if last is not None and now_ns - last < self._period_ns:
                self._pending[cause] = count
                return
            self._emitted_ns[cause] = now_ns
            self._pending.pop(cause, None)
        if self.emit is not None:
            try:
                self.emit(describe(count)[:119])
            except Exception:  # noqa: BLE001 - reporting must not break receiving
                pass


def command_refusals(
    emit: Callable[[str], None], clock_ns: Callable[[], int], period_s: float = 1.0
) -> Callable[[Command | Mission, int, str], None]:
    """A `FleetAuth.on_reject(command, vehicle_id, reason)` listener that emits at most one line
    per refusal cause (the reason up to its colon) per `period_s`: the first refusal whole, then
    a count. The agent and the multi-vehicle host publish the lines as SECURITY events, so that
    a flood of forged commands becomes a few events, not a flood of them."""
    summaries = Summaries(emit, period_s)

    def on_reject(cmd: Command | Mission, _vehicle_id: int, reason: str) -> None:
        cause = reason.split(":", 1)[0]
        kind = getattr(cmd.kind, "name", str(cmd.kind)).lower()
        summaries.note(
            cause,
            clock_ns(),
            lambda n: (
                f"refused {kind} from station {cmd.source_id}: {reason}"
                if n == 1
                else f"refused {n} commands ({cause}); latest {kind} from station {cmd.source_id}"
            ),
        )

    return on_reject


class SignatureChecker(Protocol):
    """What a gate asks of this member's keys (comms/member.py `MemberAuth` extends it): the
    roster and the signature checks, each None if fine, else why not."""

    @property
    def roster(self) -> Roster: ...

    def is_member(self, role: Role, member_id: int) -> bool: ...

    def check_state(self, state: VehicleState, signed: bytes | None = None) -> str | None:
        """`signed`: `state.signed_bytes()`, where the caller has them (the bytes it decoded
        `state` from); None: made from `state`."""
        ...

    def check_event(self, event: Event) -> str | None: ...

    def check_outcome(self, outcome: ActionOutcome) -> str | None: ...


class Gate:
    """One subscription's gate (each keeps its own 'last accepted' per vehicle). Thread-safe."""

    def __init__(
        self,
        auth: SignatureChecker,
        cfg: GateConfig = GateConfig(),
        on_summary: Callable[[str], None] | None = None,
        what: str = "state",
        worth_checking: Callable[[VehicleState], bool] | None = None,
    ) -> None:
        self.auth = auth
        self.worth_checking = worth_checking
        """Step 4b (module docstring); None: every state that gets that far is checked."""
        self.cfg = cfg
        self.what = what
        self.on_summary = on_summary
        self._skew_ns = int(cfg.max_skew_s * 1e9)
        self._min_ns = int(cfg.min_interval_s * 1e9)
        self._summaries = Summaries(on_summary, cfg.summary_period_s)
        self._lock = threading.Lock()
        self._last: dict[int, tuple[int, int]] = {}  # vehicle -> (stamp_ns, recv_ns) accepted
        self.accepted = 0
        self.skipped = 0
        self.out_of_reach = 0
        """Of `skipped`, those that step 4b skipped."""
        self.refused: dict[Refusal, int] = dict.fromkeys(Refusal, 0)
        """Refusals per cause since start (read only)."""

    def admit_state(self, state: VehicleState, recv_ns: int) -> Refusal | str | None:
        """None: accept. A Refusal: drop and count. SKIPPED: drop silently (thinning)."""
        head = self.admit_head(
            state.vehicle_id, state.seq, state.stamp_ns, bool(state.sig), recv_ns
        )
        return head if head is not None else self.admit_decoded(state, recv_ns)

    def admit_head(
        self, vid: int, seq: int, stamp_ns: int, signed: bool, recv_ns: int
    ) -> Refusal | str | None:
        """Steps 1-4 of `admit_state`, on what a state's head says (`VehicleState.peek`): a
        receiver need not decode a state these refuse or thin. None: go on with
        `admit_decoded` on the decoded state (which must have this head)."""
        if not signed:
            return self._refuse(Refusal.UNSIGNED, vid, "no signature", recv_ns)
        age_ns = recv_ns - stamp_ns
        if abs(age_ns) > self._skew_ns:
            return self._refuse(
                Refusal.STALE, vid, f"stamped {age_ns / 1e9:+.1f} s from now", recv_ns
            )
        last = self._last.get(vid)
        if last is not None:
            if stamp_ns == last[0]:
                return self._refuse(Refusal.REPLAYED, vid, f"seq {seq} again", recv_ns)
            if stamp_ns < last[0]:
                return self._refuse(
                    Refusal.OUT_OF_ORDER, vid, f"older than the last (seq {seq})", recv_ns
                )
            if recv_ns - last[1] < self._min_ns:
                with self._lock:
                    self.skipped += 1
                return SKIPPED
        return None

    def admit_decoded(
        self, state: VehicleState, recv_ns: int, signed: bytes | None = None
    ) -> Refusal | str | None:
        """The rest of `admit_state`, after `admit_head` passed `state`'s head: step 4b, the
        signature, and the last accepted stamp (under the lock: a newer state may have won).
        `signed`: `state.signed_bytes()` where the caller has them (`SignatureChecker`)."""
        vid = state.vehicle_id
        if self.worth_checking is not None and not self.worth_checking(state):
            with self._lock:
                self.skipped += 1
                self.out_of_reach += 1
            return SKIPPED
        problem = (
            self.auth.check_state(state) if signed is None else self.auth.check_state(state, signed)
        )
        if problem:
            cause = Refusal.UNKNOWN if problem.startswith("unknown") else Refusal.FORGED
            return self._refuse(cause, vid, problem, recv_ns)
        with self._lock:
            last = self._last.get(vid)
            if last is not None and state.stamp_ns <= last[0]:  # a newer one won the race
                return self._refuse(
                    Refusal.OUT_OF_ORDER, vid, f"older than the last (seq {state.seq})", recv_ns
                )
            self._last[vid] = (state.stamp_ns, recv_ns)
            self.accepted += 1
            if len(self._last) > 2 * len(self.auth.roster.members) + 16:  # revoked members go
                for gone in [v for v in self._last if not self.auth.is_member(Role.VEHICLE, v)]:
                    del self._last[gone]
        return None

    def admit_event(self, event: EventMessage, recv_ns: int) -> Refusal | None:
        """Events and autopilot outcomes: signed by their vehicle and fresh (no ordering: events
        are not latest-wins)."""
        vid = event.vehicle_id
        if not event.sig:
            return self._refuse(Refusal.UNSIGNED, vid, "no signature", recv_ns)
        age_ns = recv_ns - event.stamp_ns
        if abs(age_ns) > self._skew_ns:
            return self._refuse(
                Refusal.STALE, vid, f"stamped {age_ns / 1e9:+.1f} s from now", recv_ns
            )
        if isinstance(event, ActionOutcome):
            problem = self.auth.check_outcome(event)
        else:
            problem = self.auth.check_event(event)
        if problem:
            cause = Refusal.UNKNOWN if problem.startswith("unknown") else Refusal.FORGED
            return self._refuse(cause, vid, problem, recv_ns)
        with self._lock:
            self.accepted += 1
        return None

    @property
    def refused_total(self) -> int:
        return sum(self.refused.values())

    def _refuse(self, cause: Refusal, vid: int, detail: str, recv_ns: int) -> Refusal:
        with self._lock:
            self.refused[cause] += 1
        self._summaries.note(
            cause,
            recv_ns,
            lambda n: (
                f"refused {n} {cause.value} {self.what}{'s' if n > 1 else ''} (latest claims vehicle {vid}: {detail})"
            ),
        )
        return cause
