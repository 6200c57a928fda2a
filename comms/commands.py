"""Command results: what each vehicle answered to one command, and how to build commands.

A command goes out once (one Zenoh query, even to the whole fleet); each vehicle answers with a
CommandAck. The sender gets one `Outcome` per vehicle: accepted, rejected (with the vehicle's
reason), failed, timed out, or an error (bad signature, malformed ack).
"""

from __future__ import annotations

import enum
import secrets
from collections.abc import Callable
from dataclasses import dataclass

from comms.schema import AckResult, Command, CommandAck, Mission


class OutcomeStatus(enum.Enum):
    ACCEPTED = "accepted"
    REJECTED = "rejected"
    FAILED = "failed"
    TIMEOUT = "timeout"
    ERROR = "error"


@dataclass(frozen=True)
class Outcome:
    vehicle_id: int
    status: OutcomeStatus
    reason: str
    ack: CommandAck | None
    latency_s: float

    @staticmethod
    def from_ack(ack: CommandAck, latency_s: float) -> Outcome:
        status = {
            AckResult.ACCEPTED: OutcomeStatus.ACCEPTED,
            AckResult.REJECTED: OutcomeStatus.REJECTED,
            AckResult.FAILED: OutcomeStatus.FAILED,
        }[ack.result]
        return Outcome(ack.vehicle_id, status, ack.reason, ack, latency_s)


@dataclass(frozen=True)
class CommandResult:
    command: Command | Mission
    outcomes: dict[int, Outcome]
    errors: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        """True when at least one vehicle answered and every answer is ACCEPTED."""
        return bool(self.outcomes) and all(
            o.status is OutcomeStatus.ACCEPTED for o in self.outcomes.values()
        )

    def by_status(self, status: OutcomeStatus) -> list[int]:
        return sorted(v for v, o in self.outcomes.items() if o.status is status)

    def summary(self) -> str:
        parts = []
        for vid in sorted(self.outcomes):
            o = self.outcomes[vid]
            parts.append(f"{vid}: {o.status.value}" + (f" ({o.reason})" if o.reason else ""))
        return "; ".join(parts) or "no vehicle answered"


def new_nonce(rng: Callable[[int], int] = secrets.randbits) -> int:
    """A random 64-bit nonce (never 0, which marks an ack to an undecodable command)."""
    while True:
        n = rng(64)
        if n:
            return n
