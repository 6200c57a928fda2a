"""Per-member signatures: commands, acks, states and events, checked against the fleet roster.

Every vehicle and ground station holds its own Ed25519 key (trust/identity.py); the roster,
signed by the operator's fleet authority, says whose public key is which vehicle or station.

- Commands are signed by a STATION key (the command's `source_id` names it). A vehicle checks,
  in this order, and answers any refusal in its signed ack:
      1. tag present (all zeros = unsigned)         -> "unsigned command ..."
      2. source_id is a station of the roster        -> "unknown signer ..." (a vehicle's key,
                                                        revoked or never enrolled)
      3. signature over (fleet, command bytes)       -> "bad signature ..."
      4. |now - stamp_ns| <= max_skew_s              -> "stale command ..."
      5. (vehicle, nonce) not seen before            -> "replayed command ..."
- Acks are signed by the answering vehicle over the ack AND the SHA-256 of the command bytes it
  answers, so an ack cannot be replayed as the answer to another command.
- States and events are signed by their vehicle; comms/gate.py checks them on receipt.
- A newer roster (higher version, the authority's signature, this fleet) replaces the current
  one at once: a member left out is revoked from then on, without restarting anything.
- A process that hosts several vehicles (`covey agent --ids`) holds one FleetAuth per vehicle,
  each signing with its own vehicle's key, all sharing one roster (`FleetAuth.sibling`,
  `load_vehicle_auths`): a pushed roster is checked once and holds for all of them at once.

Only correctly signed commands reach the nonce cache, so an outsider cannot fill it. The cache
is bounded: when full, the oldest entry goes and its stamp becomes a floor below which every
command is refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import heapq
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from comms.doc_sync import RosterSyncConfig
from comms.member import command_digest
from comms.plan import FleetPlan

if TYPE_CHECKING:
    from comms.mesh import Mesh
from comms.schema import (
    TAG_BYTES,
    ActionOutcome,
    Command,
    CommandAck,
    Event,
    GuidanceTrace,
    Mission,
    PlanMessage,
    Role,
    Roster,
    StationHeartbeat,
    VehicleState,
)
from trust.identity import (
    FleetKeyError,
    MemberKey,
    check_roster,
    member_file_name,
    public_bytes,
    read_member_key,
    signed_message,
    verify,
)
from trust.links import LinkKeys
from trust.roster_sync import RosterSync

log = logging.getLogger(__name__)

ENV_KEY_FILE = "COVEY_FLEET_KEY_FILE"
ENV_KEY = "COVEY_FLEET_KEY"
"""No longer supported (a shared secret); refused with a pointer to `covey keygen`."""
_NO_TAG = bytes(TAG_BYTES)

__all__ = [
    "FleetAuth",
    "FleetKeyError",
    "command_digest",
    "host_signers",
    "load_auth",
    "load_vehicle_auths",
    "sign_plan",
]


class FleetAuth:
    """One member's signing key plus the current roster. Thread-safe.

    `clock_ns`: wall clock shared with the other side (NTP/GPS time; stamps cross machines).
    `max_skew_s`: a command stamped further than this from `clock_ns()` is refused as stale.
    `replay_window`: at most this many (vehicle, nonce) pairs are remembered.
    """

    def __init__(
        self,
        key: MemberKey,
        clock_ns: Callable[[], int] = time.time_ns,
        max_skew_s: float = 5.0,
        replay_window: int = 65536,
        rng: Callable[[int], int] = secrets.randbits,
        book: _RosterBook | None = None,
    ) -> None:
        """`book`: the roster shared with other FleetAuths of this process (use `sibling`)."""
        if not 0.0 < max_skew_s <= 3600.0:
            raise ValueError(f"max_skew_s={max_skew_s} must be within (0, 3600]")
        if not 1 <= replay_window <= 10_000_000:
            raise ValueError(f"replay_window={replay_window} must be within 1..10000000")
        self.key = key
        self.fleet = key.fleet
        self.role = key.role
        self.member_id = key.member_id
        self.clock_ns = clock_ns
        self.max_skew_ns = int(max_skew_s * 1e9)
        self.replay_window = replay_window
        self._rng = rng
        self._lock = threading.Lock()
        self._seen: set[tuple[int, int]] = set()
        self._by_stamp: list[tuple[int, int, int]] = []  # heap of (stamp_ns, vehicle, nonce)
        self._floor_ns = -1
        self._book = book if book is not None else _RosterBook(key)
        self._links: LinkKeys | None = None
        self.rejected = 0
        """How many commands this instance refused (read only)."""
        self.on_reject: Callable[[Command | Mission, int, str], None] | None = None
        """Called with (command, vehicle_id, reason) for every refused command, on the Zenoh
        thread; the agent publishes a SECURITY event from it. Exceptions are logged, not raised."""
        self.on_roster: Callable[[Roster], None] | None = None
        """Called after a newer roster was applied."""
        self.clock_note: Callable[[], str | None] | None = None
        """What this member knows of its clock against the stations' (trust/heartbeat.py), as a
        line ("vehicle clock +10.0 s against station 1 ..."), or None: a stale command's refusal
        names it, so that the operator learns the cause rather than a bare "stale"."""

    # -- identity and roster ---------------------------------------------------------------------
    @property
    def key_id(self) -> str:
        """A short fingerprint of this member's public key for logs."""
        return hashlib.sha256(public_bytes(self.key.private_key)).hexdigest()[:12]

    @property
    def roster(self) -> Roster:
        return self._book.roster

    def is_member(self, role: Role, member_id: int) -> bool:
        return (role, member_id) in self._book.keys

    def sibling(self, key: MemberKey) -> FleetAuth:
        """A FleetAuth for another member key held by this process (a host of several vehicles)
        with this one's clock and limits, sharing its roster: a roster applied through either is
        checked and applied once, for both. The newer of the two rosters is kept. Raises
        FleetKeyError if `key` belongs to another fleet or authority, or is not in the kept
        roster with its public key (revoked or replaced)."""
        self._book.join(key)
        return FleetAuth(
            key,
            clock_ns=self.clock_ns,
            max_skew_s=self.max_skew_ns / 1e9,
            replay_window=self.replay_window,
            rng=self._rng,
            book=self._book,
        )

    def shares_roster(self, other: FleetAuth) -> bool:
        """Whether `other` follows the same roster object as this one (made by `sibling`)."""
        return other._book is self._book

    def apply_roster(self, roster: Roster) -> str | None:
        """Replace the roster by a newer one from the authority; None if applied, else why not."""
        problem = self._book.apply(roster)
        if problem:
            return problem
        revoked = self._book.revoked(roster)
        if revoked:
            log.critical(
                "roster v%d REVOKES this process's %s: the fleet refuses what it signs from now on",
                roster.version,
                ", ".join(revoked),
            )
        else:
            log.warning(
                "applied fleet roster v%d (%d members)", roster.version, len(roster.members)
            )
        if self.on_roster is not None:
            try:
                self.on_roster(roster)
            except Exception:  # noqa: BLE001 - a listener bug must not undo a revocation
                log.exception("on_roster listener failed")
        return None

    def _sign(self, label: str, data: bytes) -> bytes:
        return self.key.private_key.sign(signed_message(label, self.fleet, data))

    def check_signature(
        self, role: Role, member_id: int, label: str, data: bytes, sig: bytes
    ) -> str | None:
        """None if `sig` is `role member_id`'s signature under the current roster, else why not."""
        book = self._book
        pub = book.keys.get((role, member_id))
        if pub is None:
            return (
                f"unknown signer: {role.name.lower()} {member_id} is not in fleet roster "
                f"v{book.roster.version} (revoked, never enrolled, or another fleet)"
            )
        if not verify(pub, sig, label, self.fleet, data):
            return f"bad signature: not made by {role.name.lower()} {member_id}'s key for fleet {self.fleet}"
        return None

    # -- commands --------------------------------------------------------------------------------
    def sign_command(self, cmd: Command) -> Command:
        """Stamp `cmd` with now, give it a nonce if it has none, name this station, and sign it."""
        return self._sign_request(cmd, "cmd")

    def sign_mission(self, mission: Mission) -> Mission:
        """As `sign_command`, for a mission upload (its own signature label: a mission's bytes
        can never pass as a command's, nor the other way)."""
        return self._sign_request(mission, "mission")

    def _sign_request(self, msg, label: str):
        if self.role is not Role.STATION:
            raise FleetKeyError(f"this is {self.key.name}'s key: only a station key signs commands")
        nonce = msg.nonce
        while not nonce:
            nonce = self._rng(64)
        stamped = dataclasses.replace(
            msg, nonce=nonce, stamp_ns=self.clock_ns(), source_id=self.member_id, tag=_NO_TAG
        )
        return dataclasses.replace(stamped, tag=self._sign(label, stamped.signed_bytes()))

    def check_command(self, cmd: Command, vehicle_id: int) -> str | None:
        """None if `cmd` may be executed by `vehicle_id`, else why not (for the ack)."""
        reason = self._check_command(cmd, vehicle_id)
        if reason is not None:
            self.refuse(cmd, vehicle_id, reason)
        return reason

    def check_mission(self, mission: Mission, vehicle_id: int) -> str | None:
        """As `check_command`, for a mission upload: the same checks in the same order (signed,
        a roster station's, fresh, never seen), sharing the command replay cache."""
        reason = self._check_command(mission, vehicle_id, "mission")
        if reason is not None:
            self.refuse(mission, vehicle_id, reason)
        return reason

    def refuse(self, cmd: Command | Mission, vehicle_id: int, reason: str) -> None:
        """Count and report one refused command (also used for commands sent to the wrong vehicle)."""
        with self._lock:
            self.rejected += 1
        log.warning(
            "vehicle %d refused %s from station %d: %s",
            vehicle_id,
            getattr(cmd.kind, "name", cmd.kind),
            cmd.source_id,
            reason,
        )
        if self.on_reject is not None:
            try:
                self.on_reject(cmd, vehicle_id, reason)
            except Exception:  # noqa: BLE001 - a listener bug must not turn a refusal into a crash
                log.exception("on_reject listener failed")

    def verify_command(self, cmd: Command | Mission, label: str = "cmd") -> str | None:
        """None if `cmd` is signed by a station of the roster and fresh, else why not: the
        checks a vehicle makes before its replay cache, which this leaves untouched (for an
        observer, such as a station's command log, that executes nothing). `label`: "mission"
        for a Mission."""
        if cmd.tag == _NO_TAG:
            return "unsigned command: this vehicle requires commands signed by a fleet station"
        problem = self.check_signature(
            Role.STATION, cmd.source_id, label, cmd.signed_bytes(), cmd.tag
        )
        if problem:
            return problem
        age_ns = self.clock_ns() - cmd.stamp_ns
        if abs(age_ns) > self.max_skew_ns:
            note = self._clock_note()
            if note:
                return f"stale command: {note}"
            return (
                f"stale command: stamped {age_ns / 1e9:+.1f} s from this vehicle's clock "
                f"(limit {self.max_skew_ns / 1e9:g} s)"
            )
        return None

    def _check_command(
        self, cmd: Command | Mission, vehicle_id: int, label: str = "cmd"
    ) -> str | None:
        problem = self.verify_command(cmd, label)
        if problem:
            return problem
        now = self.clock_ns()
        ident = (vehicle_id, cmd.nonce)
        with self._lock:
            # Forget what the skew check already refuses: the cache only spans the window.
            horizon = now - self.max_skew_ns
            while self._by_stamp and self._by_stamp[0][0] < horizon:
                _, v, n = heapq.heappop(self._by_stamp)
                self._seen.discard((v, n))
            if ident in self._seen:
                return f"replayed command: nonce {cmd.nonce:#x} was already used"
            if cmd.stamp_ns <= self._floor_ns:
                return "replayed command: older than the replay cache can vouch for"
            while len(self._seen) >= self.replay_window:
                stamp, v, n = heapq.heappop(self._by_stamp)
                self._seen.discard((v, n))
                self._floor_ns = max(self._floor_ns, stamp)
            self._seen.add(ident)
            heapq.heappush(self._by_stamp, (cmd.stamp_ns, vehicle_id, cmd.nonce))
        return None

    # -- acks ------------------------------------------------------------------------------------
    def sign_ack(self, ack: CommandAck, digest: bytes) -> CommandAck:
        """Sign `ack` as this vehicle, bound to the command whose SHA-256 is `digest`."""
        unsigned = dataclasses.replace(ack, tag=_NO_TAG)
        return dataclasses.replace(
            unsigned, tag=self._sign("ack", unsigned.signed_bytes() + digest)
        )

    def check_ack(self, ack: CommandAck, cmd: Command | Mission, digest: bytes) -> str | None:
        """None if `ack` is signed by vehicle `ack.vehicle_id` and answers exactly the command
        whose wire bytes hash to `digest`; else why not (a forged or replayed ack)."""
        said = f" (it said: {ack.result.name.lower()}" + (f": {ack.reason})" if ack.reason else ")")
        if ack.tag == _NO_TAG:
            return "forged ack: unsigned (the vehicle runs in open mode?)" + said
        if ack.nonce not in (cmd.nonce, 0):
            return f"forged ack: nonce {ack.nonce:#x} does not answer command nonce {cmd.nonce:#x}"
        problem = self.check_signature(
            Role.VEHICLE, ack.vehicle_id, "ack", ack.signed_bytes() + digest, ack.tag
        )
        if problem:
            return f"forged ack: {problem} (or it answers another command)" + said
        return None

    # -- states and events -----------------------------------------------------------------------
    @property
    def links(self) -> LinkKeys | None:
        """This vehicle's pairwise link keys (trust/links.py); None for a station."""
        if self._links is None and self.role is Role.VEHICLE:
            book = self._book
            self._links = LinkKeys(
                self.key.private_key,
                self.member_id,
                self.fleet,
                lambda vid: book.keys.get((Role.VEHICLE, vid)),
            )
        return self._links

    def sign_state(self, state: VehicleState, receivers: Iterable[int] = ()) -> VehicleState:
        """The state signed, and tagged for `receivers` (the sender's nearest neighbours' ids:
        trust/links.py) when this is a vehicle's key."""
        signed = state.signed_bytes()
        links = self.links
        tags = links.tags(signed, receivers) if links is not None else b""
        sig = self._sign("state", signed)
        if type(state) is not VehicleState:
            return dataclasses.replace(state, sig=sig, links=tags)
        # dataclasses.replace without its __init__ (a setattr per field: an agent signs every
        # state it sends), the same fields; and the bytes just signed kept for its encode()
        # (VehicleState.signed_bytes): what goes on the wire is what was signed, packed once
        out = object.__new__(VehicleState)
        out.__dict__.update(state.__dict__, sig=sig, links=tags, _signed=signed)
        return out

    def check_state(self, state: VehicleState, signed: bytes | None = None) -> str | None:
        """None if `state` is its vehicle's: by its link tag for this vehicle where it has a
        right one, else by its signature. `signed`: `state.signed_bytes()`, where the caller
        has them (a receiver: the first bytes of the payload it decoded `state` from; equal,
        tests/test_receive_fast.py); None: packed from `state`."""
        if signed is None:
            signed = state.signed_bytes()
        links = self.links if state.links else None
        if links is not None and links.check(signed, state.vehicle_id, state.links):
            return None
        return self.check_signature(Role.VEHICLE, state.vehicle_id, "state", signed, state.sig)

    def sign_event(self, event: Event) -> Event:
        return dataclasses.replace(event, sig=self._sign("event", event.signed_bytes()))

    def check_event(self, event: Event) -> str | None:
        return self.check_signature(
            Role.VEHICLE, event.vehicle_id, "event", event.signed_bytes(), event.sig
        )

    def sign_outcome(self, outcome: ActionOutcome) -> ActionOutcome:
        """Sign an autopilot outcome as its vehicle (under its own label: never an event's)."""
        return dataclasses.replace(outcome, sig=self._sign("outcome", outcome.signed_bytes()))

    def check_outcome(self, outcome: ActionOutcome) -> str | None:
        return self.check_signature(
            Role.VEHICLE, outcome.vehicle_id, "outcome", outcome.signed_bytes(), outcome.sig
        )

    def sign_trace(self, trace: GuidanceTrace) -> GuidanceTrace:
        return dataclasses.replace(trace, sig=self._sign("trace", trace.signed_bytes()))

    def check_trace(self, trace: GuidanceTrace) -> str | None:
        return self.check_signature(
            Role.VEHICLE, trace.vehicle_id, "trace", trace.signed_bytes(), trace.sig
        )

    # -- station heartbeats ----------------------------------------------------------------------
    def sign_heartbeat(self, heartbeat: StationHeartbeat) -> StationHeartbeat:
        """Sign a heartbeat as this station (trust/heartbeat.py); a vehicle's key never does."""
        if self.role is not Role.STATION or heartbeat.gcs_id != self.member_id:
            raise FleetKeyError(
                f"this is {self.key.name}'s key: it signs only station {self.member_id}'s "
                "heartbeats"
                if self.role is Role.STATION
                else f"this is {self.key.name}'s key: only a station key signs heartbeats"
            )
        return dataclasses.replace(heartbeat, sig=self._sign("hb", heartbeat.signed_bytes()))

    def check_heartbeat(self, heartbeat: StationHeartbeat) -> str | None:
        """None if station `gcs_id` of the current roster signed `heartbeat`, else why not."""
        if not heartbeat.sig:
            return "unsigned: a keyed member trusts only signed station heartbeats"
        return self.check_signature(
            Role.STATION, heartbeat.gcs_id, "hb", heartbeat.signed_bytes(), heartbeat.sig
        )

    # -- the fleet plan --------------------------------------------------------------------------
    def sign_plan(self, plan: FleetPlan) -> FleetPlan:
        """`plan` signed by this station (its signer becomes this station's id)."""
        if self.role is not Role.STATION:
            raise FleetKeyError(f"this is {self.key.name}'s key: only a station key signs plans")
        return sign_plan(self.key.private_key, plan, self.member_id)

    def check_plan(self, signer_id: int, signed: bytes, sig: bytes) -> str | None:
        """None if a plan's `signed` bytes (PlanHead.signed) carry the signature of the fleet
        authority (`signer_id` 0) or of station `signer_id` of the current roster, else why not."""
        if signer_id == 0:
            authority = Ed25519PublicKey.from_public_bytes(self.key.authority_public_key)
            if verify(authority, sig, PLAN_LABEL, self.fleet, signed):
                return None
            return f"bad signature: not made by fleet {self.fleet}'s authority key"
        return self.check_signature(Role.STATION, signer_id, PLAN_LABEL, signed, sig)

    def follow_roster(
        self,
        session: zenoh.Session,
        cfg: RosterSyncConfig,
        *,
        on_summary: Callable[[str], None],
        on_applied: Callable[[Roster], None],
    ) -> RosterSync:
        """This member's roster follower on `session` (trust/roster_sync.py); `Mesh` starts it
        and undeclares it when it closes."""
        return RosterSync(
            session, self.fleet, self, cfg, on_summary=on_summary, on_applied=on_applied
        )

    def _clock_note(self) -> str | None:
        if self.clock_note is None:
            return None
        try:
            return self.clock_note()
        except Exception:  # noqa: BLE001 - a note that fails must not change a refusal
            log.exception("clock_note failed")
            return None


PLAN_LABEL = "plan"
"""The signature label of a fleet plan (trust/identity.py signed_message)."""


def sign_plan(private_key: Ed25519PrivateKey, plan: FleetPlan, signer_id: int = 0) -> FleetPlan:
    """`plan` signed with `private_key` as `signer_id` (0: the fleet authority's key, N: station
    N's), over its wire bytes (comms/schema.py PlanMessage)."""
    unsigned = dataclasses.replace(plan, signer_id=signer_id, signature=b"")
    data = PlanMessage(unsigned).signed_bytes()
    sig = private_key.sign(signed_message(PLAN_LABEL, plan.fleet, data))
    return dataclasses.replace(unsigned, signature=sig)


class _RosterBook:
    """The current roster and its public keys, shared by the FleetAuths of one process (one per
    member key it holds), so that a roster pushed to the fleet is checked and applied once, at
    once, for all of them. Readers take `roster` and `keys` without a lock (each is replaced
    whole)."""

    def __init__(self, key: MemberKey) -> None:
        self.fleet = key.fleet
        self.authority_public_key = key.authority_public_key
        self.roster = key.roster
        self.keys = _public_keys(key.roster)
        self.held: list[MemberKey] = [key]
        self._lock = threading.Lock()

    def join(self, key: MemberKey) -> None:
        """Hold one more member key of this fleet and authority (the newer roster wins)."""
        if key.fleet != self.fleet:
            raise FleetKeyError(f"{key.name}'s key is for fleet {key.fleet!r}, not {self.fleet!r}")
        if key.authority_public_key != self.authority_public_key:
            raise FleetKeyError(
                f"{key.name}'s key was issued by another fleet authority than {self.held[0].name}'s"
            )
        if key.roster.version > self.roster.version:
            problem = self.apply(key.roster)
            if problem:
                raise FleetKeyError(f"{key.name}'s roster: {problem}")
        with self._lock:
            self.held.append(key)
        revoked = self.revoked(self.roster)
        if revoked:
            raise FleetKeyError(
                f"{', '.join(revoked)} not in fleet roster v{self.roster.version} with "
                "this key: revoked or replaced; ask the operator for a new key file"
            )

    def apply(self, roster: Roster) -> str | None:
        if roster.version <= self.roster.version:
            return f"roster v{roster.version} is not newer than v{self.roster.version}"
        problem = check_roster(roster, self.authority_public_key, self.fleet)
        if problem:
            return problem
        keys = _public_keys(roster)
        with self._lock:
            if roster.version <= self.roster.version:  # a concurrent newer one won
                return f"roster v{roster.version} is not newer than v{self.roster.version}"
            self.roster, self.keys = roster, keys
        return None

    def revoked(self, roster: Roster) -> list[str]:
        """The held members that `roster` leaves out or lists with another key."""
        with self._lock:
            held = list(self.held)
        out = []
        for key in held:
            entry = roster.member(key.role, key.member_id)
            if entry is None or entry.public_key != public_bytes(key.private_key):
                out.append(key.name)
        return out


def _public_keys(roster: Roster) -> dict[tuple[Role, int], Ed25519PublicKey]:
    return {
        (m.role, m.member_id): Ed25519PublicKey.from_public_bytes(m.public_key)
        for m in roster.members
    }


# -- loading -------------------------------------------------------------------------------------
def load_auth(
    key_file: str | None,
    env: Mapping[str, str] = os.environ,
    fleet: str | None = None,
    **kw: Any,
) -> FleetAuth | None:
    """A FleetAuth for the configured member key file, or None (open mode, said loudly once).

    Raises FleetKeyError when a key is configured but unusable (an empty path included): never
    fall back to open mode because of a typo or an empty variable."""
    if env.get(ENV_KEY):
        raise FleetKeyError(
            f"${ENV_KEY} (a shared fleet secret) is no longer supported: every member "
            f"has its own key file now (covey keygen); unset it and use --key-file"
        )
    path = key_file if key_file is not None else env.get(ENV_KEY_FILE)
    if path is None:
        log.warning(
            "OPEN MODE: no key file (--key-file or $%s); commands, states and events are NOT "
            "authenticated and anyone on the mesh can fly or impersonate these vehicles. "
            "Tests and simulator experiments only.",
            ENV_KEY_FILE,
        )
        return None
    key = read_member_key(path)
    if fleet is not None and key.fleet != fleet:
        raise FleetKeyError(
            f"key file {path} is for fleet {key.fleet!r}, but this process joins fleet {fleet!r}"
        )
    auth = FleetAuth(key, **kw)
    log.info(
        "keyed mode: %s of fleet %s (key %s, roster v%d)",
        key.name,
        key.fleet,
        auth.key_id,
        key.roster.version,
    )
    return auth


def fleet_auth_of(mesh: Mesh) -> FleetAuth | None:
    """The FleetAuth a keyed mesh holds (its `auth`, typed by comms as a MemberAuth), or None in
    open mode; a TypeError for any other signer, which covey's vehicles never hand a mesh."""
    auth = mesh.auth
    if auth is not None and not isinstance(auth, FleetAuth):
        raise TypeError(f"a vehicle's mesh must sign with a FleetAuth, got {type(auth).__name__}")
    return auth


def host_signers(
    ids: Iterable[int], mesh_auth: FleetAuth | None, auths: Mapping[int, FleetAuth] | None
) -> list[FleetAuth | None]:
    """The signer of each of a host's vehicles, in `ids` order: its own FleetAuth, or None for
    all in open mode. Raises ValueError unless every vehicle has its own key and the mesh's
    (which verifies what arrives and follows the roster) shares their roster, or, in open
    mode, the mesh has no key either (it would sign every vehicle's states as one member)."""
    ids = list(ids)
    if auths is None:
        if mesh_auth is not None:
            raise ValueError(
                "the mesh is keyed but the host got no vehicle keys: it would sign every "
                "vehicle's states with one member's key"
            )
        return [None] * len(ids)
    if set(auths) != set(ids):
        missing, extra = sorted(set(ids) - set(auths)), sorted(set(auths) - set(ids))
        raise ValueError(f"vehicle keys do not match the ids: missing {missing}, extra {extra}")
    for vid in ids:
        auth = auths[vid]
        if auth.role is not Role.VEHICLE or auth.member_id != vid:
            raise ValueError(f"the key given for vehicle {vid} is {auth.key.name}'s")
    if mesh_auth is None or not all(mesh_auth.shares_roster(a) for a in auths.values()):
        raise ValueError(
            "a keyed host needs a mesh keyed with one of its vehicles' keys (their shared "
            "roster is the one it checks and follows)"
        )
    return [auths[vid] for vid in ids]


def load_vehicle_auths(
    key_dir: str | os.PathLike[str],
    vehicle_ids: Iterable[int],
    fleet: str | None = None,
    **kw: Any,
) -> dict[int, FleetAuth]:
    """One FleetAuth per vehicle of a multi-vehicle host, from `key_dir/vehicle-<id>.key` (the
    names `covey keygen` writes), sharing one roster (the newest of their files'): vehicle id ->
    its FleetAuth, in the order given. Raises FleetKeyError naming the first file that is
    missing, unreadable, malformed, another member's, for another fleet or authority, or
    revoked: a host starts with every key it was asked for, or not at all."""
    if str(key_dir).strip() == "":
        raise FleetKeyError("the key directory path is empty (an unset variable?)")
    d = Path(key_dir).expanduser()
    if not d.is_dir():
        raise FleetKeyError(f"key directory {d} is not a directory (covey keygen writes one)")
    auths: dict[int, FleetAuth] = {}
    first: FleetAuth | None = None
    for vid in vehicle_ids:
        path = d / member_file_name(Role.VEHICLE, vid)
        key = read_member_key(path)
        if key.role is not Role.VEHICLE or key.member_id != vid:
            raise FleetKeyError(f"key file {path} is {key.name}'s key, not vehicle {vid}'s")
        if fleet is not None and key.fleet != fleet:
            raise FleetKeyError(
                f"key file {path} is for fleet {key.fleet!r}, but this process joins fleet "
                f"{fleet!r}"
            )
        if first is None:
            first = FleetAuth(key, **kw)
            auth = first
        else:
            try:
                auth = first.sibling(key)
            except FleetKeyError as exc:
                raise FleetKeyError(f"key file {path}: {exc}") from None
        auths[vid] = auth
    if first is not None:
        log.info(
            "keyed mode: %d vehicles of fleet %s, one key each from %s (roster v%d)",
            len(auths),
            first.fleet,
            d,
            first.roster.version,
        )
    return auths
