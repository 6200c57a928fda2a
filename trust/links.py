"""Pairwise link tags: a cheap check, per receiver, that a vehicle state is its sender's.

Every state stays Ed25519-signed (the station, recorders and any vehicle can check it), but a
neighbour that verifies 10-20 states a tick pays about 0.1 ms each (docs/companion.md, "The
floor under one agent"). So the sender also tags each state for its nearest neighbours, one
64-bit MAC each, with a key it shares with that neighbour alone:

    link key(a, b) = HKDF-SHA256(X25519(a, b), salt "covey-link-v1",
                                 info fleet \\0 low id, high id, low public key, high public key)
    tag(a -> b)    = BLAKE2b-64(key = link key(a, b),
                                "covey-link-v1\\0state\\0" sender id, receiver id, state bytes)

Each member's X25519 key pair is its Ed25519 key's birational twin (RFC 7748's map, as
libsodium's crypto_sign_ed25519_{pk,sk}_to_curve25519), so the roster the authority signs
vouches for both and no key file changes. A tag made with link key(a, b) proves, to b, that a
made it: only a and b can compute the key, and b never tags a state of a's. A compromised
vehicle c learns link keys (c, *) only: it cannot tag for a to b. What a tag does not give is
what a signature gives to third parties (proof to the station, recordings): those keep the
signature.

A receiver with a valid tag for it skips the signature; one whose tag is wrong or missing (a
new neighbour the sender has not heard yet, a stripped trailer) checks the signature as before,
so a tag can only make a check cheaper, never let through what the signature would refuse. A
revoked member has no public key in the roster, hence no link key: its tags are never valid.

X25519 and HKDF are `cryptography`'s; the map from an Edwards y coordinate to a Montgomery u
coordinate (u = (1 + y) / (1 - y) mod p) is the one line of arithmetic done here, and the tests
check it against `cryptography`'s own X25519 public key of the same secret.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
import threading
from collections.abc import Callable, Iterable
from hashlib import blake2b

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from comms.schema import LINK_ENTRY_BYTES, LINK_TAG_BYTES, MAX_LINK_TAGS

_P = 2**255 - 19
_SALT = b"covey-link-v1"
_TAG_HEAD = b"covey-link-v1\0state\0"
_IDS = struct.Struct("<HH")


def x25519_private(key: Ed25519PrivateKey) -> X25519PrivateKey:
    """The X25519 twin of an Ed25519 private key: SHA-512 of its seed, first half (X25519
    clamps it), as libsodium's crypto_sign_ed25519_sk_to_curve25519."""
    seed = key.private_bytes_raw()
    return X25519PrivateKey.from_private_bytes(hashlib.sha512(seed).digest()[:32])


def x25519_public(key: Ed25519PublicKey) -> X25519PublicKey:
    """The X25519 twin of an Ed25519 public key: u = (1 + y) / (1 - y) mod p of its point.
    Raises ValueError for a key with no twin (y = 1, the neutral point) or y >= p."""
    raw = key.public_bytes(Encoding.Raw, PublicFormat.Raw)
    y = int.from_bytes(raw, "little") & ((1 << 255) - 1)
    if y >= _P or y == 1:
        raise ValueError("an Ed25519 public key with no X25519 twin")
    u = (1 + y) * pow(1 - y, _P - 2, _P) % _P
    return X25519PublicKey.from_public_bytes(u.to_bytes(32, "little"))


def link_key(
    own: X25519PrivateKey, own_id: int, peer: X25519PublicKey, peer_id: int, fleet: str
) -> bytes:
    """The 32-byte key vehicles `own_id` and `peer_id` share (the same from either side).
    Raises ValueError for a peer key of small order (an all-zero shared secret)."""
    shared = own.exchange(peer)
    own_pub = own.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
    peer_pub = peer.public_bytes(Encoding.Raw, PublicFormat.Raw)
    (lo_id, lo_pub), (hi_id, hi_pub) = sorted(((own_id, own_pub), (peer_id, peer_pub)))
    info = fleet.encode() + b"\0" + _IDS.pack(lo_id, hi_id) + lo_pub + hi_pub
    return HKDF(hashes.SHA256(), 32, _SALT, info).derive(shared)


def tag_mac(key: bytes, sender_id: int, receiver_id: int) -> blake2b:
    """The MAC of the link from `sender_id` to `receiver_id`, fed all but the state: a copy of
    it, fed a state's signed bytes, gives its tag (`LinkKeys` keeps one per neighbour: keying
    BLAKE2b costs more than the copy)."""
    mac = hashlib.blake2b(key=key, digest_size=LINK_TAG_BYTES)
    mac.update(_TAG_HEAD)
    mac.update(_IDS.pack(sender_id, receiver_id))
    return mac


def tag(key: bytes, sender_id: int, receiver_id: int, signed: bytes) -> bytes:
    """The link tag of a state's signed bytes from `sender_id` to `receiver_id`."""
    mac = tag_mac(key, sender_id, receiver_id)
    mac.update(signed)
    return mac.digest()


class LinkKeys:
    """One vehicle's link keys with the roster's other vehicles, derived when first needed and
    kept while the roster keeps the peer's public key (`public_key(peer_id)`: the current
    roster's key of a vehicle, None if it is not a member). Thread-safe."""

    def __init__(
        self,
        private_key: Ed25519PrivateKey,
        own_id: int,
        fleet: str,
        public_key: Callable[[int], Ed25519PublicKey | None],
    ) -> None:
        self.own_id = own_id
        self.fleet = fleet
        self._own = x25519_private(private_key)
        self._public_key = public_key
        self._keys: dict[int, tuple[Ed25519PublicKey, bytes | None]] = {}
        # by peer: its public key, and `tag_mac` to it and from it (None: no link key)
        self._macs: dict[int, tuple[Ed25519PublicKey, tuple[blake2b, blake2b] | None]] = {}
        self._lock = threading.Lock()
        self.tags_made = 0
        self.tags_good = 0
        """Received states whose tag for this vehicle was right (their signature not checked)."""
        self.tags_bad = 0
        """Received states whose tag for this vehicle was wrong (their signature checked)."""

    def key(self, peer_id: int) -> bytes | None:
        """The link key with vehicle `peer_id`, or None (not in the roster, no twin key)."""
        pub = self._public_key(peer_id)
        if pub is None or peer_id == self.own_id:
            return None
        held = self._keys.get(peer_id)
        if held is not None and held[0] is pub:
            return held[1]
        try:
            key: bytes | None = link_key(
                self._own, self.own_id, x25519_public(pub), peer_id, self.fleet
            )
        except ValueError:
            key = None
        with self._lock:
            self._keys[peer_id] = (pub, key)
        return key

    def _macs_with(self, peer_id: int) -> tuple[blake2b, blake2b] | None:
        """`tag_mac` both ways with `peer_id`, kept while the roster keeps its public key (as
        `key`), or None (no link key)."""
        pub = self._public_key(peer_id)
        held = self._macs.get(peer_id)
        if held is not None and held[0] is pub:
            return held[1]
        key = self.key(peer_id)
        macs = (
            None
            if key is None
            else (tag_mac(key, self.own_id, peer_id), tag_mac(key, peer_id, self.own_id))
        )
        if pub is not None:
            with self._lock:
                self._macs[peer_id] = (pub, macs)
        return macs

    def tags(self, signed: bytes, receivers: Iterable[int]) -> bytes:
        """The link trailer of a state (its `signed_bytes()`) from this vehicle: an entry for
        each of the first MAX_LINK_TAGS `receivers` that has a link key (each `tag`, from the
        link's kept `tag_mac`)."""
        out = bytearray()
        made = 0
        for rid in receivers:
            if made == MAX_LINK_TAGS:
                break
            macs = self._macs_with(rid)
            if macs is None:
                continue
            mac = macs[0].copy()
            mac.update(signed)
            out += rid.to_bytes(2, "little") + mac.digest()
            made += 1
        self.tags_made += made
        return bytes(out)

    def check(self, signed: bytes, sender_id: int, links: bytes) -> bool | None:
        """True: the trailer's tag for this vehicle is `sender_id`'s; False: it has one and it
        is wrong (or the sender has no link key); None: it has none for this vehicle."""
        me = self.own_id.to_bytes(2, "little")
        k = links.find(me)
        while k >= 0 and k % LINK_ENTRY_BYTES:  # inside a tag, not an entry's receiver id
            k = links.find(me, k + 1)
        if k >= 0:
            macs = self._macs_with(sender_id)
            got = links[k + 2 : k + LINK_ENTRY_BYTES]
            if macs is not None:
                mac = macs[1].copy()  # tag(key, sender_id, own_id, signed)
                mac.update(signed)
                if hmac.compare_digest(got, mac.digest()):
                    self.tags_good += 1
                    return True
            self.tags_bad += 1
            return False
        return None
