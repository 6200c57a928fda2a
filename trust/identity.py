"""Fleet identities: Ed25519 key pairs, the authority-signed roster, and their files.

    authority.key   {"covey": "fleet-authority", "fleet", "private_key"}    operator only
    roster.bin      the signed Roster (comms/schema.py)                     public
    vehicle-3.key   {"covey": "member-key", "fleet", "role", "id", "private_key",
                     "authority_public_key", "roster"}                      vehicle 3 only

A member file holds ONE private key (its own), the authority's public key (the trust anchor it
checks every roster against) and the roster it was issued with. Every private-key file must be
readable by its owner only. Every signature covers a domain label and the fleet name, so that a
signature made for one kind of message or one fleet never passes for another.

All cryptography is the `cryptography` package's Ed25519; nothing here is hand-written crypto.
"""

from __future__ import annotations

import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from comms.keys import check_fleet
from comms.member import FleetKeyError
from comms.schema import MAX_VEHICLE_ID, TAG_BYTES, DecodeError, Role, Roster
from kit.safe_load import BadFileError, decode_utf8, parse_json

MEMBER_FILE = "member-key"
AUTHORITY_FILE = "fleet-authority"
MAX_KEY_FILE_BYTES = 1_000_000
"""A member file embeds the roster (35 bytes a member, hex: 70): 4096 members fit."""


def signed_message(label: str, fleet: str, data: bytes) -> bytes:
    """What is actually signed: domain label, fleet name, then the message bytes."""
    return b"covey-sig-v2\0" + label.encode() + b"\0" + fleet.encode() + b"\0" + data


def public_bytes(key: Ed25519PrivateKey | Ed25519PublicKey) -> bytes:
    pub = key.public_key() if isinstance(key, Ed25519PrivateKey) else key
    return pub.public_bytes(Encoding.Raw, PublicFormat.Raw)


def private_bytes(key: Ed25519PrivateKey) -> bytes:
    from cryptography.hazmat.primitives.serialization import NoEncryption, PrivateFormat

    return key.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())


def verify(public_key: Ed25519PublicKey, sig: bytes, label: str, fleet: str, data: bytes) -> bool:
    """True if `sig` is `public_key`'s signature of (label, fleet, data)."""
    if len(sig) != TAG_BYTES:
        return False
    try:
        public_key.verify(sig, signed_message(label, fleet, data))
    except InvalidSignature:
        return False
    return True


def sign_roster(authority: Ed25519PrivateKey, roster: Roster) -> Roster:
    from dataclasses import replace

    roster.validate()
    return replace(
        roster, sig=authority.sign(signed_message("roster", roster.fleet, roster.signed_bytes()))
    )


def check_roster(roster: Roster, authority_public_key: bytes, fleet: str) -> str | None:
    """None if `roster` is the authority's, for `fleet`; else why not."""
    if roster.fleet != fleet:
        return f"roster is for fleet {roster.fleet!r}, not {fleet!r}"
    pub = Ed25519PublicKey.from_public_bytes(authority_public_key)
    if not verify(pub, roster.sig, "roster", roster.fleet, roster.signed_bytes()):
        return "roster signature does not verify with the fleet authority's key"
    return None


@dataclass(frozen=True)
class MemberKey:
    """One member's identity as read from its key file."""

    fleet: str
    role: Role
    member_id: int
    private_key: Ed25519PrivateKey
    authority_public_key: bytes
    roster: Roster
    """The roster the file was issued with (a newer one may arrive on the mesh)."""

    @property
    def name(self) -> str:
        return f"{self.role.name.lower()} {self.member_id}"


# -- files ---------------------------------------------------------------------------------------
def member_file_name(role: Role, member_id: int) -> str:
    """The one name of a member's key file: `vehicle-3.key`, `station-1.key` (what `covey keygen`
    and `covey demo` write, and what `covey agent --key-dir` reads)."""
    return f"{role.name.lower()}-{member_id}.key"


def _read_private_file(path: str | os.PathLike[str], what: str) -> dict:
    if str(path).strip() == "":
        raise FleetKeyError(f"{what} path is empty (an unset variable?); give a file or no option")
    p = Path(path).expanduser()
    try:
        st = p.stat()
    except FileNotFoundError:
        raise FleetKeyError(f"{what} {p} does not exist (create one with: covey keygen)") from None
    except OSError as exc:
        raise FleetKeyError(f"{what} {p}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise FleetKeyError(f"{what} {p} is not a regular file")
    if os.name == "posix" and st.st_mode & 0o077:
        raise FleetKeyError(
            f"{what} {p} has mode {stat.S_IMODE(st.st_mode):04o}: group/others "
            f"may read it; run: chmod 600 {p}"
        )
    if st.st_size > MAX_KEY_FILE_BYTES:
        raise FleetKeyError(f"{what} {p} is {st.st_size} bytes: not a covey key file")
    try:
        raw = p.read_bytes()
    except OSError as exc:  # PermissionError: someone else's file
        raise FleetKeyError(f"{what} {p}: cannot read it ({exc.strerror or exc})") from None
    text = raw.strip()
    if len(text) in (64, 44) and text.isascii() and not text.startswith(b"{"):
        raise FleetKeyError(
            f"{what} {p} is a shared fleet key from an older covey; covey now gives every "
            "member its own key: covey keygen init, then covey keygen add vehicle N"
        )
    try:
        doc = parse_json(decode_utf8(raw, f"{what} {p}"), f"{what} {p}")
    except BadFileError as exc:  # too deep, not UTF-8, not JSON: one line, never a traceback
        raise FleetKeyError(f"{exc}: not a covey key file") from None
    if not isinstance(doc, dict):
        raise FleetKeyError(f"{what} {p} is not a covey key file (not a JSON object)")
    return doc


def _field(doc: dict, name: str, kind: type, where: str):
    value = doc.get(name)
    if not isinstance(value, kind) or isinstance(value, bool):
        raise FleetKeyError(f"{where}: field {name!r} is missing or not a {kind.__name__}")
    return value


def _hex(doc: dict, name: str, size: int | None, where: str) -> bytes:
    try:
        raw = bytes.fromhex(_field(doc, name, str, where))
    except ValueError:
        raise FleetKeyError(f"{where}: field {name!r} is not hex") from None
    if size is not None and len(raw) != size:
        raise FleetKeyError(f"{where}: field {name!r} must be {size} bytes, got {len(raw)}")
    return raw


def read_member_key(path: str | os.PathLike[str]) -> MemberKey:
    """Read and check a member key file: its roster must be the authority's and list this key."""
    doc = _read_private_file(path, "key file")
    where = f"key file {Path(path).expanduser()}"
    if doc.get("covey") == AUTHORITY_FILE:
        raise FleetKeyError(
            f"{where} is the fleet AUTHORITY key: it must stay with the operator; "
            "give each process its member key (covey keygen add)"
        )
    if doc.get("covey") != MEMBER_FILE:
        raise FleetKeyError(f"{where} is not a covey member key file")
    fleet = _field(doc, "fleet", str, where)
    try:
        check_fleet(fleet)
        role = Role[_field(doc, "role", str, where).upper()]
    except (ValueError, KeyError) as exc:
        raise FleetKeyError(f"{where}: {exc}") from None
    member_id = _field(doc, "id", int, where)
    if not 1 <= member_id <= MAX_VEHICLE_ID:
        raise FleetKeyError(f"{where}: id {member_id} is outside 1..{MAX_VEHICLE_ID}")
    private = Ed25519PrivateKey.from_private_bytes(_hex(doc, "private_key", 32, where))
    authority = _hex(doc, "authority_public_key", 32, where)
    try:
        roster = Roster.decode(_hex(doc, "roster", None, where))
    except DecodeError as exc:
        raise FleetKeyError(f"{where}: its roster is malformed: {exc}") from None
    problem = check_roster(roster, authority, fleet)
    if problem:
        raise FleetKeyError(f"{where}: {problem}")
    key = MemberKey(fleet, role, member_id, private, authority, roster)
    entry = roster.member(role, member_id)
    if entry is None or entry.public_key != public_bytes(private):
        raise FleetKeyError(
            f"{where}: {key.name} is not in its roster (v{roster.version}) with "
            "this key: revoked or replaced; ask the operator for a new key file"
        )
    return key


def read_authority(path: str | os.PathLike[str]) -> tuple[str, Ed25519PrivateKey]:
    """(fleet, authority private key) from an authority file."""
    doc = _read_private_file(path, "authority file")
    where = f"authority file {Path(path).expanduser()}"
    if doc.get("covey") != AUTHORITY_FILE:
        raise FleetKeyError(f"{where} is not a covey fleet-authority file")
    fleet = _field(doc, "fleet", str, where)
    return fleet, Ed25519PrivateKey.from_private_bytes(_hex(doc, "private_key", 32, where))


def write_private_file(path: Path, doc: dict, overwrite: bool = False) -> None:
    """Write JSON with mode 0600; never overwrite unless asked (then atomically)."""
    if path.parent != Path() and not path.parent.exists():
        path.parent.mkdir(mode=0o700, parents=True)
    target = path.with_name(path.name + ".tmp") if overwrite else path
    if overwrite:
        target.unlink(missing_ok=True)
    fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")
    os.chmod(target, 0o600)
    if overwrite:
        os.replace(target, path)


def member_doc(
    fleet: str,
    role: Role,
    member_id: int,
    private: Ed25519PrivateKey,
    authority_public_key: bytes,
    roster: Roster,
) -> dict:
    return {
        "covey": MEMBER_FILE,
        "version": 1,
        "fleet": fleet,
        "role": role.name.lower(),
        "id": member_id,
        "private_key": private_bytes(private).hex(),
        "authority_public_key": authority_public_key.hex(),
        "roster": roster.encode().hex(),
    }


def authority_doc(fleet: str, private: Ed25519PrivateKey) -> dict:
    return {
        "covey": AUTHORITY_FILE,
        "version": 1,
        "fleet": fleet,
        "private_key": private_bytes(private).hex(),
    }
