"""Signed commands: HMAC-SHA256 over every command and ack, with freshness and replay checks.

Every ground station and agent of a fleet shares one 32-byte fleet key. The sender signs a
command's `signed_bytes()` (`sign_command` also stamps it with the sender's clock and draws a
nonce if it has none); the vehicle checks, in this order:

    1. tag present (all zeros = unsigned)    -> "unsigned command ..."
    2. tag correct (constant-time compare)   -> "bad signature ..."
    3. |now - stamp_ns| <= max_skew_s        -> "stale command ..."
    4. (vehicle, nonce) not seen before      -> "replayed command ..."

A rejected command's reason goes back in the (signed) ack, so the operator sees why. Acks are
signed too; `check_ack` tells the sender when an ack does not come from a key holder.

Commands and acks are signed under different domain labels, so a command's tag can never pass
as an ack's. Only correctly signed commands reach the nonce cache, so an attacker without the
key cannot fill it. The cache is bounded: when full, the oldest entry goes and its stamp becomes
a floor below which every command is refused (nothing older than the floor can be told apart
from a replay any more).

Keys never come from the command line (shell history, `ps`): from a file (`--key-file`,
`COVEY_FLEET_KEY_FILE`) that only its owner can read, or from `COVEY_FLEET_KEY` (hex or base64).
`covey keygen -o PATH` writes a new key with mode 0600 and never overwrites one.
"""

from __future__ import annotations

import argparse
import base64
import binascii
import dataclasses
import hashlib
import heapq
import hmac
import logging
import os
import secrets
import stat
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path

from comms.schema import TAG_BYTES, Command, CommandAck

log = logging.getLogger(__name__)

KEY_BYTES = 32
"""Length of the keys `covey keygen` writes."""
MIN_KEY_BYTES = 16
"""Shorter keys are refused: HMAC-SHA256 is only as strong as its key."""
ENV_KEY = "COVEY_FLEET_KEY"
ENV_KEY_FILE = "COVEY_FLEET_KEY_FILE"
DEFAULT_KEY_PATH = Path("~/.config/covey/fleet.key")
_CMD_LABEL = b"covey-cmd-v1\0"
_ACK_LABEL = b"covey-ack-v1\0"
_NO_TAG = bytes(TAG_BYTES)


class FleetKeyError(ValueError):
    """A fleet key could not be loaded; the message says why and how to fix it."""


class CommandAuth:
    """Signs and checks commands and acks with one fleet key. Thread-safe.

    `clock_ns`: wall clock shared with the other side (NTP/GPS time; stamps cross machines).
    `max_skew_s`: a command stamped further than this from `clock_ns()` is refused as stale.
    `replay_window`: at most this many (vehicle, nonce) pairs are remembered.
    """

    def __init__(
        self,
        key: bytes,
        clock_ns: Callable[[], int] = time.time_ns,
        max_skew_s: float = 5.0,
        replay_window: int = 65536,
        rng: Callable[[int], int] = secrets.randbits,
    ) -> None:
        if not isinstance(key, bytes | bytearray) or len(key) < MIN_KEY_BYTES:
            raise FleetKeyError(f"a fleet key must be at least {MIN_KEY_BYTES} bytes")
        if not 0.0 < max_skew_s <= 3600.0:
            raise ValueError(f"max_skew_s={max_skew_s} must be within (0, 3600]")
        if not 1 <= replay_window <= 10_000_000:
            raise ValueError(f"replay_window={replay_window} must be within 1..10000000")
        self._key = bytes(key)
        self.clock_ns = clock_ns
        self.max_skew_ns = int(max_skew_s * 1e9)
        self.replay_window = replay_window
        self._rng = rng
        self._lock = threading.Lock()
        self._seen: set[tuple[int, int]] = set()
        self._by_stamp: list[tuple[int, int, int]] = []  # heap of (stamp_ns, vehicle, nonce)
        self._floor_ns = -1
        self.rejected = 0
        """How many commands this instance refused (read only)."""
        self.on_reject: Callable[[Command, int, str], None] | None = None
        """Called with (command, vehicle_id, reason) for every refused command, on the Zenoh
        thread; the agent publishes a SECURITY event from it. Exceptions are logged, not raised."""

    @property
    def key_id(self) -> str:
        """A short fingerprint of the key for logs (never log the key)."""
        return hashlib.sha256(b"covey-key-id\0" + self._key).hexdigest()[:12]

    def _tag(self, label: bytes, data: bytes) -> bytes:
        return hmac.new(self._key, label + data, hashlib.sha256).digest()

    # -- commands ----------------------------------------------------------------------------
    def sign_command(self, cmd: Command) -> Command:
        """Stamp `cmd` with now, give it a nonce if it has none, and sign it."""
        nonce = cmd.nonce
        while not nonce:
            nonce = self._rng(64)
        stamped = dataclasses.replace(cmd, nonce=nonce, stamp_ns=self.clock_ns(), tag=_NO_TAG)
        return dataclasses.replace(stamped, tag=self._tag(_CMD_LABEL, stamped.signed_bytes()))

    def check_command(self, cmd: Command, vehicle_id: int) -> str | None:
        """None if `cmd` may be executed by `vehicle_id`, else why not (for the ack)."""
        reason = self._check_command(cmd, vehicle_id)
        if reason is not None:
            with self._lock:
                self.rejected += 1
            log.warning("vehicle %d refused %s from station %d: %s", vehicle_id,
                        getattr(cmd.kind, "name", cmd.kind), cmd.source_id, reason)  # fmt: skip
            if self.on_reject is not None:
                try:
                    self.on_reject(cmd, vehicle_id, reason)
                except Exception:  # noqa: BLE001 - a listener bug must not turn a refusal into a crash
                    log.exception("on_reject listener failed")
        return reason

    def _check_command(self, cmd: Command, vehicle_id: int) -> str | None:
        if cmd.tag == _NO_TAG:
            return "unsigned command: this vehicle requires commands signed with the fleet key"
        if not hmac.compare_digest(cmd.tag, self._tag(_CMD_LABEL, cmd.signed_bytes())):
            return "bad signature: wrong fleet key or the command was altered"
        now = self.clock_ns()
        age_ns = now - cmd.stamp_ns
        if abs(age_ns) > self.max_skew_ns:
            return (f"stale command: stamped {age_ns / 1e9:+.1f} s from this vehicle's clock "
                    f"(limit {self.max_skew_ns / 1e9:g} s)")  # fmt: skip
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

    # -- acks --------------------------------------------------------------------------------
    def sign_ack(self, ack: CommandAck) -> CommandAck:
        unsigned = dataclasses.replace(ack, tag=_NO_TAG)
        return dataclasses.replace(unsigned, tag=self._tag(_ACK_LABEL, unsigned.signed_bytes()))

    def check_ack(self, ack: CommandAck, cmd: Command) -> str | None:
        """None if `ack` comes from a key holder and answers `cmd`, else why not."""
        said = f" (it said: {ack.result.name.lower()}" + (f": {ack.reason})" if ack.reason else ")")
        if ack.tag == _NO_TAG:
            return "unsigned ack: the vehicle runs in open mode" + said
        if not hmac.compare_digest(ack.tag, self._tag(_ACK_LABEL, ack.signed_bytes())):
            return "ack with a bad signature: the vehicle has another fleet key" + said
        if ack.nonce not in (cmd.nonce, 0):
            return f"ack nonce {ack.nonce:#x} does not answer command nonce {cmd.nonce:#x}"
        return None


# -- keys ------------------------------------------------------------------------------------
def parse_key(text: str | bytes, where: str) -> bytes:
    """A key from its hex (64 digits) or base64 text; raw bytes of a binary key file pass."""
    raw = text if isinstance(text, bytes) else text.encode()
    stripped = raw.strip()
    key: bytes | None = None
    try:
        key = bytes.fromhex(stripped.decode("ascii"))
    except (ValueError, UnicodeDecodeError):
        try:
            key = base64.b64decode(stripped, validate=True)
        except (binascii.Error, ValueError):
            key = raw if len(raw) == KEY_BYTES and isinstance(text, bytes) else None
    if key is None:
        raise FleetKeyError(f"{where}: not a key (expected {2 * KEY_BYTES} hex digits or base64)")
    if len(key) < MIN_KEY_BYTES:
        raise FleetKeyError(f"{where}: key is {len(key)} bytes, at least {MIN_KEY_BYTES} needed")
    return key


def read_key_file(path: str | os.PathLike[str]) -> bytes:
    """Read a key file, refusing one that its group or others may read or write."""
    p = Path(path).expanduser()
    try:
        st = p.stat()
    except FileNotFoundError:
        raise FleetKeyError(
            f"key file {p} does not exist (create one with: covey keygen -o {p})"
        ) from None
    if not stat.S_ISREG(st.st_mode):
        raise FleetKeyError(f"key file {p} is not a regular file")
    if os.name == "posix" and st.st_mode & 0o077:
        raise FleetKeyError(
            f"key file {p} has mode {stat.S_IMODE(st.st_mode):04o}: group/others may read it; "
            f"run: chmod 600 {p}"
        )
    if st.st_size > 4096:
        raise FleetKeyError(f"key file {p} is {st.st_size} bytes: not a key file")
    return parse_key(p.read_bytes(), f"key file {p}")


def load_key(key_file: str | None, env: Mapping[str, str] = os.environ) -> bytes | None:
    """The fleet key from `key_file`, else $COVEY_FLEET_KEY, else $COVEY_FLEET_KEY_FILE, else None."""
    if key_file:
        return read_key_file(key_file)
    if env.get(ENV_KEY):
        return parse_key(env[ENV_KEY], f"${ENV_KEY}")
    if env.get(ENV_KEY_FILE):
        return read_key_file(env[ENV_KEY_FILE])
    return None


def load_auth(
    key_file: str | None,
    env: Mapping[str, str] = os.environ,
    **kw: object,
) -> CommandAuth | None:
    """A CommandAuth for the configured fleet key, or None (open mode, said loudly in the log).

    Raises FleetKeyError when a key is configured but unusable: never fall back to open mode
    because of a typo."""
    key = load_key(key_file, env)
    if key is None:
        log.warning(
            "OPEN MODE: no fleet key (--key-file, $%s or $%s); commands are NOT authenticated "
            "and anyone on the mesh can fly these vehicles. Simulator demos only.",
            ENV_KEY_FILE, ENV_KEY,
        )  # fmt: skip
        return None
    auth = CommandAuth(key, **kw)  # type: ignore[arg-type]
    log.info("signed commands on (fleet key %s)", auth.key_id)
    return auth


def write_new_key(
    path: str | os.PathLike[str], rng_bytes: Callable[[int], bytes] = secrets.token_bytes
) -> Path:
    """Write a fresh key as hex text with mode 0600; refuse to overwrite anything."""
    p = Path(path).expanduser()
    if p.parent != Path() and not p.parent.exists():
        p.parent.mkdir(mode=0o700, parents=True)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(rng_bytes(KEY_BYTES).hex() + "\n")
    os.chmod(p, 0o600)  # the umask cannot loosen it, but be explicit
    return p


def keygen_cli(argv: list[str]) -> int:
    p = argparse.ArgumentParser(
        prog="covey keygen",
        description="Create a random 32-byte fleet key for signed commands (mode 0600). Copy it to "
        "every agent and ground station of the fleet over a secure channel; pass it with "
        f"--key-file PATH or ${ENV_KEY_FILE}.",
    )
    p.add_argument("-o", "--output", default=str(DEFAULT_KEY_PATH),
                   help=f"where to write the key (default {DEFAULT_KEY_PATH}); never overwritten")  # fmt: skip
    args = p.parse_args(argv)
    try:
        path = write_new_key(args.output)
    except FileExistsError:
        print(
            f"covey keygen: {args.output} already exists; not overwriting a fleet key",
            file=sys.stderr,
        )
        return 1
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        print(
            f"covey keygen: cannot write {args.output!r}: {getattr(exc, 'strerror', None) or exc}",
            file=sys.stderr,
        )
        return 1
    key_id = CommandAuth(read_key_file(path)).key_id
    print(f"wrote fleet key {key_id} to {path} (mode 0600)")
    return 0
