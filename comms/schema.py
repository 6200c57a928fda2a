"""Every message covey puts on the wire, and its codec.

Fixed-layout little-endian structs, each starting with a type byte and a version byte, so that the
C firmware, the Python processes and recordings share the same bytes. `decode()` raises one typed
`DecodeError` for anything malformed: wrong length, unknown type or version, non-finite numbers,
out-of-range fields. Nothing else escapes a decoder.

Layouts (all little-endian, packed; `<` struct codes):

    VehicleState  type 1 v3  <BBHIQ3f3ff3fBBHfBBf [+ 64s]  70 bytes, 134 signed
        type, version, vehicle_id, seq, stamp_ns, pos_ned_m[3], vel_ned_m_s[3], heading_rad,
        goal_ned_m[3], mode, armed, flags, battery_pct, mission_item, mission_items,
        pos_sigma_m, [sig: Ed25519 of vehicle_id]   (v1, without the mission progress, and v2,
        without the position uncertainty, are refused with the version named)
    Command       type 2 v2  <BBQQHB3dIH + n*H + 64s  header 51 bytes + 2 per target + 64 tag
        type, version, nonce, stamp_ns, source_id, kind, params[3] (float64), seq, n_targets,
        targets[n_targets] (empty = the whole fleet), tag (Ed25519 of station source_id, or
        zeros in open mode)
    CommandAck    type 3 v2  <BBHQQBB96s64s           182 bytes
        type, version, vehicle_id, nonce, stamp_ns, result, mode, reason (utf-8, zero padded),
        tag (Ed25519 of vehicle_id over these bytes AND the SHA-256 of the command answered)
    Event         type 4 v1  <BBHQBB120s [+ 64s]      134 bytes, 198 signed
        type, version, vehicle_id, stamp_ns, severity, kind, text (utf-8, zero padded), [sig]
    ActionOutcome type 12 v1 <BBHQQBB + n + [64s]     22 + n bytes (n <= 96), 86 + n signed
        type, version, vehicle_id, nonce (of the command), stamp_ns, ok (0 failed, 1 done),
        n (detail length), detail (n bytes of utf-8), [sig: Ed25519 of vehicle_id]; on the
        vehicle's event key, next to its Events
    Roster        type 5 v1  <BB32sIQH + n*<BH32s + 64s  48 bytes + 35 per member + 64 sig
        type, version, fleet (ascii, zero padded), roster version, stamp_ns, n_members,
        members[n] (role, id, Ed25519 public key), sig (the fleet authority's Ed25519);
        at most MAX_ROSTER_BYTES; `Roster.peek` reads the header alone
    GuidanceTrace type 6 v1  <BBHIQd3dBH + n*<HId [+ 64s]  51 bytes + 14 per neighbour [+ 64]
        type, version, vehicle_id, state_seq, stamp_ns, heading_rad (float64),
        cmd_vel_ned_m_s[3] (float64), flags (TraceFlag), n_neighbours,
        neighbours[n] (vehicle id, seq of its state, age_s as float64), [sig]
    FeedBatch     type 7 v1  <BBIH + n*(<IB + 64|128 bytes)  8 bytes + 69 per entry (133 signed),
                                                             at most MAX_FEED_BYTES
        type, version, feed_seq, n_entries, entries[n] (entry_seq, state length, the state's
        bytes exactly as its vehicle published them: a VehicleState, signed or not)
    StationHeartbeat type 8 v1  <BBHIQ [+ 64s]       16 bytes, 80 signed
        type, version, gcs_id, seq, stamp_ns, [sig: Ed25519 of station gcs_id]
    PlanMessage   type 11 v1 <BB32sIQHBBB + fence + zones + rally + 64s  at most MAX_PLAN_BYTES
        type, version, fleet, plan version, stamp_ns, signer_id (0: the fleet authority, N:
        station N), flags (1: has a fence), n_zones, n_rally; fence: <ddH floor, ceiling (NaN:
        none), n + n*<dd vertices (north, east m); each zone: <B name length, name (utf-8), then
        as the fence; each rally point: <dddB north, east, alt m, name length, name; sig (the
        signer's Ed25519; zeros in open mode). `PlanMessage.peek` reads the header alone
    Mission       type 10 v1 <BBQQHIIHH + n*H + k*<BBddfff + 64s  34 + 2 per target + 30 per
                                                             item + 64, at most MAX_MISSION_BYTES
        type, version, nonce, stamp_ns, source_id, mission_id, mission_version, n_targets,
        n_items, targets[n], items[k] (kind, frame, x, y (float64: north_m/east_m or
        lat_deg/lon_deg), alt_m (up: above the origin for LOCAL, AMSL for GLOBAL), speed_m_s
        (0: cruise), hold_s), tag (Ed25519 of station source_id, as a Command's)
    TrafficReport type 9 v1  <BBBHIBBBQ3f3f [+ 64s]  44 bytes, 108 signed
        type, version, reporter_role, reporter_id, track_id, source, emitter_type, flags,
        stamp_ns, pos_ned_m[3], vel_ned_m_s[3], [sig: Ed25519 of the reporter (a station, or a
        vehicle relaying its autopilot's ADS-B)]
    PlanMessage   type 11 v1 <BB32sIQHBBB + fence + zones + rally + 64s  at most MAX_PLAN_BYTES
        type, version, fleet, plan version, stamp_ns, signer_id (0: the fleet authority, N:
        station N), flags (1: has a fence), n_zones, n_rally; fence: <ddH floor, ceiling (NaN:
        none), n + n*<dd vertices (north, east m); each zone: <B name length, name (utf-8), then
        as the fence; each rally point: <dddB north, east, alt m, name length, name; sig (the
        signer's Ed25519; zeros in open mode). `PlanMessage.peek` reads the header alone
    Mission       type 10 v1 <BBQQHIIHH + n*H + k*<BBddfff + 64s  34 + 2 per target + 30 per
                                                             item + 64, at most MAX_MISSION_BYTES
        type, version, nonce, stamp_ns, source_id, mission_id, mission_version, n_targets,
        n_items, targets[n], items[k] (kind, frame, x, y (float64: north_m/east_m or
        lat_deg/lon_deg), alt_m (up: above the origin for LOCAL, AMSL for GLOBAL), speed_m_s
        (0: cruise), hold_s), tag (Ed25519 of station source_id, as a Command's)

Signatures are made and checked in trust/auth.py; this module only carries their bytes.
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

from comms.plan import (
    MAX_NAME_BYTES,
    MAX_PLAN_VERTICES,
    MAX_RALLY_POINTS,
    MAX_ZONES,
    Fence,
    FleetPlan,
    RallyPoint,
    Zone,
)

SCHEMA_VERSION = 1
"""Version of VehicleState, Event, Roster and GuidanceTrace (the signature is an optional
trailer)."""
SIGNED_SCHEMA_VERSION = 2
"""Version of Command and CommandAck: v2 carries a 64-byte Ed25519 tag (v1 had HMAC-SHA256)."""
MAX_VEHICLE_ID = 65000
"""Vehicle ids are 1..MAX_VEHICLE_ID; 0 means 'none' (a ground station, or an undecodable sender)."""
MAX_TARGETS = 1024
REASON_BYTES = 96
EVENT_TEXT_BYTES = 120
OUTCOME_DETAIL_BYTES = 96
"""The longest detail of an ActionOutcome, in UTF-8 bytes (a longer one is cut)."""
TAG_BYTES = 64
"""An Ed25519 signature."""
LINK_TAG_BYTES = 8
"""A pairwise link tag on a state (trust/links.py): keyed BLAKE2b truncated to 64 bits."""
LINK_ENTRY_BYTES = 2 + LINK_TAG_BYTES
"""One entry of a state's link trailer: the receiving vehicle's id (u16), then its tag."""
MAX_LINK_TAGS = 32
"""A state carries link tags for at most this many receivers (its nearest neighbours)."""
PUBLIC_KEY_BYTES = 32
MAX_ROSTER_MEMBERS = 4096
MAX_ROSTER_BYTES = 48 + 35 * MAX_ROSTER_MEMBERS + TAG_BYTES
"""The largest Roster on the wire (143,472 bytes: a header, 4096 members, the signature).
Anything longer is refused before a byte of it is read (`Roster.peek`), and the shipped routers
pass nothing longer on the roster key (comms/zenoh_configs/)."""
FLEET_NAME_BYTES = 32
MAX_TRACE_NEIGHBOURS = 256
"""A guidance trace lists at most this many neighbours; a longer list is cut (TraceFlag.CUT).
The longest signed trace is then 3699 bytes: under the routers' 4 KiB message limit
(comms/zenoh_configs/)."""
MAX_TRACE_AGE_S = 3600.0
"""A neighbour sample older than this is no neighbour: a trace that says so is malformed."""
MAX_FEED_BYTES = 4096
"""The largest FeedBatch: the routers' message size limit (comms/zenoh_configs/). A process
whose feed is longer sends it as several batches (comms/feed.py)."""

TAKEOFF_ALT_RANGE_M = (0.5, 500.0)
LOCAL_HORIZONTAL_LIMIT_M = 100_000.0
LOCAL_DOWN_RANGE_M = (-10_000.0, 100.0)
GLOBAL_ALT_RANGE_M = (-500.0, 10_000.0)
POSITION_LIMIT_M = 1_000_000.0
SPEED_LIMIT_M_S = 1_000.0
POS_SIGMA_LIMIT_M = 1_000.0
"""Largest position uncertainty a state may carry (the C filter's COVEY_SAFETY_MAX_SIGMA_M)."""


class DecodeError(ValueError):
    """The bytes are not a valid covey message; the message says why."""


class MsgType(enum.IntEnum):
    VEHICLE_STATE = 1
    COMMAND = 2
    COMMAND_ACK = 3
    EVENT = 4
    ROSTER = 5
    GUIDANCE_TRACE = 6
    FEED_BATCH = 7
    STATION_HEARTBEAT = 8
    TRAFFIC_REPORT = 9
    MISSION = 10
    PLAN = 11
    ACTION_OUTCOME = 12
    RELAY_BATCH = 13


class Role(enum.IntEnum):
    """What a fleet member's key may do (trust/auth.py enforces it)."""

    VEHICLE = 1
    """Signs its own states, events and acks; can never command."""
    STATION = 2
    """Signs commands."""


class Mode(enum.IntEnum):
    """Flight mode of an agent's command state machine (agent/commands.py owns the transitions)."""

    LANDED = 0
    TAKING_OFF = 1
    HOLDING = 2
    GOTO = 3
    LANDING = 4
    RETURNING = 5
    KILLED = 6
    MISSION = 7
    """Flying an uploaded mission's items (agent/mission.py)."""


class StateFlag(enum.IntFlag):
    NONE = 0
    HAS_GOAL = 1
    FAILSAFE_GCS_LOST = 2
    FAILSAFE_LINK_LOST = 4
    NEIGHBOURS_STALE = 8
    GEOFENCE = 16
    OPEN_MODE = 32
    """Commands are not authenticated (simulator demo only)."""
    FILTER_ACTIVE = 64
    """The safety filter changed the policy's command this tick."""
    REPLAY = 128
    """Republished from a recording, not a live vehicle."""


class CommandKind(enum.IntEnum):
    TAKEOFF = 1  # params: alt_m
    LAND = 2
    GOTO_LOCAL = 3  # params: n_m, e_m, d_m
    GOTO_GLOBAL = 4  # params: lat_deg, lon_deg, alt_m
    HOLD = 5
    RETURN = 6
    KILL = 7
    MISSION_START = 8
    """Fly the uploaded mission from its first item."""
    MISSION_PAUSE = 9
    """Hold in place; the mission waits at its current item."""
    MISSION_RESUME = 10
    """Continue a paused mission's current item."""
    MISSION_ABORT = 11
    """Hold in place and drop the mission's progress (start flies it from item 1 again)."""
    MISSION_STATUS = 12
    """Change nothing; the ack's reason says the vehicle's mission and progress."""


class AckResult(enum.IntEnum):
    ACCEPTED = 0
    REJECTED = 1
    FAILED = 2


class Severity(enum.IntEnum):
    DEBUG = 0
    INFO = 1
    WARNING = 2
    ERROR = 3
    CRITICAL = 4


class EventKind(enum.IntEnum):
    STATUS = 0
    MODE_CHANGE = 1
    FAILSAFE = 2
    COMMAND = 3
    LINK_STATS = 4
    SECURITY = 5
    ACTION = 6
    """The autopilot's outcome of an accepted command: an `ActionOutcome` message shows as this
    kind. Events of this kind exist only in recordings made before that message (their text was
    `<nonce as 16 hex> done|failed: <detail>`); they are shown as plain text."""
    CLOCK = 7
    """The vehicle's clock against the stations' (`ClockReport` in the text)."""


_MODE_VALUES = frozenset(m.value for m in Mode)
_TWO_PI = 2 * math.pi


class TraceFlag(enum.IntFlag):
    NONE = 0
    DECIDED = 1
    """The policy decided in this tick (else guidance held its last decision)."""
    CUT = 2
    """The neighbour list was cut at MAX_TRACE_NEIGHBOURS: the trace cannot be replayed exactly."""


def _check_finite(name: str, *values: float) -> None:
    for v in values:
        if not math.isfinite(v):
            raise DecodeError(f"{name} must be finite, got {v}")


def _check_range(name: str, value: float, lo: float, hi: float) -> None:
    if not lo <= value <= hi:
        raise DecodeError(f"{name}={value} is outside [{lo}, {hi}]")


_E = TypeVar("_E", bound=enum.IntEnum)


def _enum(cls: type[_E], name: str, value: int) -> _E:
    try:
        return cls(value)
    except ValueError:
        raise DecodeError(f"{name}={value} is not a valid {cls.__name__}") from None


def _check_vehicle_id(name: str, vid: int, allow_zero: bool = False) -> None:
    lo = 0 if allow_zero else 1
    if not lo <= vid <= MAX_VEHICLE_ID:
        raise DecodeError(f"{name}={vid} is outside [{lo}, {MAX_VEHICLE_ID}]")


def _text_field(raw: bytes, name: str) -> str:
    text = raw.rstrip(b"\0")
    if b"\0" in text:
        raise DecodeError(f"{name} has bytes after its NUL padding")
    try:
        return text.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DecodeError(f"{name} is not valid UTF-8: {exc}") from None


def _fit_text(text: str, size: int) -> bytes:
    """Encode to UTF-8 and cut to `size` bytes without splitting a character. NUL pads the
    field on the wire, so a NUL in the text is sent as U+FFFD (it could not come back)."""
    raw = text.replace("\0", "\ufffd").encode("utf-8", errors="replace")  # lone surrogates: "?"
    if len(raw) <= size:
        return raw
    return raw[:size].decode("utf-8", errors="ignore").encode("utf-8")


def _header(data: bytes, expected: MsgType, version: int = SCHEMA_VERSION) -> None:
    if len(data) < 2:
        raise DecodeError(f"message too short for a header: {len(data)} bytes")
    if data[0] != expected:
        raise DecodeError(f"expected message type {expected.value}, got {data[0]}")
    if data[1] != version:
        raise DecodeError(
            f"unsupported {expected.name} version {data[1]} (this covey speaks {version})"
        )


def _check_sig(sig: bytes) -> None:
    if len(sig) not in (0, TAG_BYTES):
        raise DecodeError(f"signature must be empty or {TAG_BYTES} bytes, got {len(sig)}")


_LINK_IDS: dict[int, struct.Struct] = {}
"""Entry count -> the Struct that reads the receiver ids of that many link entries."""


def _link_ids(links: bytes) -> tuple[int, ...]:
    """The receiver ids of whole link entries (at most MAX_LINK_TAGS + 1 Structs are made)."""
    n = min(len(links) // LINK_ENTRY_BYTES, MAX_LINK_TAGS + 1)
    reader = _LINK_IDS.get(n)
    if reader is None:
        reader = _LINK_IDS[n] = struct.Struct("<" + f"H{LINK_TAG_BYTES}x" * n)
    return reader.unpack_from(links)


def link_receivers(links: bytes) -> list[int]:
    """The receiving vehicles' ids of a state's link trailer, in order."""
    if len(links) > (MAX_LINK_TAGS + 1) * LINK_ENTRY_BYTES:  # longer than any valid one
        return [
            int.from_bytes(links[k : k + 2], "little")
            for k in range(0, len(links), LINK_ENTRY_BYTES)
        ]
    return list(_link_ids(links))


def links_ok(links: bytes, sig: bytes) -> bool:
    """The fast test of a state's link trailer (`_check_links` says why not)."""
    n, rest = divmod(len(links), LINK_ENTRY_BYTES)
    if rest or n > MAX_LINK_TAGS or len(sig) != TAG_BYTES:
        return False
    ids = _link_ids(links)
    return not ids or (min(ids) >= 1 and max(ids) <= MAX_VEHICLE_ID)


def _check_links(links: bytes, sig: bytes) -> None:
    if not links:
        return
    n, rest = divmod(len(links), LINK_ENTRY_BYTES)
    if rest or n > MAX_LINK_TAGS:
        raise DecodeError(
            f"link tags must be at most {MAX_LINK_TAGS} entries of {LINK_ENTRY_BYTES} bytes, "
            f"got {len(links)} bytes"
        )
    if len(sig) != TAG_BYTES:
        raise DecodeError("link tags come only on a signed state")
    for rid in link_receivers(links):
        _check_vehicle_id("link tag receiver", rid)


_STATE_HEAD = struct.Struct("<BBHIQ")
"""A VehicleState's head: type, version, vehicle id, seq, stamp (`VehicleState.peek`)."""
_MODES = {int(m): m for m in Mode}
"""Mode by wire value (a dict lookup instead of the enum's call, on the decode path)."""
_STATE_FLAGS = tuple(StateFlag(i) for i in range(256))
"""StateFlag by wire value 0..255."""


@dataclass(frozen=True)
class VehicleState:
    """One vehicle's state, as it publishes it (latest wins)."""

    vehicle_id: int
    seq: int
    stamp_ns: int
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    heading_rad: float
    mode: Mode = Mode.LANDED
    armed: bool = False
    battery_pct: float = 100.0
    flags: StateFlag = StateFlag.NONE
    goal_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where guidance is flying to; meaningful only with StateFlag.HAS_GOAL."""
    sig: bytes = b""
    """Ed25519 signature of the vehicle over `signed_bytes()` (trust/auth.py); empty: unsigned."""
    mission_item: int = 0
    """The mission item being flown, from 1 (agent/mission.py); 0: none (no mission, not
    started, aborted); mission_items + 1: the mission is done."""
    mission_items: int = 0
    """How many items the vehicle's mission has (0: no mission)."""
    pos_sigma_m: float = 0.0
    """1-sigma of the horizontal position estimate, per axis, metres (PX4's eph, the GNSS
    receiver's accuracy, the simulator's drift); 0: exact or not reported. The separation
    filter keeps each pair this much further apart, scaled (policy.safety.pair_radius_m)."""
    links: bytes = b""
    """Pairwise link tags for the sender's nearest neighbours (trust/links.py): entries of
    LINK_ENTRY_BYTES (receiver id u16, tag), at most MAX_LINK_TAGS, only on a signed state. On
    the wire after the signature, as a count byte and the entries; covered by no signature (a
    receiver whose tag is missing or wrong checks the signature instead)."""

    TYPE: ClassVar[MsgType] = MsgType.VEHICLE_STATE
    VERSION: ClassVar[int] = 3
    """v2 added the mission progress (issue 36), v3 the position uncertainty (issue 35)."""
    _FMT: ClassVar[struct.Struct] = struct.Struct("<BBHIQ3f3ff3fBBHfBBf")

    def validate(self) -> None:
        """Raise DecodeError with the reason unless every field is within its limits. The first
        test is the fast path a valid state takes (a fleet host validates hundreds per tick);
        NaN fails every comparison in it, so anything doubtful gets the reasoned checks below."""
        p, v, g, lim, top = (
            self.pos_ned_m,
            self.vel_ned_m_s,
            self.goal_ned_m,
            POSITION_LIMIT_M,
            SPEED_LIMIT_M_S,
        )
        if (
            len(p) == len(v) == len(g) == 3
            and 1 <= self.vehicle_id <= MAX_VEHICLE_ID
            and 0 <= self.seq < 2**32
            and 0 <= self.stamp_ns < 2**64
            and -lim <= p[0] <= lim
            and -lim <= p[1] <= lim
            and -lim <= p[2] <= lim
            and -lim <= g[0] <= lim
            and -lim <= g[1] <= lim
            and -lim <= g[2] <= lim
            and -top <= v[0] <= top
            and -top <= v[1] <= top
            and -top <= v[2] <= top
            and -_TWO_PI <= self.heading_rad <= _TWO_PI
            and 0.0 <= self.battery_pct <= 100.0
            and self.mode in _MODE_VALUES
            and not int(self.flags) & ~0xFF
            and len(self.sig) in (0, TAG_BYTES)
            and 0 <= self.mission_items <= MAX_MISSION_ITEMS
            and 0 <= self.mission_item <= self.mission_items + 1
            and 0.0 <= self.pos_sigma_m <= POS_SIGMA_LIMIT_M
            and (not self.links or links_ok(self.links, self.sig))
        ):
            return
        self._validate_reasoned()

    def _validate_reasoned(self) -> None:
        """The reference checks, one reason each (what validate() falls back to)."""
        _check_vehicle_id("vehicle_id", self.vehicle_id)
        if not 0 <= self.seq < 2**32:
            raise DecodeError(f"seq={self.seq} does not fit 32 bits")
        if not 0 <= self.stamp_ns < 2**64:
            raise DecodeError(f"stamp_ns={self.stamp_ns} does not fit 64 bits")
        _check_finite("pos_ned_m", *self.pos_ned_m)
        _check_finite("vel_ned_m_s", *self.vel_ned_m_s)
        _check_finite("goal_ned_m", *self.goal_ned_m)
        _check_finite("heading_rad", self.heading_rad)
        _check_finite("battery_pct", self.battery_pct)
        for i, p in enumerate((*self.pos_ned_m, *self.goal_ned_m)):
            _check_range(f"position[{i}]", p, -POSITION_LIMIT_M, POSITION_LIMIT_M)
        for i, v in enumerate(self.vel_ned_m_s):
            _check_range(f"vel_ned_m_s[{i}]", v, -SPEED_LIMIT_M_S, SPEED_LIMIT_M_S)
        _check_range("heading_rad", self.heading_rad, -2 * math.pi, 2 * math.pi)
        _check_range("battery_pct", self.battery_pct, 0.0, 100.0)
        _enum(Mode, "mode", int(self.mode))
        if int(self.flags) & ~0xFF:
            raise DecodeError(f"flags={int(self.flags):#x} has unknown bits")
        if not 0 <= self.mission_items <= MAX_MISSION_ITEMS:
            raise DecodeError(
                f"mission_items={self.mission_items} is outside [0, {MAX_MISSION_ITEMS}]"
            )
        if not 0 <= self.mission_item <= self.mission_items + 1:
            raise DecodeError(
                f"mission_item={self.mission_item} is outside [0, {self.mission_items + 1}]"
            )
        _check_finite("pos_sigma_m", self.pos_sigma_m)
        _check_range("pos_sigma_m", self.pos_sigma_m, 0.0, POS_SIGMA_LIMIT_M)
        _check_sig(self.sig)
        _check_links(self.links, self.sig)

    def signed_bytes(self) -> bytes:
        """Every byte that the signature covers (the whole state but the signature). A state
        that FleetAuth.sign_state made keeps the bytes it signed (its fields cannot change:
        the class is frozen) and gives them again rather than packing them twice. (getattr:
        reading __dict__ would make it, and every field read after it slower.)"""
        kept: bytes | None = getattr(self, "_signed", None)
        if kept is not None:
            return kept
        return self._FMT.pack(
            self.TYPE,
            self.VERSION,
            self.vehicle_id,
            self.seq,
            self.stamp_ns,
            *self.pos_ned_m,
            *self.vel_ned_m_s,
            self.heading_rad,
            *self.goal_ned_m,
            int(self.mode),
            int(self.armed),
            int(self.flags),
            self.battery_pct,
            self.mission_item,
            self.mission_items,
            self.pos_sigma_m,
        )

    def encode(self) -> bytes:
        self.validate()
        links = self.links
        if links:
            count = len(links) // LINK_ENTRY_BYTES
            return b"".join((self.signed_bytes(), self.sig, bytes((count,)), links))
        return self.signed_bytes() + self.sig

    @classmethod
    def peek(cls, data: bytes) -> tuple[int, int, int, bool] | None:
        """(vehicle_id, seq, stamp_ns, signed) read from a state's head without decoding the rest,
        or None where `decode` would refuse the head (type, version, too short): a receiver
        chooses which of many states to decode (comms/heard.py). Nothing else is checked: a
        state is still decoded, whole, before anything trusts it."""
        if len(data) < cls._FMT.size or data[0] != cls.TYPE or data[1] != cls.VERSION:
            return None
        _, _, vid, seq, stamp_ns = _STATE_HEAD.unpack_from(data)
        return vid, seq, stamp_ns, len(data) > cls._FMT.size

    @classmethod
    def decode(cls, data: bytes) -> VehicleState:
        if len(data) < 2 or data[0] != cls.TYPE or data[1] != cls.VERSION:
            _header(data, cls.TYPE, cls.VERSION)  # raises, naming what is wrong
        signed_end = cls._FMT.size + TAG_BYTES
        links = b""
        if len(data) > signed_end:
            count = data[signed_end]
            if not 1 <= count <= MAX_LINK_TAGS or len(data) != (
                signed_end + 1 + count * LINK_ENTRY_BYTES
            ):
                raise DecodeError(
                    f"VehicleState must be {cls._FMT.size} bytes (+{TAG_BYTES} signed, + a count "
                    f"byte of 1..{MAX_LINK_TAGS} and that many {LINK_ENTRY_BYTES}-byte link "
                    f"tags), got {len(data)} with a count byte of {count}"
                )
            links = bytes(data[signed_end + 1 :])
        elif len(data) not in (cls._FMT.size, signed_end):
            raise DecodeError(
                f"VehicleState must be {cls._FMT.size} bytes (+{TAG_BYTES} signed), got {len(data)}"
            )
        # f: type, version, id, seq, stamp, pos[3], vel[3], heading, goal[3], mode, armed, flags, battery
        f = cls._FMT.unpack_from(data)
        if f[16] not in (0, 1):
            raise DecodeError(f"armed must be 0 or 1, got {f[16]}")
        if f[17] > 0xFF:
            raise DecodeError(f"flags={f[17]:#x} has unknown bits")
        mode = _MODES.get(f[15])
        if mode is None:
            mode = _enum(Mode, "mode", f[15])  # raises, naming it
        # Built without the frozen dataclass's __init__ (one setattr per field: a fleet host
        # decodes hundreds a tick); equal to cls(**fields) (tests/test_schema_fast.py), and
        # validated below as every state is.
        lim, top = POSITION_LIMIT_M, SPEED_LIMIT_M_S
        msg = object.__new__(cls)
        msg.__dict__.update(
            vehicle_id=f[2],
            seq=f[3],
            stamp_ns=f[4],
            pos_ned_m=f[5:8],
            vel_ned_m_s=f[8:11],
            heading_rad=f[11],
            mode=mode,
            armed=f[16] == 1,
            battery_pct=f[18],
            flags=_STATE_FLAGS[f[17]],
            goal_ned_m=f[12:15],
            sig=data[cls._FMT.size : signed_end],
            mission_item=f[19],
            mission_items=f[20],
            pos_sigma_m=f[21],
            links=links,
        )
        # `validate`'s fast test less what the wire format and the checks above already hold
        # (the tuples' lengths; seq, stamp and the mission counts unsigned and in range; mode,
        # flags, armed; the signature's length; the trailer's length and count, so `links_ok`
        # but its receiver ids): what passes it passes `validate`; anything else gets
        # `validate` itself, which says why (tests/test_receive_fast.py decodes random bytes
        # both ways). NaN fails every comparison.
        if not (
            1 <= f[2] <= MAX_VEHICLE_ID
            and -lim <= f[5] <= lim
            and -lim <= f[6] <= lim
            and -lim <= f[7] <= lim
            and -top <= f[8] <= top
            and -top <= f[9] <= top
            and -top <= f[10] <= top
            and -_TWO_PI <= f[11] <= _TWO_PI
            and -lim <= f[12] <= lim
            and -lim <= f[13] <= lim
            and -lim <= f[14] <= lim
            and 0.0 <= f[18] <= 100.0
            and f[20] <= MAX_MISSION_ITEMS
            and f[19] <= f[20] + 1
            and 0.0 <= f[21] <= POS_SIGMA_LIMIT_M
            and (not links or (min(ids := _link_ids(links)) >= 1 and max(ids) <= MAX_VEHICLE_ID))
        ):
            msg.validate()
        return msg


@dataclass(frozen=True)
class Command:
    """A ground-station command to one vehicle, a list of them, or the whole fleet."""

    kind: CommandKind
    nonce: int
    stamp_ns: int
    params: tuple[float, float, float] = (0.0, 0.0, 0.0)
    targets: tuple[int, ...] = ()
    """Vehicle ids this command is for; empty means every vehicle of the fleet."""
    source_id: int = 0
    """Who sent it (a ground station id); part of the signed bytes."""
    seq: int = 0
    tag: bytes = bytes(TAG_BYTES)
    """Ed25519 signature of station `source_id` over every byte before it (and the fleet name);
    zeros in open mode (trust/auth.py)."""

    TYPE: ClassVar[MsgType] = MsgType.COMMAND
    VERSION: ClassVar[int] = SIGNED_SCHEMA_VERSION
    _HEAD: ClassVar[struct.Struct] = struct.Struct("<BBQQHB3dIH")

    @staticmethod
    def takeoff(alt_m: float, **kw: Any) -> Command:
        return Command(kind=CommandKind.TAKEOFF, params=(alt_m, 0.0, 0.0), **kw)

    @staticmethod
    def goto_local(n_m: float, e_m: float, d_m: float, **kw: Any) -> Command:
        return Command(kind=CommandKind.GOTO_LOCAL, params=(n_m, e_m, d_m), **kw)

    @staticmethod
    def goto_global(lat_deg: float, lon_deg: float, alt_m: float, **kw: Any) -> Command:
        return Command(kind=CommandKind.GOTO_GLOBAL, params=(lat_deg, lon_deg, alt_m), **kw)

    def applies_to(self, vehicle_id: int) -> bool:
        return not self.targets or vehicle_id in self.targets

    def validate(self) -> None:
        _enum(CommandKind, "kind", int(self.kind))
        if not 0 <= self.nonce < 2**64 or not 0 <= self.stamp_ns < 2**64:
            raise DecodeError("nonce and stamp_ns must fit 64 bits")
        if not 0 <= self.seq < 2**32:
            raise DecodeError(f"seq={self.seq} does not fit 32 bits")
        _check_vehicle_id("source_id", self.source_id, allow_zero=True)
        if len(self.targets) > MAX_TARGETS:
            raise DecodeError(f"{len(self.targets)} targets, at most {MAX_TARGETS}")
        if len(set(self.targets)) != len(self.targets):
            raise DecodeError("targets contain duplicates")
        for t in self.targets:
            _check_vehicle_id("target", t)
        if len(self.tag) != TAG_BYTES:
            raise DecodeError(f"tag must be {TAG_BYTES} bytes, got {len(self.tag)}")
        p0, p1, p2 = self.params
        _check_finite(f"{CommandKind(self.kind).name} params", p0, p1, p2)
        kind = CommandKind(self.kind)
        if kind is CommandKind.TAKEOFF:
            _check_range("takeoff alt_m", p0, *TAKEOFF_ALT_RANGE_M)
            unused: tuple[float, ...] = (p1, p2)
        elif kind is CommandKind.GOTO_LOCAL:
            _check_range("goto north_m", p0, -LOCAL_HORIZONTAL_LIMIT_M, LOCAL_HORIZONTAL_LIMIT_M)
            _check_range("goto east_m", p1, -LOCAL_HORIZONTAL_LIMIT_M, LOCAL_HORIZONTAL_LIMIT_M)
            _check_range("goto down_m", p2, *LOCAL_DOWN_RANGE_M)
            unused = ()
        elif kind is CommandKind.GOTO_GLOBAL:
            _check_range("goto lat_deg", p0, -90.0, 90.0)
            _check_range("goto lon_deg", p1, -180.0, 180.0)
            _check_range("goto alt_m", p2, *GLOBAL_ALT_RANGE_M)
            unused = ()
        else:
            unused = (p0, p1, p2)
        if any(u != 0.0 for u in unused):
            raise DecodeError(f"{kind.name} takes fewer parameters; unused ones must be 0")

    def signed_bytes(self) -> bytes:
        """Every byte that the tag covers."""
        head = self._HEAD.pack(
            self.TYPE,
            self.VERSION,
            self.nonce,
            self.stamp_ns,
            self.source_id,
            int(self.kind),
            *self.params,
            self.seq,
            len(self.targets),
        )
        return head + struct.pack(f"<{len(self.targets)}H", *self.targets)

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.tag

    @classmethod
    def decode(cls, data: bytes) -> Command:
        _header(data, cls.TYPE, cls.VERSION)
        if len(data) < cls._HEAD.size + TAG_BYTES:
            raise DecodeError(f"Command too short: {len(data)} bytes")
        f = cls._HEAD.unpack_from(data)
        seq, n = f[9], f[10]
        expected = cls._HEAD.size + 2 * n + TAG_BYTES
        if n > MAX_TARGETS:
            raise DecodeError(f"{n} targets, at most {MAX_TARGETS}")
        if len(data) != expected:
            raise DecodeError(f"Command with {n} targets must be {expected} bytes, got {len(data)}")
        targets = struct.unpack_from(f"<{n}H", data, cls._HEAD.size)
        msg = cls(
            nonce=f[2],
            stamp_ns=f[3],
            source_id=f[4],
            kind=_enum(CommandKind, "kind", f[5]),
            params=f[6:9],
            seq=seq,
            targets=targets,
            tag=data[-TAG_BYTES:],
        )
        msg.validate()
        return msg


@dataclass(frozen=True)
class CommandAck:
    """One vehicle's answer to a command."""

    vehicle_id: int
    nonce: int
    stamp_ns: int
    result: AckResult
    reason: str = ""
    mode: Mode = Mode.LANDED
    """The vehicle's mode after handling the command."""
    tag: bytes = bytes(TAG_BYTES)
    """Ed25519 signature of `vehicle_id` over `signed_bytes()` and the answered command's
    SHA-256 (trust/auth.py): an ack cannot be replayed as the answer to another command."""

    TYPE: ClassVar[MsgType] = MsgType.COMMAND_ACK
    VERSION: ClassVar[int] = SIGNED_SCHEMA_VERSION
    _FMT: ClassVar[struct.Struct] = struct.Struct(f"<BBHQQBB{REASON_BYTES}s{TAG_BYTES}s")

    @property
    def accepted(self) -> bool:
        return self.result is AckResult.ACCEPTED

    def validate(self) -> None:
        _check_vehicle_id("vehicle_id", self.vehicle_id, allow_zero=True)
        if not 0 <= self.nonce < 2**64 or not 0 <= self.stamp_ns < 2**64:
            raise DecodeError("nonce and stamp_ns must fit 64 bits")
        _enum(AckResult, "result", int(self.result))
        _enum(Mode, "mode", int(self.mode))
        if len(self.tag) != TAG_BYTES:
            raise DecodeError(f"tag must be {TAG_BYTES} bytes, got {len(self.tag)}")

    def signed_bytes(self) -> bytes:
        return self._FMT.pack(
            self.TYPE,
            self.VERSION,
            self.vehicle_id,
            self.nonce,
            self.stamp_ns,
            int(self.result),
            int(self.mode),
            _fit_text(self.reason, REASON_BYTES),
            b"",
        )[:-TAG_BYTES]

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.tag

    @classmethod
    def decode(cls, data: bytes) -> CommandAck:
        _header(data, cls.TYPE, cls.VERSION)
        if len(data) != cls._FMT.size:
            raise DecodeError(f"CommandAck must be {cls._FMT.size} bytes, got {len(data)}")
        f = cls._FMT.unpack(data)
        msg = cls(
            vehicle_id=f[2],
            nonce=f[3],
            stamp_ns=f[4],
            result=_enum(AckResult, "result", f[5]),
            mode=_enum(Mode, "mode", f[6]),
            reason=_text_field(f[7], "reason"),
            tag=f[8],
        )
        msg.validate()
        return msg


@dataclass(frozen=True)
class Event:
    """Status text, mode changes, failsafe transitions and link statistics."""

    vehicle_id: int
    stamp_ns: int
    text: str
    severity: Severity = Severity.INFO
    kind: EventKind = EventKind.STATUS
    sig: bytes = b""
    """Ed25519 signature of vehicle `vehicle_id` over `signed_bytes()`; empty: unsigned."""

    TYPE: ClassVar[MsgType] = MsgType.EVENT
    _FMT: ClassVar[struct.Struct] = struct.Struct(f"<BBHQBB{EVENT_TEXT_BYTES}s")

    def validate(self) -> None:
        _check_vehicle_id("vehicle_id", self.vehicle_id, allow_zero=True)
        if not 0 <= self.stamp_ns < 2**64:
            raise DecodeError("stamp_ns must fit 64 bits")
        _enum(Severity, "severity", int(self.severity))
        _enum(EventKind, "kind", int(self.kind))
        _check_sig(self.sig)

    def signed_bytes(self) -> bytes:
        return self._FMT.pack(
            self.TYPE,
            SCHEMA_VERSION,
            self.vehicle_id,
            self.stamp_ns,
            int(self.severity),
            int(self.kind),
            _fit_text(self.text, EVENT_TEXT_BYTES),
        )

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.sig

    @classmethod
    def decode(cls, data: bytes) -> Event:
        _header(data, cls.TYPE)
        if len(data) not in (cls._FMT.size, cls._FMT.size + TAG_BYTES):
            raise DecodeError(
                f"Event must be {cls._FMT.size} bytes (+{TAG_BYTES} signed), got {len(data)}"
            )
        f = cls._FMT.unpack_from(data)
        msg = cls(
            vehicle_id=f[2],
            stamp_ns=f[3],
            severity=_enum(Severity, "severity", f[4]),
            kind=_enum(EventKind, "kind", f[5]),
            text=_text_field(f[6], "text"),
            sig=data[cls._FMT.size :],
        )
        msg.validate()
        return msg


@dataclass(frozen=True)
class ActionOutcome:
    """How the autopilot's part of an accepted command ended: done, or failed with the reason.

    A command is acked when the vehicle's mode machine accepts it; the autopilot's part runs
    after (agent/actions.py) and its outcome follows as this message, on the vehicle's event
    key, signed by the vehicle like its events (trust/auth.py `sign_outcome`). Recordings made
    before it existed carry outcomes as Events of kind ACTION: those are read and shown as
    plain events, and no command log takes them."""

    vehicle_id: int
    nonce: int
    """The nonce of the command whose autopilot part ended."""
    ok: bool
    detail: str = ""
    """What was done, or why it failed; at most OUTCOME_DETAIL_BYTES of UTF-8 on the wire (cut
    at a character boundary)."""
    stamp_ns: int = 0
    """The vehicle's clock when the part ended."""
    sig: bytes = b""
    """Ed25519 signature of vehicle `vehicle_id` over `signed_bytes()`; empty: unsigned."""

    TYPE: ClassVar[MsgType] = MsgType.ACTION_OUTCOME
    VERSION: ClassVar[int] = 1
    _FMT: ClassVar[struct.Struct] = struct.Struct("<BBHQQBB")

    @property
    def kind(self) -> EventKind:
        """Shown with the events of kind ACTION (the station's events panel)."""
        return EventKind.ACTION

    @property
    def severity(self) -> Severity:
        return Severity.INFO if self.ok else Severity.ERROR

    def validate(self) -> None:
        _check_vehicle_id("vehicle_id", self.vehicle_id)
        if not 0 <= self.nonce < 2**64 or not 0 <= self.stamp_ns < 2**64:
            raise DecodeError("nonce and stamp_ns must fit 64 bits")
        if not isinstance(self.ok, bool):
            raise DecodeError(f"ok must be a bool, got {self.ok!r}")
        _check_sig(self.sig)

    def signed_bytes(self) -> bytes:
        detail = _fit_text(self.detail, OUTCOME_DETAIL_BYTES)
        head = self._FMT.pack(
            self.TYPE,
            self.VERSION,
            self.vehicle_id,
            self.nonce,
            self.stamp_ns,
            int(self.ok),
            len(detail),
        )
        return head + detail

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.sig

    @classmethod
    def decode(cls, data: bytes) -> ActionOutcome:
        _header(data, cls.TYPE, cls.VERSION)
        size = cls._FMT.size
        if len(data) < size:
            raise DecodeError(f"ActionOutcome needs at least {size} bytes, got {len(data)}")
        f = cls._FMT.unpack_from(data)
        if f[5] not in (0, 1):
            raise DecodeError(f"ok={f[5]} must be 0 or 1")
        n = f[6]
        if n > OUTCOME_DETAIL_BYTES:
            raise DecodeError(f"detail length {n} is over {OUTCOME_DETAIL_BYTES} bytes")
        if len(data) not in (size + n, size + n + TAG_BYTES):
            raise DecodeError(
                f"ActionOutcome with {n} detail bytes must be {size + n} bytes "
                f"(+{TAG_BYTES} signed), got {len(data)}"
            )
        raw = data[size : size + n]
        if b"\0" in raw:
            raise DecodeError("detail holds a NUL byte")
        try:
            detail = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise DecodeError(f"detail is not valid UTF-8: {exc}") from None
        msg = cls(f[2], f[3], f[5] == 1, detail, f[4], data[size + n :])
        msg.validate()
        return msg


EventMessage = Event | ActionOutcome
"""What travels on a vehicle's event key (keys.event)."""


def decode_event_message(data: bytes | bytearray | memoryview) -> EventMessage:
    """An Event or an ActionOutcome, by its type byte; DecodeError for anything else."""
    data = bytes(data)
    if data[:1] == bytes([MsgType.ACTION_OUTCOME]):
        return ActionOutcome.decode(data)
    if data[:1] != bytes([MsgType.EVENT]):
        raise DecodeError(
            f"expected an Event or an ActionOutcome, got message type "
            f"{data[0] if data else 'none (empty)'}"
        )
    return Event.decode(data)


@dataclass(frozen=True)
class GuidanceTrace:
    """What an agent fed guidance in one tick and what it commanded, so that closed-loop replay
    (tools/closed_loop.py) can run the same policy on the same inputs. Published after the
    VehicleState of the same tick (`covey agent --trace-guidance`)."""

    vehicle_id: int
    state_seq: int
    """seq of the VehicleState published in the same tick (same pos, vel and goal)."""
    stamp_ns: int
    heading_rad: float
    """Heading passed to guidance (the published heading is the one after guidance)."""
    cmd_vel_ned_m_s: tuple[float, float, float]
    """The velocity guidance commanded."""
    neighbours: tuple[tuple[int, int, float], ...] = ()
    """(vehicle id, seq of its state, age in s) of every neighbour in guidance's snapshot."""
    complete: bool = True
    """False when the neighbour list was cut (TraceFlag.CUT)."""
    decided: bool = True
    """The policy decided in this tick (False: guidance held its last decision)."""
    sig: bytes = b""
    """Ed25519 signature of the vehicle over `signed_bytes()` (trust/auth.py); empty: unsigned."""

    TYPE: ClassVar[MsgType] = MsgType.GUIDANCE_TRACE
    _HEAD: ClassVar[struct.Struct] = struct.Struct("<BBHIQd3dBH")
    _NEIGHBOUR: ClassVar[struct.Struct] = struct.Struct("<HId")

    @classmethod
    def build(
        cls,
        vehicle_id: int,
        state_seq: int,
        stamp_ns: int,
        heading_rad: float,
        cmd_vel_ned_m_s,
        nbr_ids,
        nbr_seqs,
        nbr_ages_s,
        decided: bool = True,
    ) -> GuidanceTrace:
        """A trace from guidance's inputs (numpy values welcome); neighbours past
        MAX_TRACE_NEIGHBOURS are cut and the trace marked incomplete."""
        nbrs = tuple(
            (int(i), int(s), float(a))
            for i, s, a in zip(nbr_ids, nbr_seqs, nbr_ages_s, strict=True)
        )
        return cls(
            vehicle_id=int(vehicle_id),
            state_seq=int(state_seq),
            stamp_ns=int(stamp_ns),
            heading_rad=float(heading_rad),
            cmd_vel_ned_m_s=tuple(float(x) for x in cmd_vel_ned_m_s),  # type: ignore[arg-type]
            neighbours=nbrs[:MAX_TRACE_NEIGHBOURS],
            complete=len(nbrs) <= MAX_TRACE_NEIGHBOURS,
            decided=bool(decided),
        )

    @property
    def flags(self) -> TraceFlag:
        return (TraceFlag.DECIDED if self.decided else TraceFlag.NONE) | (
            TraceFlag.NONE if self.complete else TraceFlag.CUT
        )

    def validate(self) -> None:
        _check_vehicle_id("vehicle_id", self.vehicle_id)
        if not 0 <= self.state_seq < 2**32:
            raise DecodeError(f"state_seq={self.state_seq} does not fit 32 bits")
        if not 0 <= self.stamp_ns < 2**64:
            raise DecodeError("stamp_ns must fit 64 bits")
        _check_finite("heading_rad", self.heading_rad)
        _check_range("heading_rad", self.heading_rad, -2 * math.pi, 2 * math.pi)
        if len(self.cmd_vel_ned_m_s) != 3:
            raise DecodeError(f"cmd_vel_ned_m_s has {len(self.cmd_vel_ned_m_s)} axes, not 3")
        _check_finite("cmd_vel_ned_m_s", *self.cmd_vel_ned_m_s)
        for i, v in enumerate(self.cmd_vel_ned_m_s):
            _check_range(f"cmd_vel_ned_m_s[{i}]", v, -SPEED_LIMIT_M_S, SPEED_LIMIT_M_S)
        if len(self.neighbours) > MAX_TRACE_NEIGHBOURS:
            raise DecodeError(
                f"{len(self.neighbours)} neighbours, at most {MAX_TRACE_NEIGHBOURS} (cut the list)"
            )
        seen: set[int] = set()
        for vid, seq, age_s in self.neighbours:
            _check_vehicle_id("neighbour id", vid)
            if vid == self.vehicle_id:
                raise DecodeError(f"vehicle {vid} lists itself as its neighbour")
            if vid in seen:
                raise DecodeError(f"neighbour {vid} is listed twice")
            seen.add(vid)
            if not 0 <= seq < 2**32:
                raise DecodeError(f"neighbour {vid}: seq={seq} does not fit 32 bits")
            _check_finite(f"neighbour {vid} age_s", age_s)
            _check_range(f"neighbour {vid} age_s", age_s, 0.0, MAX_TRACE_AGE_S)
        _check_sig(self.sig)

    def signed_bytes(self) -> bytes:
        head = self._HEAD.pack(
            self.TYPE,
            SCHEMA_VERSION,
            self.vehicle_id,
            self.state_seq,
            self.stamp_ns,
            self.heading_rad,
            *self.cmd_vel_ned_m_s,
            int(self.flags),
            len(self.neighbours),
        )
        return head + b"".join(self._NEIGHBOUR.pack(*n) for n in self.neighbours)

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.sig

    @classmethod
    def decode(cls, data: bytes) -> GuidanceTrace:
        _header(data, cls.TYPE)
        if len(data) < cls._HEAD.size:
            raise DecodeError(f"GuidanceTrace too short: {len(data)} bytes")
        # f: type, version, id, state_seq, stamp, heading, cmd_vel[3], flags, n
        f = cls._HEAD.unpack_from(data)
        flags, n = f[9], f[10]
        if flags & ~int(TraceFlag.DECIDED | TraceFlag.CUT):
            raise DecodeError(f"flags={flags:#x} has unknown bits")
        if n > MAX_TRACE_NEIGHBOURS:
            raise DecodeError(f"{n} neighbours, at most {MAX_TRACE_NEIGHBOURS}")
        size = cls._HEAD.size + n * cls._NEIGHBOUR.size
        if len(data) not in (size, size + TAG_BYTES):
            raise DecodeError(
                f"GuidanceTrace with {n} neighbours must be {size} bytes (+{TAG_BYTES} signed), "
                f"got {len(data)}"
            )
        msg = cls(
            vehicle_id=f[2],
            state_seq=f[3],
            stamp_ns=f[4],
            heading_rad=f[5],
            cmd_vel_ned_m_s=f[6:9],
            neighbours=tuple(cls._NEIGHBOUR.iter_unpack(data[cls._HEAD.size : size])),
            complete=not flags & TraceFlag.CUT,
            decided=bool(flags & TraceFlag.DECIDED),
            sig=data[size:],
        )
        msg.validate()
        return msg


@dataclass(frozen=True)
class FeedEntry:
    """One vehicle's latest state in a FeedBatch."""

    entry_seq: int
    """How many entries of this vehicle its feed has carried, this one included (from 1): a
    receiver counts the entries it missed from the gaps (the station's link loss)."""
    state: bytes
    """A VehicleState's bytes exactly as its vehicle published them (signed or not). Decoded and
    checked by the receiver one entry at a time, so that one bad entry costs only itself."""


_STATE_SIZES = (VehicleState._FMT.size, VehicleState._FMT.size + TAG_BYTES)


@dataclass(frozen=True)
class FeedBatch:
    """The latest state of each vehicle of one process that published since its last batch: what
    a ground station hears instead of every state (comms/feed.py, docs/scaling.md)."""

    feed_seq: int
    """This batch's number in its process's feed (from 1, wrapping at 2**32)."""
    entries: tuple[FeedEntry, ...]
    """At least one; at most as many as fit MAX_FEED_BYTES."""

    TYPE: ClassVar[MsgType] = MsgType.FEED_BATCH
    _HEAD: ClassVar[struct.Struct] = struct.Struct("<BBIH")
    _ENTRY: ClassVar[struct.Struct] = struct.Struct("<IB")
    MAX_ENTRIES: ClassVar[int] = (MAX_FEED_BYTES - _HEAD.size) // (_ENTRY.size + _STATE_SIZES[0])
    """The most entries a batch can hold (unsigned states; fewer fit when they are signed)."""

    @classmethod
    def size(cls, state_sizes: list[int] | tuple[int, ...]) -> int:
        """Bytes of a batch of entries whose states have these sizes."""
        return cls._HEAD.size + cls._ENTRY.size * len(state_sizes) + sum(state_sizes)

    def validate(self) -> None:
        if not 0 <= self.feed_seq < 2**32:
            raise DecodeError(f"feed_seq={self.feed_seq} does not fit 32 bits")
        if not 1 <= len(self.entries) <= self.MAX_ENTRIES:
            raise DecodeError(f"{len(self.entries)} feed entries, must be 1..{self.MAX_ENTRIES}")
        for i, e in enumerate(self.entries):
            if not 0 <= e.entry_seq < 2**32:
                raise DecodeError(f"entry {i}: entry_seq={e.entry_seq} does not fit 32 bits")
            if len(e.state) not in _STATE_SIZES:
                raise DecodeError(
                    f"entry {i}: a state is {_STATE_SIZES[0]} or {_STATE_SIZES[1]} bytes, "
                    f"not {len(e.state)}"
                )
        size = self.size([len(e.state) for e in self.entries])
        if size > MAX_FEED_BYTES:
            raise DecodeError(f"FeedBatch of {size} bytes, at most {MAX_FEED_BYTES}")

    def encode(self) -> bytes:
        self.validate()
        head = self._HEAD.pack(self.TYPE, SCHEMA_VERSION, self.feed_seq, len(self.entries))
        return head + b"".join(
            self._ENTRY.pack(e.entry_seq, len(e.state)) + e.state for e in self.entries
        )

    @classmethod
    def decode(cls, data: bytes) -> FeedBatch:
        _header(data, cls.TYPE)
        if not cls._HEAD.size <= len(data) <= MAX_FEED_BYTES:
            raise DecodeError(
                f"FeedBatch must be {cls._HEAD.size}..{MAX_FEED_BYTES} bytes, got {len(data)}"
            )
        _, _, feed_seq, n = cls._HEAD.unpack_from(data)
        if not 1 <= n <= cls.MAX_ENTRIES:
            raise DecodeError(f"{n} feed entries, must be 1..{cls.MAX_ENTRIES}")
        entries, at = [], cls._HEAD.size
        for i in range(n):
            if at + cls._ENTRY.size > len(data):
                raise DecodeError(f"FeedBatch of {len(data)} bytes ends inside entry {i} of {n}")
            entry_seq, length = cls._ENTRY.unpack_from(data, at)
            at += cls._ENTRY.size
            if length not in _STATE_SIZES:
                raise DecodeError(
                    f"entry {i}: a state is {_STATE_SIZES[0]} or {_STATE_SIZES[1]} bytes, "
                    f"not {length}"
                )
            if at + length > len(data):
                raise DecodeError(f"FeedBatch of {len(data)} bytes ends inside entry {i} of {n}")
            entries.append(FeedEntry(entry_seq, data[at : at + length]))
            at += length
        if at != len(data):
            raise DecodeError(f"FeedBatch has {len(data) - at} bytes after its {n} entries")
        return cls(feed_seq, tuple(entries))


MAX_STATE_BYTES = VehicleState._FMT.size + TAG_BYTES + 1 + MAX_LINK_TAGS * LINK_ENTRY_BYTES
"""The longest VehicleState on the wire: signed, with the most link tags."""


@dataclass(frozen=True)
class RelayBatch:
    """The states a router's cell relay heard in one block of cells since its last batch, exactly
    as their vehicles published them (comms/relay.py). Sent each relay period to each vehicle
    that wants the block, and empty now and then while the block is quiet: a relay that still
    sends is one that still relays. Each state is decoded and checked by the receiver as one on
    its own key would be."""

    relay_seq: int
    """This batch's number on its block (wrapping at 2**32)."""
    states: tuple[bytes, ...]
    """At most as many as fit MAX_FEED_BYTES; none: the relay is there, the block was quiet."""

    TYPE: ClassVar[MsgType] = MsgType.RELAY_BATCH
    _HEAD: ClassVar[struct.Struct] = struct.Struct("<BBIH")
    _LEN: ClassVar[struct.Struct] = struct.Struct("<H")

    @classmethod
    def size(cls, state_sizes: list[int] | tuple[int, ...]) -> int:
        return cls._HEAD.size + cls._LEN.size * len(state_sizes) + sum(state_sizes)

    def validate(self) -> None:
        if not 0 <= self.relay_seq < 2**32:
            raise DecodeError(f"relay_seq={self.relay_seq} does not fit 32 bits")
        for i, state in enumerate(self.states):
            if not 2 <= len(state) <= MAX_STATE_BYTES:
                raise DecodeError(f"state {i}: {len(state)} bytes, must be 2..{MAX_STATE_BYTES}")
        size = self.size([len(s) for s in self.states])
        if size > MAX_FEED_BYTES:
            raise DecodeError(f"RelayBatch of {size} bytes, at most {MAX_FEED_BYTES}")

    def encode(self) -> bytes:
        self.validate()
        head = self._HEAD.pack(self.TYPE, SCHEMA_VERSION, self.relay_seq, len(self.states))
        return head + b"".join(self._LEN.pack(len(s)) + s for s in self.states)

    @classmethod
    def decode(cls, data: bytes) -> RelayBatch:
        _header(data, cls.TYPE)
        if not cls._HEAD.size <= len(data) <= MAX_FEED_BYTES:
            raise DecodeError(
                f"RelayBatch must be {cls._HEAD.size}..{MAX_FEED_BYTES} bytes, got {len(data)}"
            )
        _, _, relay_seq, n = cls._HEAD.unpack_from(data)
        states, at = [], cls._HEAD.size
        end, len_size, read_len = len(data), cls._LEN.size, cls._LEN.unpack_from
        for i in range(n):
            if at + len_size > end:
                raise DecodeError(f"RelayBatch of {len(data)} bytes ends inside state {i} of {n}")
            (length,) = read_len(data, at)
            at += len_size
            if not 2 <= length <= MAX_STATE_BYTES or at + length > end:
                raise DecodeError(
                    f"RelayBatch state {i} of {n}: {length} bytes, must be 2..{MAX_STATE_BYTES} "
                    f"and within the batch's {len(data)}"
                )
            states.append(data[at : at + length])
            at += length
        if at != end:
            raise DecodeError(f"RelayBatch has {len(data) - at} bytes after its {n} states")
        return cls(relay_seq, tuple(states))


@dataclass(frozen=True)
class StationHeartbeat:
    """A ground station's sign of life, a few times a second (trust/heartbeat.py). Signed by the
    station in keyed mode: the station-lost failsafe trusts only these, never a liveliness token,
    and members estimate their clock's offset to the stations from `stamp_ns`."""

    gcs_id: int
    seq: int
    """This station's heartbeat count since it started (wrapping at 2**32)."""
    stamp_ns: int
    """The station's wall clock when it sent this heartbeat."""
    sig: bytes = b""
    """Ed25519 signature of station `gcs_id` over `signed_bytes()` (trust/auth.py); empty:
    unsigned (open mode)."""

    TYPE: ClassVar[MsgType] = MsgType.STATION_HEARTBEAT
    _FMT: ClassVar[struct.Struct] = struct.Struct("<BBHIQ")

    def validate(self) -> None:
        _check_vehicle_id("gcs_id", self.gcs_id)
        if not 0 <= self.seq < 2**32:
            raise DecodeError(f"seq={self.seq} does not fit 32 bits")
        if not 0 <= self.stamp_ns < 2**64:
            raise DecodeError(f"stamp_ns={self.stamp_ns} does not fit 64 bits")
        _check_sig(self.sig)

    def signed_bytes(self) -> bytes:
        return self._FMT.pack(self.TYPE, SCHEMA_VERSION, self.gcs_id, self.seq, self.stamp_ns)

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.sig

    @classmethod
    def decode(cls, data: bytes) -> StationHeartbeat:
        _header(data, cls.TYPE)
        if len(data) not in (cls._FMT.size, cls._FMT.size + TAG_BYTES):
            raise DecodeError(
                f"StationHeartbeat must be {cls._FMT.size} bytes (+{TAG_BYTES} signed), "
                f"got {len(data)}"
            )
        _, _, gcs_id, seq, stamp_ns = cls._FMT.unpack_from(data)
        msg = cls(gcs_id, seq, stamp_ns, data[cls._FMT.size :])
        msg.validate()
        return msg


class TrafficSource(enum.IntEnum):
    """Where a traffic report comes from."""

    ADSB = 1
    """An ADS-B (or FLARM) receiver on a vehicle's autopilot."""
    REMOTE_ID = 2
    """A Remote ID broadcast heard by a receiver."""
    MANUAL = 3
    """Entered by an operator (a vehicle flown by hand that the station tracks)."""
    SIM = 4
    """A simulated intruder (`covey intruder`)."""


class TrafficFlag(enum.IntFlag):
    NONE = 0
    MANNED = 1
    """A manned aircraft: covey keeps the larger separation from it."""


MAX_TRAFFIC_TRACK_ID = 0xFFFFFFFF
"""Track ids are 32-bit: an ADS-B ICAO address (24 bits), or one a reporter assigns."""


@dataclass(frozen=True)
class TrafficReport:
    """One vehicle that is not a covey member (it does not cooperate), as a station or a
    vehicle's receiver saw it (agent/traffic.py). Agents treat it as a non-cooperative
    neighbour; in keyed mode only a roster member's signed report counts (docs/sky.md)."""

    reporter_role: Role
    reporter_id: int
    """The station (or vehicle) that reports it, and whose key signs it."""
    track_id: int
    """Which traffic this is, per reporter: an ICAO address for ADS-B."""
    source: TrafficSource
    stamp_ns: int
    """When the position was true, on the reporter's wall clock."""
    pos_ned_m: tuple[float, float, float]
    """In the fleet's local NED frame."""
    vel_ned_m_s: tuple[float, float, float]
    emitter_type: int = 0
    """ADS-B emitter category (MAVLink ADSB_EMITTER_TYPE, 0..19; 0: no information)."""
    flags: TrafficFlag = TrafficFlag.NONE
    sig: bytes = b""
    """Ed25519 signature of the reporter over `signed_bytes()`; empty: unsigned (open mode)."""

    TYPE: ClassVar[MsgType] = MsgType.TRAFFIC_REPORT
    _FMT: ClassVar[struct.Struct] = struct.Struct("<BBBHIBBBQ3f3f")

    def validate(self) -> None:
        _enum(Role, "reporter_role", self.reporter_role)
        _check_vehicle_id("reporter_id", self.reporter_id)
        if not 0 <= self.track_id <= MAX_TRAFFIC_TRACK_ID:
            raise DecodeError(f"track_id={self.track_id} does not fit 32 bits")
        _enum(TrafficSource, "source", self.source)
        if not 0 <= self.emitter_type <= 19:
            raise DecodeError(f"emitter_type={self.emitter_type} is outside [0, 19]")
        if not 0 <= int(self.flags) <= int(TrafficFlag.MANNED):
            raise DecodeError(f"flags={int(self.flags)} has unknown bits")
        if not 0 <= self.stamp_ns < 2**64:
            raise DecodeError(f"stamp_ns={self.stamp_ns} does not fit 64 bits")
        if len(self.pos_ned_m) != 3 or len(self.vel_ned_m_s) != 3:
            raise DecodeError("pos_ned_m and vel_ned_m_s must have 3 components")
        _check_finite("traffic pos_ned_m", *self.pos_ned_m)
        _check_finite("traffic vel_ned_m_s", *self.vel_ned_m_s)
        for v in self.pos_ned_m:
            _check_range("traffic pos_ned_m", v, -POSITION_LIMIT_M, POSITION_LIMIT_M)
        for v in self.vel_ned_m_s:
            _check_range("traffic vel_ned_m_s", v, -SPEED_LIMIT_M_S, SPEED_LIMIT_M_S)
        _check_sig(self.sig)

    @property
    def manned(self) -> bool:
        return bool(self.flags & TrafficFlag.MANNED)

    def signed_bytes(self) -> bytes:
        return self._FMT.pack(
            self.TYPE,
            SCHEMA_VERSION,
            self.reporter_role,
            self.reporter_id,
            self.track_id,
            self.source,
            self.emitter_type,
            self.flags,
            self.stamp_ns,
            *self.pos_ned_m,
            *self.vel_ned_m_s,
        )

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.sig

    @classmethod
    def decode(cls, data: bytes) -> TrafficReport:
        _header(data, cls.TYPE)
        if len(data) not in (cls._FMT.size, cls._FMT.size + TAG_BYTES):
            raise DecodeError(
                f"TrafficReport must be {cls._FMT.size} bytes (+{TAG_BYTES} signed), "
                f"got {len(data)}"
            )
        f = cls._FMT.unpack_from(data)
        msg = cls(
            _enum(Role, "reporter_role", f[2]),
            f[3],
            f[4],
            _enum(TrafficSource, "source", f[5]),
            f[8],
            tuple(f[9:12]),
            tuple(f[12:15]),
            f[6],
            TrafficFlag(f[7]) if 0 <= f[7] <= int(TrafficFlag.MANNED) else f[7],
            data[cls._FMT.size :],
        )
        msg.validate()
        return msg


@dataclass(frozen=True)
class ClockReport:
    """A vehicle's clock offset to a station, as its agent estimates it from the station's
    signed heartbeats (trust/heartbeat.py). It travels as a signed Event of kind CLOCK whose
    text is `clock <+s.s> s against station <id>` (` ok` appended once it is back within the
    limit), so that the ground station can show the offset as a health problem."""

    vehicle_id: int
    offset_s: float
    """This vehicle's clock minus the station's, in seconds (positive: the vehicle is ahead)."""
    gcs_id: int
    ok: bool = False
    """The offset is within the freshness window again (the report that ends a problem)."""

    def to_event(self, stamp_ns: int) -> Event:
        text = f"clock {self.offset_s:+.1f} s against station {self.gcs_id}" + (
            " ok" if self.ok else ""
        )
        severity = Severity.INFO if self.ok else Severity.ERROR
        return Event(self.vehicle_id, stamp_ns, text, severity, EventKind.CLOCK)

    @classmethod
    def from_event(cls, event: Event) -> ClockReport:
        """The report a CLOCK event carries; DecodeError says what is wrong with it."""
        if event.kind is not EventKind.CLOCK:
            raise DecodeError(f"a clock report needs a CLOCK event, got {event.kind.name}")
        words = event.text.split(" ")
        if len(words) not in (6, 7) or words[:1] + words[2:5] != [
            "clock",
            "s",
            "against",
            "station",
        ]:
            raise DecodeError(
                f"clock report text must be 'clock <s> s against station <id>', got "
                f"{event.text[:40]!r}"
            )
        if len(words) == 7 and words[6] != "ok":
            raise DecodeError(f"clock report ends in {words[6]!r}, not 'ok'")
        try:
            offset_s, gcs_id = float(words[1]), int(words[5])
        except ValueError:
            raise DecodeError(f"clock report numbers do not parse: {event.text[:40]!r}") from None
        _check_finite("clock offset_s", offset_s)
        _check_vehicle_id("clock report gcs_id", gcs_id)
        return cls(event.vehicle_id, offset_s, gcs_id, ok=len(words) == 7)


@dataclass(frozen=True)
class Member:
    """One key of a fleet roster: who holds it and what it may sign."""

    role: Role
    member_id: int
    """Vehicle id (role VEHICLE) or ground-station id (role STATION), 1..MAX_VEHICLE_ID."""
    public_key: bytes
    """Raw Ed25519 public key (32 bytes)."""


@dataclass(frozen=True)
class Roster:
    """The fleet's members, signed by the fleet authority. A higher `version` replaces a lower
    one on every member (trust/auth.py); a member left out is revoked."""

    fleet: str
    version: int
    stamp_ns: int
    members: tuple[Member, ...]
    """Sorted by (role, member_id); one key per (role, id), every key distinct."""
    sig: bytes = bytes(TAG_BYTES)

    TYPE: ClassVar[MsgType] = MsgType.ROSTER
    _HEAD: ClassVar[struct.Struct] = struct.Struct(f"<BB{FLEET_NAME_BYTES}sIQH")
    _MEMBER: ClassVar[struct.Struct] = struct.Struct(f"<BH{PUBLIC_KEY_BYTES}s")

    def member(self, role: Role, member_id: int) -> Member | None:
        for m in self.members:
            if m.role is role and m.member_id == member_id:
                return m
        return None

    def validate(self) -> None:
        if not isinstance(self.fleet, str) or not 1 <= len(self.fleet.encode()) <= FLEET_NAME_BYTES:
            raise DecodeError(
                f"roster fleet name {self.fleet!r} must be 1-{FLEET_NAME_BYTES} bytes"
            )
        if not self.fleet.isascii() or not all(c.isalnum() or c in "_-" for c in self.fleet):
            raise DecodeError(f"roster fleet name {self.fleet!r} must be A-Z a-z 0-9 _ -")
        if not 1 <= self.version < 2**32:
            raise DecodeError(f"roster version {self.version} must be within 1..2^32-1")
        if not 0 <= self.stamp_ns < 2**64:
            raise DecodeError("stamp_ns must fit 64 bits")
        if len(self.members) > MAX_ROSTER_MEMBERS:
            raise DecodeError(f"{len(self.members)} roster members, at most {MAX_ROSTER_MEMBERS}")
        order = [(int(m.role), m.member_id) for m in self.members]
        if order != sorted(set(order)):
            raise DecodeError("roster members must be sorted by (role, id) without duplicates")
        if len({m.public_key for m in self.members}) != len(self.members):
            raise DecodeError("two roster members share a public key")
        for m in self.members:
            _enum(Role, "role", int(m.role))
            _check_vehicle_id("member id", m.member_id)
            if len(m.public_key) != PUBLIC_KEY_BYTES:
                raise DecodeError(f"public key must be {PUBLIC_KEY_BYTES} bytes")
        if len(self.sig) != TAG_BYTES:
            raise DecodeError(f"roster signature must be {TAG_BYTES} bytes, got {len(self.sig)}")

    def signed_bytes(self) -> bytes:
        head = self._HEAD.pack(
            self.TYPE,
            SCHEMA_VERSION,
            self.fleet.encode(),
            self.version,
            self.stamp_ns,
            len(self.members),
        )
        return head + b"".join(
            self._MEMBER.pack(int(m.role), m.member_id, m.public_key) for m in self.members
        )

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.sig

    @classmethod
    def peek(cls, data: bytes) -> RosterHead:
        """The fixed header of a roster's wire bytes, checked in O(1): size (at most
        MAX_ROSTER_BYTES, refused before anything else), type and version, fleet name, roster
        version and a length that matches the member count. Says nothing of the signature or
        the members: a receiver drops what is not newer than its own roster, then verifies the
        signature over `RosterHead.signed`, and only then decodes the members."""
        if len(data) > MAX_ROSTER_BYTES:
            raise DecodeError(f"Roster of {len(data)} bytes, at most {MAX_ROSTER_BYTES}")
        _header(data, cls.TYPE)
        if len(data) < cls._HEAD.size + TAG_BYTES:
            raise DecodeError(f"Roster too short: {len(data)} bytes")
        _, _, fleet_raw, version, _stamp_ns, n = cls._HEAD.unpack_from(data)
        if n > MAX_ROSTER_MEMBERS:
            raise DecodeError(f"{n} roster members, at most {MAX_ROSTER_MEMBERS}")
        expected = cls._HEAD.size + n * cls._MEMBER.size + TAG_BYTES
        if len(data) != expected:
            raise DecodeError(f"Roster with {n} members must be {expected} bytes, got {len(data)}")
        fleet = _text_field(fleet_raw, "fleet")
        if not fleet or not fleet.isascii() or not all(c.isalnum() or c in "_-" for c in fleet):
            raise DecodeError(f"roster fleet name {fleet!r} must be 1-32 of A-Z a-z 0-9 _ -")
        if version < 1:
            raise DecodeError(f"roster version {version} must be within 1..2^32-1")
        return RosterHead(fleet, version, n, bytes(data[:-TAG_BYTES]), bytes(data[-TAG_BYTES:]))

    @classmethod
    def decode(cls, data: bytes) -> Roster:
        head = cls.peek(data)
        _, _, fleet_raw, version, stamp_ns, n = cls._HEAD.unpack_from(data)
        members = []
        for i in range(n):
            role, mid, key = cls._MEMBER.unpack_from(data, cls._HEAD.size + i * cls._MEMBER.size)
            members.append(Member(_enum(Role, "role", role), mid, key))
        msg = cls(
            fleet=_text_field(fleet_raw, "fleet"),
            version=version,
            stamp_ns=stamp_ns,
            members=tuple(members),
            sig=head.sig,
        )
        msg.validate()
        return msg


@dataclass(frozen=True)
class RosterHead:
    """What `Roster.peek` reads of a roster's wire bytes without decoding its members."""

    fleet: str
    version: int
    n_members: int
    signed: bytes
    """The bytes the fleet authority signs (`Roster.signed_bytes()` of the decoded roster)."""
    sig: bytes


MAX_MISSION_ITEMS = 100
"""The most items one mission holds (QGC plans of a few dozen are usual)."""
MAX_MISSION_BYTES = 4096
"""The largest Mission on the wire: the routers' message size limit (comms/zenoh_configs/). A
mission for more vehicles than fit is sent as several (groundstation/mission_cli.py)."""
MISSION_SPEED_RANGE_M_S = (0.0, 100.0)
MISSION_HOLD_RANGE_S = (0.0, 3600.0)


class MissionItemKind(enum.IntEnum):
    """What one mission item asks (QGC's MAV_CMD in brackets)."""

    WAYPOINT = 1
    """Fly to a position, then wait `hold_s` there (NAV_WAYPOINT 16, NAV_LOITER_TIME 19)."""
    TAKEOFF = 2
    """Climb to `alt_m` where the vehicle is (NAV_TAKEOFF 22; an airborne vehicle climbs)."""
    HOLD = 3
    """Hold where the vehicle is for `hold_s`."""
    LAND = 4
    """Land where the vehicle is; the mission ends (NAV_LAND 21)."""
    RETURN = 5
    """Return home and land; the mission ends (NAV_RETURN_TO_LAUNCH 20)."""


class MissionFrame(enum.IntEnum):
    """How a mission item's position reads."""

    LOCAL = 0
    """x, y: metres north and east of the fleet origin; alt_m above the origin (up)."""
    GLOBAL = 1
    """x, y: WGS-84 latitude and longitude in degrees; alt_m above mean sea level."""


_POSITIONED = frozenset({MissionItemKind.WAYPOINT, MissionItemKind.TAKEOFF})


@dataclass(frozen=True)
class MissionItem:
    """One item of a mission. Unused fields are 0 (a TAKEOFF uses alt_m only, LAND and RETURN
    none, HOLD hold_s only)."""

    kind: MissionItemKind
    frame: MissionFrame = MissionFrame.LOCAL
    x: float = 0.0
    """North metres (LOCAL) or latitude degrees (GLOBAL)."""
    y: float = 0.0
    """East metres (LOCAL) or longitude degrees (GLOBAL)."""
    alt_m: float = 0.0
    """Altitude, up: above the fleet origin (LOCAL) or above mean sea level (GLOBAL)."""
    speed_m_s: float = 0.0
    """Horizontal speed on the way to this item; 0: the guidance's cruise speed."""
    hold_s: float = 0.0
    """Seconds to wait once there (WAYPOINT, HOLD)."""

    _FMT: ClassVar[struct.Struct] = struct.Struct("<BBddfff")

    def validate(self, i: int = 0) -> None:
        where = f"mission item {i + 1}"
        kind = _enum(MissionItemKind, f"{where} kind", int(self.kind))
        frame = _enum(MissionFrame, f"{where} frame", int(self.frame))
        _check_finite(where, self.x, self.y, self.alt_m, self.speed_m_s, self.hold_s)
        _check_range(f"{where} speed_m_s", self.speed_m_s, *MISSION_SPEED_RANGE_M_S)
        _check_range(f"{where} hold_s", self.hold_s, *MISSION_HOLD_RANGE_S)
        if kind is MissionItemKind.WAYPOINT:
            if frame is MissionFrame.GLOBAL:
                _check_range(f"{where} lat_deg", self.x, -90.0, 90.0)
                _check_range(f"{where} lon_deg", self.y, -180.0, 180.0)
                _check_range(f"{where} alt_m", self.alt_m, *GLOBAL_ALT_RANGE_M)
            else:
                lim = LOCAL_HORIZONTAL_LIMIT_M
                _check_range(f"{where} north_m", self.x, -lim, lim)
                _check_range(f"{where} east_m", self.y, -lim, lim)
                _check_range(
                    f"{where} alt_m", self.alt_m, -LOCAL_DOWN_RANGE_M[1], -LOCAL_DOWN_RANGE_M[0]
                )
            return
        if frame is not MissionFrame.LOCAL or self.x or self.y or self.speed_m_s:
            raise DecodeError(f"{where}: a {kind.name} has no position or speed (keep them 0)")
        if kind is MissionItemKind.TAKEOFF:
            _check_range(f"{where} takeoff alt_m", self.alt_m, *TAKEOFF_ALT_RANGE_M)
        elif self.alt_m:
            raise DecodeError(f"{where}: a {kind.name} has no altitude (keep it 0)")
        if kind in (MissionItemKind.LAND, MissionItemKind.RETURN) and self.hold_s:
            raise DecodeError(f"{where}: a {kind.name} has no hold time (keep it 0)")

    def pack(self) -> bytes:
        return self._FMT.pack(
            int(self.kind), int(self.frame), self.x, self.y, self.alt_m, self.speed_m_s, self.hold_s
        )


@dataclass(frozen=True)
class Mission:
    """A route for one vehicle, several, or the fleet: uploaded like a command (one query,
    `Mesh.send_command`), signed like one by a roster station (trust/auth.py `sign_mission`),
    answered by each vehicle with a CommandAck that says why when it is refused."""

    nonce: int
    stamp_ns: int
    items: tuple[MissionItem, ...]
    """1..MAX_MISSION_ITEMS items, flown in order."""
    mission_id: int = 1
    """The operator's number for this mission (shown in progress and events)."""
    mission_version: int = 1
    """Its revision (a re-upload of an edited mission)."""
    targets: tuple[int, ...] = ()
    """Vehicle ids this mission is for; empty means every vehicle of the fleet."""
    source_id: int = 0
    """Who sent it (a ground station id); part of the signed bytes."""
    tag: bytes = bytes(TAG_BYTES)
    """Ed25519 signature of station `source_id`; zeros in open mode."""

    TYPE: ClassVar[MsgType] = MsgType.MISSION
    VERSION: ClassVar[int] = SCHEMA_VERSION
    kind: ClassVar[str] = "MISSION"
    """What logs and refusals call it (a Command's kind is its CommandKind)."""
    _HEAD: ClassVar[struct.Struct] = struct.Struct("<BBQQHIIHH")

    @classmethod
    def size(cls, n_targets: int, n_items: int) -> int:
        """Wire bytes of a mission with these counts (the signature included)."""
        return cls._HEAD.size + 2 * n_targets + MissionItem._FMT.size * n_items + TAG_BYTES

    def applies_to(self, vehicle_id: int) -> bool:
        return not self.targets or vehicle_id in self.targets

    def validate(self) -> None:
        if not 0 <= self.nonce < 2**64 or not 0 <= self.stamp_ns < 2**64:
            raise DecodeError("nonce and stamp_ns must fit 64 bits")
        _check_vehicle_id("source_id", self.source_id, allow_zero=True)
        for name, v in (("mission_id", self.mission_id), ("mission_version", self.mission_version)):
            if not 0 <= v < 2**32:
                raise DecodeError(f"{name}={v} does not fit 32 bits")
        if len(set(self.targets)) != len(self.targets):
            raise DecodeError("targets contain duplicates")
        for t in self.targets:
            _check_vehicle_id("target", t)
        if not 1 <= len(self.items) <= MAX_MISSION_ITEMS:
            raise DecodeError(f"{len(self.items)} mission items, must be 1..{MAX_MISSION_ITEMS}")
        size = self.size(len(self.targets), len(self.items))
        if size > MAX_MISSION_BYTES:
            raise DecodeError(f"Mission of {size} bytes, at most {MAX_MISSION_BYTES}")
        for i, item in enumerate(self.items):
            item.validate(i)
        if len(self.tag) != TAG_BYTES:
            raise DecodeError(f"tag must be {TAG_BYTES} bytes, got {len(self.tag)}")

    def signed_bytes(self) -> bytes:
        """Every byte that the tag covers."""
        head = self._HEAD.pack(
            self.TYPE,
            self.VERSION,
            self.nonce,
            self.stamp_ns,
            self.source_id,
            self.mission_id,
            self.mission_version,
            len(self.targets),
            len(self.items),
        )
        targets = struct.pack(f"<{len(self.targets)}H", *self.targets)
        return head + targets + b"".join(item.pack() for item in self.items)

    def encode(self) -> bytes:
        self.validate()
        return self.signed_bytes() + self.tag

    @classmethod
    def decode(cls, data: bytes) -> Mission:
        if len(data) > MAX_MISSION_BYTES:
            raise DecodeError(f"Mission of {len(data)} bytes, at most {MAX_MISSION_BYTES}")
        _header(data, cls.TYPE, cls.VERSION)
        if len(data) < cls._HEAD.size + TAG_BYTES:
            raise DecodeError(f"Mission too short: {len(data)} bytes")
        f = cls._HEAD.unpack_from(data)
        n_targets, n_items = f[7], f[8]
        if not 1 <= n_items <= MAX_MISSION_ITEMS:
            raise DecodeError(f"{n_items} mission items, must be 1..{MAX_MISSION_ITEMS}")
        expected = cls.size(n_targets, n_items)
        if len(data) != expected:
            raise DecodeError(
                f"Mission with {n_targets} targets and {n_items} items must be {expected} "
                f"bytes, got {len(data)}"
            )
        at = cls._HEAD.size
        targets = struct.unpack_from(f"<{n_targets}H", data, at)
        at += 2 * n_targets
        items = []
        for k in range(n_items):
            g = MissionItem._FMT.unpack_from(data, at + k * MissionItem._FMT.size)
            items.append(
                MissionItem(
                    _enum(MissionItemKind, f"mission item {k + 1} kind", g[0]),
                    _enum(MissionFrame, f"mission item {k + 1} frame", g[1]),
                    *g[2:],
                )
            )
        msg = cls(
            nonce=f[2],
            stamp_ns=f[3],
            source_id=f[4],
            mission_id=f[5],
            mission_version=f[6],
            targets=targets,
            items=tuple(items),
            tag=data[-TAG_BYTES:],
        )
        msg.validate()
        return msg


MAX_PLAN_BYTES = (
    (51 + 18 + MAX_ZONES * (1 + MAX_NAME_BYTES + 18) + MAX_RALLY_POINTS * (25 + MAX_NAME_BYTES))
    + 16 * MAX_PLAN_VERTICES
    + TAG_BYTES
)
"""The largest PlanMessage on the wire (41,061 bytes): anything longer is refused before a byte
of it is read (`PlanMessage.peek`), and the shipped routers pass nothing longer on the plan key."""


class _Reader:
    """Reads a variable-length message front to back; running out is a DecodeError."""

    def __init__(self, data: bytes, at: int, end: int, what: str) -> None:
        self.data, self.at, self.end, self.what = data, at, end, what

    def take(self, fmt: struct.Struct) -> tuple:
        if self.at + fmt.size > self.end:
            raise DecodeError(f"{self.what} ends early at byte {self.at}")
        out = fmt.unpack_from(self.data, self.at)
        self.at += fmt.size
        return out

    def text(self, n: int, name: str) -> str:
        if self.at + n > self.end:
            raise DecodeError(f"{self.what} ends inside {name}")
        raw = self.data[self.at : self.at + n]
        self.at += n
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DecodeError(f"{name} is not valid UTF-8") from None


def _alt_or_nan(alt_m: float | None) -> float:
    return math.nan if alt_m is None else alt_m


def _nan_or_alt(value: float, name: str) -> float | None:
    if math.isnan(value):
        return None
    _check_finite(name, value)
    return value


def _check_fleet_name(fleet: str, what: str) -> None:
    if not isinstance(fleet, str) or not 1 <= len(fleet.encode()) <= FLEET_NAME_BYTES:
        raise DecodeError(f"{what} fleet name {fleet!r} must be 1-{FLEET_NAME_BYTES} bytes")
    if not fleet.isascii() or not all(c.isalnum() or c in "_-" for c in fleet):
        raise DecodeError(f"{what} fleet name {fleet!r} must be A-Z a-z 0-9 _ -")


@dataclass(frozen=True)
class PlanMessage:
    """A fleet plan on the wire (comms/plan.py): signed by the fleet authority or a roster
    station (trust/auth.py), followed like the roster (comms/plan_sync.py): a higher `version`
    replaces a lower one on every member."""

    plan: FleetPlan

    TYPE: ClassVar[MsgType] = MsgType.PLAN
    FLAG_FENCE: ClassVar[int] = 1
    _HEAD: ClassVar[struct.Struct] = struct.Struct(f"<BB{FLEET_NAME_BYTES}sIQHBBB")
    _POLY: ClassVar[struct.Struct] = struct.Struct("<ddH")
    _VERTEX: ClassVar[struct.Struct] = struct.Struct("<dd")
    _LEN: ClassVar[struct.Struct] = struct.Struct("<B")
    _RALLY: ClassVar[struct.Struct] = struct.Struct("<dddB")

    def validate(self) -> None:
        p = self.plan
        _check_fleet_name(p.fleet, "plan")
        if len(p.signature) not in (0, TAG_BYTES):
            raise DecodeError(f"plan signature must be {TAG_BYTES} bytes, got {len(p.signature)}")

    def _poly(self, vertices: tuple, floor: float | None, ceiling: float | None) -> bytes:
        out = [self._POLY.pack(_alt_or_nan(floor), _alt_or_nan(ceiling), len(vertices))]
        out += [self._VERTEX.pack(n, e) for n, e in vertices]
        return b"".join(out)

    def signed_bytes(self) -> bytes:
        """What the signer signs: everything but the signature."""
        self.validate()
        p = self.plan
        out = [
            self._HEAD.pack(
                self.TYPE,
                SCHEMA_VERSION,
                p.fleet.encode(),
                p.version,
                p.stamp_ns,
                p.signer_id,
                self.FLAG_FENCE if p.fence is not None else 0,
                len(p.keep_out),
                len(p.rally),
            )
        ]
        if p.fence is not None:
            f = p.fence
            out.append(self._poly(f.vertices_ne_m, f.floor_alt_m, f.ceiling_alt_m))
        for z in p.keep_out:
            name = z.name.encode()
            out += [self._LEN.pack(len(name)), name]
            out.append(self._poly(z.vertices_ne_m, z.floor_alt_m, z.ceiling_alt_m))
        for r in p.rally:
            name = r.name.encode()
            out += [self._RALLY.pack(r.n_m, r.e_m, r.alt_m, len(name)), name]
        return b"".join(out)

    def encode(self) -> bytes:
        """The wire bytes; an unsigned plan (open mode) carries a zero signature."""
        data = self.signed_bytes() + (self.plan.signature or bytes(TAG_BYTES))
        if len(data) > MAX_PLAN_BYTES:  # unreachable within FleetPlan's limits; kept honest
            raise DecodeError(f"PlanMessage of {len(data)} bytes, at most {MAX_PLAN_BYTES}")
        return data

    @classmethod
    def peek(cls, data: bytes) -> PlanHead:
        """The fixed header of a plan's wire bytes, checked in O(1) (size first, at most
        MAX_PLAN_BYTES): a receiver drops what is not newer than its own plan, verifies the
        signature over `PlanHead.signed`, and only then decodes the polygons."""
        if len(data) > MAX_PLAN_BYTES:
            raise DecodeError(f"PlanMessage of {len(data)} bytes, at most {MAX_PLAN_BYTES}")
        _header(data, cls.TYPE)
        if len(data) < cls._HEAD.size + TAG_BYTES:
            raise DecodeError(f"PlanMessage too short: {len(data)} bytes")
        _, _, fleet_raw, version, _stamp, signer_id, _flags, _nz, _nr = cls._HEAD.unpack_from(data)
        fleet = _text_field(fleet_raw, "fleet")
        _check_fleet_name(fleet, "plan")
        if version < 1:
            raise DecodeError(f"plan version {version} must be within 1..2^32-1")
        return PlanHead(
            fleet, version, signer_id, bytes(data[:-TAG_BYTES]), bytes(data[-TAG_BYTES:])
        )

    @classmethod
    def decode(cls, data: bytes) -> PlanMessage:
        head = cls.peek(data)
        _, _, _, version, stamp_ns, signer_id, flags, n_zones, n_rally = cls._HEAD.unpack_from(data)
        if flags & ~cls.FLAG_FENCE:
            raise DecodeError(f"plan flags {flags:#x} has unknown bits")
        if n_zones > MAX_ZONES or n_rally > MAX_RALLY_POINTS:
            raise DecodeError(
                f"plan with {n_zones} zones and {n_rally} rally points: at most {MAX_ZONES} "
                f"and {MAX_RALLY_POINTS}"
            )
        rd = _Reader(data, cls._HEAD.size, len(data) - TAG_BYTES, "PlanMessage")
        budget = [MAX_PLAN_VERTICES]

        def poly(what: str) -> tuple[tuple, float | None, float | None]:
            floor, ceiling, n = rd.take(cls._POLY)
            if n > budget[0]:
                raise DecodeError(f"{what}: {n} vertices, over the plan's {MAX_PLAN_VERTICES}")
            budget[0] -= n
            vertices = tuple(rd.take(cls._VERTEX) for _ in range(n))
            return (
                vertices,
                _nan_or_alt(floor, f"{what} floor"),
                _nan_or_alt(ceiling, f"{what} ceiling"),
            )

        try:
            fence = Fence(*poly("the fence")) if flags & cls.FLAG_FENCE else None
            zones = []
            for i in range(n_zones):
                (size,) = rd.take(cls._LEN)
                name = rd.text(size, f"zone {i} name")
                vertices, floor, ceiling = poly(f"zone {name!r}")
                zones.append(Zone(vertices, name, floor, ceiling))
            rally = []
            for i in range(n_rally):
                n_m, e_m, alt_m, size = rd.take(cls._RALLY)
                rally.append(RallyPoint(n_m, e_m, alt_m, rd.text(size, f"rally point {i} name")))
            if rd.at != rd.end:
                raise DecodeError(f"PlanMessage has {rd.end - rd.at} bytes after its content")
            plan = FleetPlan(
                head.fleet,
                version,
                stamp_ns,
                fence,
                tuple(zones),
                tuple(rally),
                signer_id=signer_id,
                signature=head.sig,
            )
        except DecodeError:
            raise
        except ValueError as exc:  # the geometry's own checks: one line, as a DecodeError
            raise DecodeError(f"plan v{version}: {exc}") from None
        return cls(plan)


@dataclass(frozen=True)
class PlanHead:
    """What `PlanMessage.peek` reads of a plan's wire bytes without decoding its polygons."""

    fleet: str
    version: int
    signer_id: int
    """0: the fleet authority; N: ground station N."""
    signed: bytes
    """The bytes the signer signs (`PlanMessage.signed_bytes()` of the decoded plan)."""
    sig: bytes


Message = (
    VehicleState
    | Command
    | CommandAck
    | Event
    | Roster
    | GuidanceTrace
    | FeedBatch
    | StationHeartbeat
    | TrafficReport
    | Mission
    | PlanMessage
    | ActionOutcome
    | RelayBatch
)
_DECODERS: dict[int, type[Message]] = {
    MsgType.VEHICLE_STATE: VehicleState,
    MsgType.COMMAND: Command,
    MsgType.COMMAND_ACK: CommandAck,
    MsgType.EVENT: Event,
    MsgType.ROSTER: Roster,
    MsgType.GUIDANCE_TRACE: GuidanceTrace,
    MsgType.FEED_BATCH: FeedBatch,
    MsgType.STATION_HEARTBEAT: StationHeartbeat,
    MsgType.TRAFFIC_REPORT: TrafficReport,
    MsgType.MISSION: Mission,
    MsgType.PLAN: PlanMessage,
    MsgType.ACTION_OUTCOME: ActionOutcome,
    MsgType.RELAY_BATCH: RelayBatch,
}


def decode(data: bytes | bytearray | memoryview) -> Message:
    """Decode any covey message by its type byte. Raises only DecodeError."""
    data = bytes(data)
    if not data:
        raise DecodeError("empty message")
    cls = _DECODERS.get(data[0])
    if cls is None:
        raise DecodeError(f"unknown message type {data[0]}")
    try:
        return cls.decode(data)
    except DecodeError:
        raise
    except (struct.error, ValueError, OverflowError, TypeError) as exc:  # defence in depth
        raise DecodeError(f"malformed {cls.__name__}: {exc}") from None


__all__ = [
    "AckResult",
    "ActionOutcome",
    "ClockReport",
    "Command",
    "CommandAck",
    "CommandKind",
    "DecodeError",
    "Event",
    "EventKind",
    "EventMessage",
    "FeedBatch",
    "FeedEntry",
    "RelayBatch",
    "GuidanceTrace",
    "Member",
    "Message",
    "Mission",
    "MissionFrame",
    "MissionItem",
    "MissionItemKind",
    "Mode",
    "MsgType",
    "PlanHead",
    "PlanMessage",
    "Role",
    "Roster",
    "RosterHead",
    "Severity",
    "StateFlag",
    "StationHeartbeat",
    "TraceFlag",
    "TrafficFlag",
    "TrafficReport",
    "TrafficSource",
    "VehicleState",
    "decode",
    "decode_event_message",
]
