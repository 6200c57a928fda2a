"""What the wire asks of a member's keys and of a radio link: the typed contracts between comms/
and the packages above it.

The mesh signs what it sends and checks what it receives, but the keys, the roster and the
signatures live in trust/ (trust/auth.py `FleetAuth` is the one implementation of `MemberAuth`),
which sits above comms/: so comms/ names only these Protocols, and trust/ fills them in. The same
for the radio-link emulation a receiver puts between the wire and its callback (`StateLink`:
comms/link.py `LinkEmulator`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable
from typing import Protocol

import zenoh

from comms.doc_sync import DocSync, RosterSyncConfig
from comms.gate import SignatureChecker
from comms.link import Deliver
from comms.schema import (
    ActionOutcome,
    Command,
    CommandAck,
    Event,
    GuidanceTrace,
    Mission,
    Role,
    Roster,
    RosterHead,
    VehicleState,
)


class FleetKeyError(ValueError):
    """A key, key file or roster could not be used; the message says why and how to fix it."""


def command_digest(payload: bytes) -> bytes:
    """SHA-256 of a command's wire bytes, as bound into the ack that answers it."""
    return hashlib.sha256(payload).digest()


class NamedKey(Protocol):
    """A member's key file, as far as messages name it (trust/identity.py `MemberKey`)."""

    @property
    def name(self) -> str:
        """ "vehicle 3", "station 1"."""
        ...


class MemberAuth(SignatureChecker, Protocol):
    """One member's signing key and the roster it checks others against (keyed mode); the
    gate's checks (comms/gate.py `SignatureChecker`) included."""

    @property
    def fleet(self) -> str:
        """The fleet the key belongs to."""
        ...

    @property
    def role(self) -> Role: ...

    @property
    def member_id(self) -> int: ...

    @property
    def key(self) -> NamedKey: ...

    def _sign(self, label: str, data: bytes) -> bytes:
        """This member's signature over `data` under `label` (comms/traffic.py's reports)."""
        ...

    def check_signature(
        self, role: Role, member_id: int, label: str, data: bytes, sig: bytes
    ) -> str | None:
        """None if `sig` is `role member_id`'s signature under the roster, else why not."""
        ...

    def sign_state(self, state: VehicleState, receivers: Iterable[int] = ()) -> VehicleState: ...

    def sign_event(self, event: Event) -> Event: ...

    def sign_outcome(self, outcome: ActionOutcome) -> ActionOutcome: ...

    def sign_trace(self, trace: GuidanceTrace) -> GuidanceTrace: ...

    def sign_command(self, cmd: Command) -> Command: ...

    def sign_mission(self, mission: Mission) -> Mission: ...

    def check_command(self, cmd: Command, vehicle_id: int) -> str | None: ...

    def verify_command(self, cmd: Command | Mission, label: str = "cmd") -> str | None:
        """Only the signature of a command or mission (no freshness, no replay cache): None if
        a roster station signed it, else why not (a station's command log checks others')."""
        ...

    def check_mission(self, mission: Mission, vehicle_id: int) -> str | None: ...

    def refuse(self, cmd: Command | Mission, vehicle_id: int, reason: str) -> None: ...

    def sign_ack(self, ack: CommandAck, digest: bytes) -> CommandAck: ...

    def check_ack(self, ack: CommandAck, cmd: Command | Mission, digest: bytes) -> str | None: ...

    def check_plan(self, signer_id: int, signed: bytes, sig: bytes) -> str | None:
        """None if a fleet plan's signature is the authority's or a station's, else why not."""
        ...

    def follow_roster(
        self,
        session: zenoh.Session,
        cfg: RosterSyncConfig,
        *,
        on_summary: Callable[[str], None],
        on_applied: Callable[[Roster], None],
    ) -> DocSync[RosterHead, Roster]:
        """Start following the fleet's roster on `session` (the Mesh keeps and closes it)."""
        ...


class StateLink(Protocol):
    """Stands between the wire and a receiver's callback: decides whether and when each state
    arrives (comms/link.py `LinkEmulator`: rate, loss, latency, range)."""

    def offer(self, state: VehicleState, recv_ns: int, deliver: Deliver) -> None:
        """Decide the fate of `state`; `deliver(state, t_ns)` is called now, later or never."""
        ...
