"""Every command sent to the fleet, from any station, with each vehicle's answer.

Several stations (and several tabs of one station) can command one fleet. Each station observes
every command query on the mesh and every vehicle's ack copy (`Mesh.observe_commands`), and keeps
them here, so that every operator sees one truth: who sent what to whom, what each vehicle
answered, and which accepted command a later accepted one replaced on a vehicle ("superseded").

Pure and thread-safe: no viser, no Zenoh, no clock. Bounded: at most `max_commands` commands,
each with at most `max_answers` answers; a vehicle id only stays while a kept command refers to it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from comms.schema import AckResult, ActionOutcome, Command, CommandAck, CommandKind


@dataclass(frozen=True)
class CommandLogConfig:
    """How much of the fleet's command traffic a station keeps."""

    max_commands: int = 50
    """Newest commands kept; older ones are dropped."""
    max_answers: int = 1024
    """Answers kept per command (a broadcast to a large fleet); more are counted, not kept."""

    def __post_init__(self) -> None:
        if not 1 <= self.max_commands <= 100_000 or not 1 <= self.max_answers <= 100_000:
            raise ValueError("max_commands and max_answers must be within 1..100000")


@dataclass(frozen=True)
class Answer:
    """One vehicle's answer to one command."""

    result: AckResult
    reason: str


@dataclass(frozen=True)
class LoggedCommand:
    """One command as the station saw it, with what became of it on each vehicle."""

    seq: int
    """Order of arrival at this station (1, 2, ...)."""
    recv_ns: int
    command: Command
    answers: dict[int, Answer]
    """Vehicle id -> its answer (acks seen so far)."""
    superseded: dict[int, int]
    """Vehicle id -> seq of the later accepted command that replaced this one there."""
    dropped_answers: int = 0
    done: dict[int, ActionOutcome] = field(default_factory=dict)
    """Vehicle id -> how the autopilot's part ended (done, or failed with the reason); absent
    while it runs, and for commands with no autopilot part (e.g. a goto flown by the agent)."""

    @property
    def source_id(self) -> int:
        return self.command.source_id

    def describe(self) -> str:
        p, kind = self.command.params, self.command.kind
        if kind is CommandKind.TAKEOFF:
            what = f"takeoff to {p[0]:g} m"
        elif kind is CommandKind.GOTO_LOCAL:
            what = f"goto N {p[0]:g} E {p[1]:g} D {p[2]:g} m"
        elif kind is CommandKind.GOTO_GLOBAL:
            what = f"goto lat {p[0]:.6f} lon {p[1]:.6f} alt {p[2]:g} m"
        else:
            what = kind.name.lower()
        who = ",".join(map(str, self.command.targets)) if self.command.targets else "all"
        return f"{what} → {who}"


@dataclass
class _Entry:
    seq: int
    recv_ns: int
    command: Command
    digest: bytes = b""
    answers: dict[int, Answer] = field(default_factory=dict)
    superseded: dict[int, int] = field(default_factory=dict)
    dropped_answers: int = 0
    done: dict[int, ActionOutcome] = field(default_factory=dict)

    def view(self) -> LoggedCommand:
        return LoggedCommand(
            self.seq,
            self.recv_ns,
            self.command,
            dict(self.answers),
            dict(self.superseded),
            self.dropped_answers,
            dict(self.done),
        )


SupersededCallback = Callable[[LoggedCommand, int, LoggedCommand], None]
"""Called with (the earlier command, the vehicle, the later command) when a vehicle accepts a
command that replaces one it had accepted before."""

AckCheck = Callable[[CommandAck, Command, bytes], str | None]
"""Returns why an ack must not be believed for a command whose wire bytes hash to the digest
(a forged or replayed ack), or None."""


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
        self._seq = 0
        self.version = 0
        """Bumped on every change (a renderer redraws only when it moved)."""
        self.refused_acks = 0
        """Acks that failed the check, or whose command never arrived (counted, not shown)."""

    def on_command(self, command: Command, recv_ns: int, digest: bytes = b"") -> None:
        """`digest`: SHA-256 of the command's wire bytes (its acks are signed over it)."""
        with self._lock:
            if command.nonce in self._entries:  # the same query seen twice (or resent)
                return
            self._seq += 1
            self._entries[command.nonce] = _Entry(self._seq, recv_ns, command, digest)
            while len(self._entries) > self.cfg.max_commands:
                nonce, _ = self._entries.popitem(last=False)
                for vid in [v for v, n in self._last_accepted.items() if n == nonce]:
                    del self._last_accepted[vid]
            self.version += 1
            early = self._early.pop(command.nonce, [])
        # An ack can overtake its command on the mesh (it takes another path): apply it now.
        for ack, check in early:
            self.on_ack(ack, recv_ns, check)

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
            if vid not in entry.answers and len(entry.answers) >= self.cfg.max_answers:
                entry.dropped_answers += 1
                return
            entry.answers[vid] = Answer(ack.result, ack.reason)
            self.version += 1
            if ack.result is not AckResult.ACCEPTED:
                return
            early_outcome = self._early_outcomes.pop((ack.nonce, vid), None)
            if early_outcome is not None:
                entry.done[vid] = early_outcome
            before = self._entries.get(self._last_accepted.get(vid, -1))
            if before is not None and before.seq > entry.seq:
                entry.superseded[vid] = before.seq  # this ack arrived late: already replaced
                return
            self._last_accepted[vid] = ack.nonce
            if before is not None and before is not entry:
                before.superseded[vid] = entry.seq
                notify = (before.view(), vid, entry.view())
        if notify is not None and self.on_superseded is not None:
            self.on_superseded(*notify)

    def on_outcome(self, outcome: ActionOutcome) -> bool:
        """The autopilot's outcome of a command a vehicle accepted (an ACTION event, already
        verified like every event). False: no such command kept, or that vehicle did not accept
        it (ignored)."""
        with self._lock:
            entry = self._entries.get(outcome.nonce)
            answer = entry.answers.get(outcome.vehicle_id) if entry is not None else None
            if answer is None:  # it overtook its ack (or command): keep it, bounded, for a while
                self._early_outcomes[(outcome.nonce, outcome.vehicle_id)] = outcome
                while len(self._early_outcomes) > self.cfg.max_answers:
                    self._early_outcomes.popitem(last=False)
                return False
            if answer.result is not AckResult.ACCEPTED:
                return False
            entry.done[outcome.vehicle_id] = outcome
            self.version += 1
            return True

    def entries(self) -> list[LoggedCommand]:
        """Kept commands, newest first."""
        with self._lock:
            return [e.view() for e in reversed(self._entries.values())]

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
