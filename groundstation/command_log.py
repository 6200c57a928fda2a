"""Every command sent to the fleet, from any station, with what became of it on each vehicle.

Several stations (and several tabs of one station) can command one fleet. Each station observes
every command query on the mesh and every vehicle's ack copy (`Mesh.observe_commands`), and keeps
them here, so that every operator sees one truth: who sent what to whom, and per vehicle whether
it is still waiting for an answer, was accepted, is done ("landed", "reached goal"), failed, was
superseded by a newer command before it finished, timed out, or was not reachable.

In keyed mode a command enters the log only if its signature verifies as a command (a station of
the roster signed it, and it is fresh: `FleetAuth.verify_command`); every other attempt is only
counted, per cause, for the last minute (`refused_last_minute`), so a flood of forged queries can
neither pose as a station nor push a real command out. In open mode nothing is signed, and each
entry says so.

Mission uploads are listed the same way ("mission 3 (6 items) → 1,2,3"), verified as missions
(their own signature label), with each vehicle's ack: accepted is "done: loaded" (an upload
changes no flight, so it never supersedes a command), rejected carries the item and reason.

Fleet plan versions are listed too (`on_plan`: every version the station followed, from any
station or the authority), one line each; a version this station pushed names the operator and
what they changed (an uploaded file, or edits made in the browser: `mark_own_plan`).

"Done" is the vehicle's own report: its signed state shows the mode the command ends in (a
take-off ends HOLDING at altitude, a goto HOLDING at its goal, a land LANDED), stamped after the
vehicle's ack. The autopilot's outcome (an `ActionOutcome` message) marks a failure.

Each ack and each outcome counts once per (vehicle, command nonce): the first verified one
stands, and a later copy is only counted (`duplicate_acks`, `duplicate_outcomes`). A vehicle
answers the querier with the query reply and everyone else with a copy on `msg/<id>/ack`
(comms/keys.py says why both exist); a station that sees the same answer twice (the copy
through two routers, or the vehicle's "replayed command" refusal of a command sent again with
its nonce) must not let it flip the first answer or count it twice.

Pure and thread-safe: no viser, no Zenoh, no clock. Bounded: at most `max_commands` commands,
each with at most `max_answers` answers; a vehicle id only stays while a kept command refers to it.
"""

from __future__ import annotations

import enum
import math
import threading
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from comms.schema import (
    AckResult,
    ActionOutcome,
    Command,
    CommandAck,
    CommandKind,
    Mission,
    Mode,
    StateFlag,
    VehicleState,
)
from groundstation.inputs import describe

REFUSED_WINDOW_S = 60
"""Refused command attempts are summarised over this many seconds."""
_MAX_CAUSES = 8
"""Distinct refusal causes counted; more share the last one ("other")."""
GOAL_MATCH_M = 0.5
"""A vehicle holding within this of a goto's goal has reached it."""

Request = Command | Mission
"""What the log keeps: a command, or a mission upload (answered through the command path)."""


@dataclass(frozen=True)
class CommandLogConfig:
    """How much of the fleet's command traffic a station keeps."""

    max_commands: int = 50
    """Newest commands kept; older ones are dropped."""
    max_answers: int = 1024
    """Answers kept per command (a broadcast to a large fleet); more are counted, not kept."""
    max_own: int = 1000
    """Nonces of the commands this station sent that are remembered (to say "this station")."""

    def __post_init__(self) -> None:
        if not 1 <= self.max_commands <= 100_000 or not 1 <= self.max_answers <= 100_000:
            raise ValueError("max_commands and max_answers must be within 1..100000")
        if not 1 <= self.max_own <= 100_000:
            raise ValueError("max_own must be within 1..100000")


class Status(enum.Enum):
    """What became of a command on one vehicle, as the operator reads it."""

    WAITING = "no answer yet"
    ACCEPTED = "accepted"
    DONE = "done"
    FAILED = "failed"
    REJECTED = "rejected"
    SUPERSEDED = "superseded"
    TIMED_OUT = "timed out"
    UNREACHABLE = "not reachable"


@dataclass(frozen=True)
class Progress:
    """One vehicle's part of one command."""

    status: Status
    detail: str = ""
    """The vehicle's reason, or the command's outcome ("landed", "reached goal")."""


@dataclass(frozen=True)
class Answer:
    """One vehicle's answer to one command."""

    result: AckResult
    reason: str
    stamp_ns: int = 0
    """The ack's stamp (the vehicle's clock): only states stamped after it can finish the command."""
    mode: Mode = Mode.LANDED
    """The vehicle's mode after the command."""


@dataclass(frozen=True)
class LoggedCommand:
    """One command as the station saw it, with what became of it on each vehicle."""

    seq: int
    """Order of arrival at this station (1, 2, ...)."""
    recv_ns: int
    command: Request
    answers: dict[int, Answer]
    """Vehicle id -> its answer (acks seen so far)."""
    superseded: dict[int, int]
    """Vehicle id -> seq of the later accepted command that replaced this one there before it
    finished."""
    dropped_answers: int = 0
    done: dict[int, ActionOutcome] = field(default_factory=dict)
    """Vehicle id -> how the autopilot's part ended (done, or failed with the reason); absent
    while it runs, and for commands with no autopilot part (e.g. a goto flown by the agent)."""
    finished: dict[int, str] = field(default_factory=dict)
    """Vehicle id -> the command's outcome as the vehicle's state showed it ("landed")."""
    own: bool = False
    """Sent by this station (this process), not only signed with a key of the same id."""
    signed: bool = False
    """Its station signature verified (keyed mode); False in open mode."""
    operator: str = ""
    """Own commands: who was logged in to the tab that sent it (web login account or token
    label; "station" for the station's own API)."""

    @property
    def source_id(self) -> int:
        return self.command.source_id

    def describe(self) -> str:
        who = ",".join(map(str, self.command.targets)) if self.command.targets else "all"
        return f"{describe_request(self.command)} → {who}"

    def sender(self) -> str:
        """Who sent it, as far as this station can tell."""
        if self.own:
            who = f"this station ({self.operator})" if self.operator else "this station"
            return who if self.signed else f"{who} (unsigned: open mode)"
        if self.signed:
            return f"station {self.source_id}"
        return f"unsigned, claims station {self.source_id}"

    def progress(
        self, vehicle_id: int, now_ns: int, answer_timeout_s: float, present: set[int] | None
    ) -> Progress:
        """Where this command stands on `vehicle_id` at `now_ns`. Without an answer after
        `answer_timeout_s`, an addressed vehicle is "not reachable" when it is not in `present`
        (None: unknown), else "timed out"."""
        answer = self.answers.get(vehicle_id)
        if answer is None:
            if (now_ns - self.recv_ns) / 1e9 < answer_timeout_s:
                return Progress(Status.WAITING)
            if present is not None and vehicle_id not in present:
                return Progress(Status.UNREACHABLE, "not on the mesh")
            return Progress(Status.TIMED_OUT, f"no answer within {answer_timeout_s:g} s")
        if answer.result is AckResult.REJECTED:
            return Progress(Status.REJECTED, answer.reason)
        if answer.result is not AckResult.ACCEPTED:
            return Progress(Status.FAILED, answer.reason)
        if vehicle_id in self.finished:
            return Progress(Status.DONE, self.finished[vehicle_id])
        if vehicle_id in self.superseded:  # only set while it had not ended there
            return Progress(Status.SUPERSEDED, f"by command #{self.superseded[vehicle_id]}")
        outcome = self.done.get(vehicle_id)
        if outcome is not None and not outcome.ok:
            return Progress(Status.FAILED, outcome.detail)
        detail = "autopilot took it; under way" if outcome is not None else "under way"
        return Progress(Status.ACCEPTED, detail)

    def vehicles(self) -> list[int]:
        """The vehicles it concerns: every one that answered, and every one it named."""
        return sorted(set(self.answers) | set(self.command.targets))


@dataclass(frozen=True)
class PlanChange:
    """A fleet plan version the station followed, as the log lists it."""

    seq: int
    """Order of arrival at this station, shared with the commands."""
    recv_ns: int
    version: int
    signer_id: int
    """Who signed it: 0 the fleet authority, N station N (open mode: the claim)."""
    summary: str
    """What the plan holds (comms/plan_sync.py `describe`)."""
    own: bool = False
    """Pushed by this station."""
    operator: str = ""
    """Own pushes: who was logged in to the tab that pushed it."""
    what: str = ""
    """Own pushes: what changed ('from 'field.geojson'', 'zone 4 ('depot') added')."""

    def sender(self) -> str:
        if self.own:
            return f"this station ({self.operator})" if self.operator else "this station"
        return "the fleet authority" if self.signer_id == 0 else f"station {self.signer_id}"

    def describe(self) -> str:
        what = f": {self.what}" if self.what else ""
        return f"plan v{self.version}{what} ({self.summary})"


def describe_request(request: Request) -> str:
    """What a command or a mission upload asks, as an operator reads it (without targets)."""
    if isinstance(request, Mission):
        n = len(request.items)
        v = f" v{request.mission_version}" if request.mission_version != 1 else ""
        return f"mission {request.mission_id}{v} ({n} item{'s' if n != 1 else ''})"
    return describe(request.kind, request.params)


def outcome_text(command: Request, mode: Mode, state: VehicleState | None) -> str | None:
    """The command's outcome if the vehicle in `mode` (with `state`, None: only the ack's mode
    is known) has finished it, else None. An accepted mission upload is done at once: loaded."""
    if isinstance(command, Mission):
        return "loaded"
    kind = command.kind
    if kind is CommandKind.KILL and mode is Mode.KILLED:
        return "killed"
    if kind is CommandKind.HOLD and mode is Mode.HOLDING:
        return "holding"
    if kind is CommandKind.LAND and mode is Mode.LANDED:
        return "landed"
    if kind in (CommandKind.MISSION_PAUSE, CommandKind.MISSION_ABORT) and mode is Mode.HOLDING:
        return "holding"
    if kind is CommandKind.MISSION_STATUS:
        return "answered"  # it changes nothing: its ack is its outcome
    if state is None:
        return None
    if kind is CommandKind.MISSION_START and 0 < state.mission_items < state.mission_item:
        return "mission done"
    if kind is CommandKind.RETURN and mode is Mode.LANDED:
        return "returned and landed"
    if kind is CommandKind.TAKEOFF and mode is Mode.HOLDING:
        return f"reached {-state.pos_ned_m[2]:.1f} m"
    holding_goal = mode is Mode.HOLDING and state.flags & StateFlag.HAS_GOAL
    if kind is CommandKind.GOTO_LOCAL and holding_goal:
        # Held at this goto's goal (a failsafe hold keeps the goal where the vehicle stopped).
        return (
            "reached goal" if math.dist(state.goal_ned_m, command.params) <= GOAL_MATCH_M else None
        )
    return None


SupersededCallback = Callable[[LoggedCommand, int, LoggedCommand], None]
"""Called with (the earlier command, the vehicle, the later command) when a vehicle accepts a
command that replaces one it had accepted and not finished."""

AckCheck = Callable[[CommandAck, Request, bytes], str | None]
"""Returns why an ack must not be believed for a command whose wire bytes hash to the digest
(a forged or replayed ack), or None."""

CommandCheck = Callable[[Request], str | None]
"""Returns why a command or mission must not be believed (`FleetAuth.verify_command`), or
None."""


@dataclass
class _Entry:
    seq: int
    recv_ns: int
    command: Request
    digest: bytes = b""
    own: bool = False
    signed: bool = False
    operator: str = ""
    answers: dict[int, Answer] = field(default_factory=dict)
    superseded: dict[int, int] = field(default_factory=dict)
    dropped_answers: int = 0
    done: dict[int, ActionOutcome] = field(default_factory=dict)
    finished: dict[int, str] = field(default_factory=dict)
    running: dict[int, bool] = field(default_factory=dict)
    """GOTO_GLOBAL: vehicle -> a state after the ack showed it flying there."""

    def view(self) -> LoggedCommand:
        return LoggedCommand(
            self.seq,
            self.recv_ns,
            self.command,
            dict(self.answers),
            dict(self.superseded),
            self.dropped_answers,
            dict(self.done),
            dict(self.finished),
            self.own,
            self.signed,
            self.operator,
        )

    def ended(self, vehicle_id: int) -> bool:
        outcome = self.done.get(vehicle_id)
        return vehicle_id in self.finished or (outcome is not None and not outcome.ok)


class _RefusedCounts:
    """Refused command attempts per cause, in one-second buckets over the last minute."""

    def __init__(self) -> None:
        self._buckets: dict[str, deque[list[int]]] = {}  # cause -> [second, count], oldest first
        self.total = 0

    def add(self, cause: str, recv_ns: int) -> None:
        self.total += 1
        if cause not in self._buckets and len(self._buckets) >= _MAX_CAUSES:
            cause = "other"
        q = self._buckets.setdefault(cause, deque(maxlen=REFUSED_WINDOW_S + 1))
        second = recv_ns // 1_000_000_000
        if q and q[-1][0] == second:
            q[-1][1] += 1
        else:
            q.append([second, 1])

    def last_minute(self, now_ns: int) -> dict[str, int]:
        since = now_ns // 1_000_000_000 - REFUSED_WINDOW_S
        counts = {c: sum(n for s, n in q if s > since) for c, q in self._buckets.items()}
        return {c: n for c, n in sorted(counts.items(), key=lambda kv: -kv[1]) if n}


def refusal_cause(reason: str) -> str:
    """The cause of a refusal, without its particulars ("unsigned command", "bad signature")."""
    return reason.partition(":")[0].strip()[:40] or "refused"


class CommandLog:
    def __init__(
        self, cfg: CommandLogConfig | None = None, on_superseded: SupersededCallback | None = None
    ) -> None:
        self.cfg = cfg or CommandLogConfig()
        self.on_superseded = on_superseded
        self._lock = threading.Lock()
        self._entries: OrderedDict[int, _Entry] = OrderedDict()  # nonce -> entry, oldest first
        self._last_accepted: dict[int, int] = {}  # vehicle -> nonce of its latest accepted command
        # Acks that arrived before their command, by nonce (bounded like the log itself).
        self._early: OrderedDict[int, list[tuple[CommandAck, AckCheck | None]]] = OrderedDict()
        # Autopilot outcomes that arrived before the ack they follow, by (nonce, vehicle).
        self._early_outcomes: OrderedDict[tuple[int, int], ActionOutcome] = OrderedDict()
        self._own: OrderedDict[int, str] = OrderedDict()  # nonce this station sent -> operator
        self._plans: deque[PlanChange] = deque(maxlen=self.cfg.max_commands)
        self._own_plans: OrderedDict[int, tuple[str, str]] = OrderedDict()  # version -> who, what
        self._refused = _RefusedCounts()
        self._seq = 0
        self.version = 0
        """Bumped on every change (a renderer redraws only when it moved)."""
        self.refused_acks = 0
        """Acks that failed the check, or whose command never arrived (counted, not shown)."""
        self.duplicate_acks = 0
        """Verified acks from a vehicle that had already answered that command (ignored)."""
        self.duplicate_outcomes = 0
        """Outcomes of a command a vehicle had already reported on (ignored)."""

    @property
    def refused_commands(self) -> int:
        """Command attempts refused since the start (counted, never logged)."""
        with self._lock:
            return self._refused.total

    def refused_last_minute(self, now_ns: int) -> dict[str, int]:
        """Refused command attempts of the last minute per cause, most first."""
        with self._lock:
            return self._refused.last_minute(now_ns)

    def mark_own(self, nonce: int, operator: str = "") -> None:
        """`nonce` is a command this station is sending for `operator` (before it goes out)."""
        with self._lock:
            self._own[nonce] = operator
            while len(self._own) > self.cfg.max_own:
                self._own.popitem(last=False)
            entry = self._entries.get(nonce)
            if entry is not None:
                entry.own, entry.operator = True, operator

    def mark_own_plan(self, version: int, operator: str = "", what: str = "") -> None:
        """Plan `version` is one this station is pushing for `operator` (before it is applied);
        `what`: what changed."""
        with self._lock:
            self._own_plans[version] = (operator, what)
            while len(self._own_plans) > self.cfg.max_commands:
                self._own_plans.popitem(last=False)

    def on_plan(self, version: int, signer_id: int, summary: str, recv_ns: int) -> None:
        """The station follows plan `version` now (verified by its plan follower)."""
        with self._lock:
            own = self._own_plans.pop(version, None)
            self._seq += 1
            operator, what = own or ("", "")
            self._plans.append(
                PlanChange(
                    self._seq, recv_ns, version, signer_id, summary, own is not None, operator, what
                )
            )
            self.version += 1

    def plan_changes(self) -> list[PlanChange]:
        """Kept plan versions, newest first."""
        with self._lock:
            return list(reversed(self._plans))

    def on_command(
        self,
        command: Request,
        recv_ns: int,
        digest: bytes = b"",
        check: CommandCheck | None = None,
    ) -> bool:
        """`digest`: SHA-256 of the command's wire bytes (its acks are signed over it). `check`
        (keyed mode): a command it refuses is counted by cause, never logged. True if logged."""
        problem = check(command) if check is not None else None
        with self._lock:
            if problem is not None:
                self._refused.add(refusal_cause(problem), recv_ns)
                self.version += 1
                return False
            if command.nonce in self._entries:  # the same query seen twice (or resent)
                return False
            self._seq += 1
            own = command.nonce in self._own
            self._entries[command.nonce] = _Entry(
                self._seq,
                recv_ns,
                command,
                digest,
                own=own,
                signed=check is not None,
                operator=self._own.get(command.nonce) or "",
            )
            while len(self._entries) > self.cfg.max_commands:
                nonce, _ = self._entries.popitem(last=False)
                for vid in [v for v, n in self._last_accepted.items() if n == nonce]:
                    del self._last_accepted[vid]
            self.version += 1
            early = self._early.pop(command.nonce, [])
        # An ack can overtake its command on the mesh (it takes another path): apply it now.
        for ack, ack_check in early:
            self.on_ack(ack, recv_ns, ack_check)
        return True

    def on_ack(self, ack: CommandAck, recv_ns: int, check: AckCheck | None = None) -> None:
        notify: tuple[LoggedCommand, int, LoggedCommand] | None = None
        with self._lock:
            entry = self._entries.get(ack.nonce)
            if entry is None:  # not seen yet, or long gone: keep a few, briefly
                waiting = self._early.setdefault(ack.nonce, [])
                if len(waiting) < self.cfg.max_answers:
                    waiting.append((ack, check))
                while len(self._early) > self.cfg.max_commands:
                    _, dropped = self._early.popitem(last=False)
                    self.refused_acks += len(dropped)
                return
            if check is not None and check(ack, entry.command, entry.digest) is not None:
                self.refused_acks += 1
                return
            vid = ack.vehicle_id
            if vid in entry.answers:  # one answer per (vehicle, nonce): the first stands
                self.duplicate_acks += 1
                return
            if len(entry.answers) >= self.cfg.max_answers:
                entry.dropped_answers += 1
                return
            entry.answers[vid] = Answer(ack.result, ack.reason, ack.stamp_ns, ack.mode)
            self.version += 1
            if ack.result is not AckResult.ACCEPTED:
                return
            early_outcome = self._early_outcomes.pop((ack.nonce, vid), None)
            if early_outcome is not None:
                entry.done[vid] = early_outcome
            text = outcome_text(entry.command, ack.mode, None)
            if text is not None:  # a hold, a kill, a land on the ground: finished at once
                entry.finished[vid] = text
            if isinstance(entry.command, Mission):
                return  # an upload flies nothing: the vehicle's latest command still runs
            before = self._entries.get(self._last_accepted.get(vid, -1))
            if before is not None and before.seq > entry.seq:
                if not entry.ended(vid):  # this ack arrived late: already replaced
                    entry.superseded[vid] = before.seq
                return
            self._last_accepted[vid] = ack.nonce
            if before is not None and before is not entry and not before.ended(vid):
                before.superseded[vid] = entry.seq
                notify = (before.view(), vid, entry.view())
        if notify is not None and self.on_superseded is not None:
            self.on_superseded(*notify)

    def on_outcome(self, outcome: ActionOutcome) -> bool:
        """The autopilot's outcome of a command a vehicle accepted (an `ActionOutcome`, already
        verified like every event). False: no such command kept, that vehicle did not accept
        it, or it already reported this command's outcome (ignored)."""
        with self._lock:
            entry = self._entries.get(outcome.nonce)
            answer = entry.answers.get(outcome.vehicle_id) if entry is not None else None
            if answer is None:  # it overtook its ack (or command): keep it, bounded, for a while
                self._early_outcomes[(outcome.nonce, outcome.vehicle_id)] = outcome
                while len(self._early_outcomes) > self.cfg.max_answers:
                    self._early_outcomes.popitem(last=False)
                return False
            if answer.result is not AckResult.ACCEPTED or entry is None:
                return False
            if outcome.vehicle_id in entry.done:
                self.duplicate_outcomes += 1
                return False
            entry.done[outcome.vehicle_id] = outcome
            self.version += 1
            return True

    def on_state(self, state: VehicleState) -> None:
        """A vehicle's (verified) state: it may show that the vehicle finished its latest
        command. Cheap for every state of a large fleet: one lookup for most."""
        vid = state.vehicle_id
        with self._lock:
            entry = self._entries.get(self._last_accepted.get(vid, -1))
            if entry is None or vid in entry.finished or vid in entry.superseded:
                return
            answer = entry.answers.get(vid)
            if answer is None or state.stamp_ns <= answer.stamp_ns:
                return  # a state from before the vehicle took the command
            if entry.command.kind is CommandKind.GOTO_GLOBAL:
                # Its goal is in the vehicle's frame: done once seen flying there, then holding.
                if state.mode is Mode.GOTO:
                    entry.running[vid] = True
                    return
                if entry.running.get(vid) and state.mode is Mode.HOLDING:
                    entry.finished[vid] = "reached goal"
                    self.version += 1
                return
            text = outcome_text(entry.command, state.mode, state)
            if text is not None:
                entry.finished[vid] = text
                self.version += 1

    def name_of(self, nonce: int) -> str | None:
        """The command with this nonce as an operator reads it, if it is kept."""
        with self._lock:
            entry = self._entries.get(nonce)
            return None if entry is None else entry.view().describe()

    def entries(self) -> list[LoggedCommand]:
        """Kept commands, newest first."""
        with self._lock:
            return [e.view() for e in reversed(self._entries.values())]

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)


def progress_all(
    entry: LoggedCommand, now_ns: int, answer_timeout_s: float, present: Iterable[int] | None
) -> dict[int, Progress]:
    """Vehicle id -> its progress, for every vehicle `entry` concerns."""
    pres = set(present) if present is not None else None
    return {v: entry.progress(v, now_ns, answer_timeout_s, pres) for v in entry.vehicles()}
