"""Following the fleet roster on the mesh: `RosterSync` is comms/doc_sync.py's `DocSync` over
`RosterDoc`, whose signature check is the fleet authority's Ed25519 key (a revocation reaches
every keyed member within a second).

Every keyed process (agent, station, multi-vehicle host) runs one `RosterSync` on
`covey/<fleet>/roster` (comms/keys.py): `Mesh` starts it through `FleetAuth.follow_roster`.
A newer roster is verified (the authority's signature over its signed bytes, about 1 ms for the
largest) before its members are decoded and it is applied.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable
from typing import Protocol

import zenoh
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from comms import keys
from comms.doc_sync import DocSync, RosterSyncConfig
from comms.schema import Roster, RosterHead
from trust.identity import MemberKey, verify


class RosterHolder(Protocol):
    """What the roster follower needs of a member (trust/auth.py `FleetAuth`): its key (the
    authority's public key is the trust anchor), the roster held, and a way to apply a newer one."""

    key: MemberKey

    @property
    def roster(self) -> Roster: ...

    def apply_roster(self, roster: Roster) -> str | None: ...


class RosterDoc:
    """The fleet roster as a `SignedDoc`: signed by the fleet authority, held by `auth`."""

    name = "roster"

    def __init__(self, fleet: str, auth: RosterHolder) -> None:
        self.key = keys.roster(fleet)
        self.auth = auth
        self._authority = Ed25519PublicKey.from_public_bytes(auth.key.authority_public_key)
        self._lock = threading.Lock()
        self._encoded: tuple[int, bytes] = (0, b"")

    def peek(self, data: bytes) -> RosterHead:
        return Roster.peek(data)

    def held_version(self) -> int:
        return self.auth.roster.version

    def genuine(self, head: RosterHead) -> str | None:
        if verify(self._authority, head.sig, "roster", head.fleet, head.signed):
            return None
        return "not signed by the fleet authority"

    def apply(self, data: bytes, head: RosterHead) -> tuple[Roster, str | None]:
        roster = Roster.decode(data)
        return roster, self.auth.apply_roster(roster)

    def held_bytes(self) -> bytes:
        roster = self.auth.roster
        with self._lock:
            version, data = self._encoded
        if version != roster.version:
            data = roster.encode()  # O(members): encode once per version, not per answer
            with self._lock:
                self._encoded = (roster.version, data)
        return data


class RosterSync(DocSync[RosterHead, Roster]):
    """One keyed member's roster follower (see the module docstring). Declared by `Mesh`;
    `undeclare()` stops it (the Mesh does, when it closes)."""

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        auth: RosterHolder,
        cfg: RosterSyncConfig = RosterSyncConfig(),
        *,
        on_summary: Callable[[str], None] | None = None,
        on_applied: Callable[[Roster], None] | None = None,
        mono_ns: Callable[[], int] = time.monotonic_ns,
        rng: random.Random | None = None,
    ) -> None:
        """`auth`: this member's trust.auth.FleetAuth (its roster is the one followed)."""
        self.auth = auth
        super().__init__(
            session,
            fleet,
            RosterDoc(fleet, auth),
            cfg,
            on_summary=on_summary,
            on_applied=on_applied,
            mono_ns=mono_ns,
            rng=rng,
        )
