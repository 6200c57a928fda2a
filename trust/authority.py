"""The fleet authority: creates the fleet, enrols and revokes members (`covey keygen`).

The directory (default ~/.config/covey/fleet, mode 0700) is the operator's: it holds the
authority key and every member file it issued. Copy `vehicle-3.key` (and only it) to vehicle 3,
`station-1.key` to station 1. Each add or revoke re-signs the roster with a higher version and
refreshes the roster inside every member file still in the directory; a running fleet picks the
new roster up from `push` (or from any member that has it) without restarting.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from collections.abc import Set as AbstractSet
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from comms.keys import check_fleet
from comms.schema import DecodeError, Member, Role, Roster
from kit.safe_load import BadFileError, read_bounded
from trust.identity import (
    MAX_KEY_FILE_BYTES,
    FleetKeyError,
    authority_doc,
    check_roster,
    member_doc,
    member_file_name,
    public_bytes,
    read_authority,
    read_member_key,
    sign_roster,
    write_private_file,
)

DEFAULT_DIR = Path("~/.config/covey/fleet")
AUTHORITY = "authority.key"
ROSTER = "roster.bin"


class Authority:
    """The operator's directory: authority key, current roster, issued member files."""

    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory).expanduser()
        self.fleet, self.key = read_authority(self.dir / AUTHORITY)
        try:
            raw = read_bounded(self.dir / ROSTER, MAX_KEY_FILE_BYTES, "roster")
            self.roster = Roster.decode(raw)
        except BadFileError as exc:
            raise FleetKeyError(str(exc)) from None
        except DecodeError as exc:
            raise FleetKeyError(f"{self.dir / ROSTER}: cannot use it ({exc})") from None
        problem = check_roster(self.roster, public_bytes(self.key), self.fleet)
        if problem:
            raise FleetKeyError(f"{self.dir / ROSTER}: {problem}")

    @staticmethod
    def init(directory: str | Path, fleet: str, clock_ns=time.time_ns) -> Authority:
        d = Path(directory).expanduser()
        check_fleet(fleet)
        if (d / AUTHORITY).exists():
            raise FileExistsError(
                f"{d / AUTHORITY} already exists; not overwriting a fleet authority"
            )
        key = Ed25519PrivateKey.generate()
        write_private_file(d / AUTHORITY, authority_doc(fleet, key))
        roster = sign_roster(key, Roster(fleet, 1, clock_ns(), ()))
        (d / ROSTER).write_bytes(roster.encode())
        return Authority(d)

    def member_path(self, role: Role, member_id: int) -> Path:
        return self.dir / member_file_name(role, member_id)

    def add(self, role: Role, member_id: int, clock_ns=time.time_ns) -> Path:
        return self.add_many([(role, member_id)], clock_ns)[0]

    def add_many(self, who: list[tuple[Role, int]], clock_ns=time.time_ns) -> list[Path]:
        """Enrol several members under ONE new roster version; returns their key files."""
        new = {}
        for role, member_id in who:
            if self.roster.member(role, member_id) is not None or (role, member_id) in new:
                raise FileExistsError(
                    f"{role.name.lower()} {member_id} is already enrolled; revoke it first"
                )
            new[(role, member_id)] = Ed25519PrivateKey.generate()
        added = [Member(r, i, public_bytes(k)) for (r, i), k in new.items()]
        members = sorted((*self.roster.members, *added), key=lambda m: (int(m.role), m.member_id))
        self._publish(tuple(members), clock_ns, skip=set(new))
        paths = []
        for (role, member_id), key in new.items():
            path = self.member_path(role, member_id)
            path.unlink(missing_ok=True)  # a revoked member's old file
            write_private_file(
                path,
                member_doc(self.fleet, role, member_id, key, public_bytes(self.key), self.roster),
            )
            paths.append(path)
        return paths

    def revoke(self, role: Role, member_id: int, clock_ns=time.time_ns) -> None:
        if self.roster.member(role, member_id) is None:
            raise KeyError(f"{role.name.lower()} {member_id} is not in the roster")
        self._publish(
            tuple(m for m in self.roster.members if (m.role, m.member_id) != (role, member_id)),
            clock_ns,
        )
        self.member_path(role, member_id).unlink(missing_ok=True)

    def _publish(
        self,
        members: tuple[Member, ...],
        clock_ns,
        skip: AbstractSet[tuple[Role, int]] = frozenset(),
    ) -> None:
        self.roster = sign_roster(
            self.key, Roster(self.fleet, self.roster.version + 1, clock_ns(), members)
        )
        tmp = self.dir / (ROSTER + ".tmp")
        tmp.write_bytes(self.roster.encode())
        tmp.replace(self.dir / ROSTER)
        for m in self.roster.members:  # refresh the roster inside every file still here
            if (m.role, m.member_id) in skip:
                continue
            path = self.member_path(m.role, m.member_id)
            try:
                old = read_member_key(path)
            except FleetKeyError:
                continue  # not here (already handed out and deleted) or not ours
            doc = member_doc(
                self.fleet,
                old.role,
                old.member_id,
                old.private_key,
                public_bytes(self.key),
                self.roster,
            )
            write_private_file(path, doc, overwrite=True)


def throwaway_fleet(
    directory: str | Path,
    fleet: str,
    vehicles: Sequence[int] = range(1, 3),
    stations: Sequence[int] = (1,),
) -> Authority:
    """A new authority with these members enrolled under one roster version (demo, tests, bench)."""
    auth = Authority.init(directory, fleet)
    auth.add_many([(Role.STATION, s) for s in stations] + [(Role.VEHICLE, v) for v in vehicles])
    return auth
