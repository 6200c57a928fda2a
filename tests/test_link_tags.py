"""Pairwise link tags on vehicle states (trust/links.py): a receiver with a right tag for it
skips the signature; anything else falls back to the signature, so a tag never lets through what
the signature would refuse. Keys, tags, revocation, the wire trailer, and a real Zenoh mesh."""

from __future__ import annotations

import dataclasses
import random
import time

import numpy as np
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from agent.neighbours import NeighbourSnapshot
from agent.shell_rows import link_receivers
from comms import keys
from comms.gate import Gate, GateConfig
from comms.mesh import Mesh
from comms.schema import (
    LINK_ENTRY_BYTES,
    MAX_LINK_TAGS,
    DecodeError,
    FeedBatch,
    Role,
    VehicleState,
)
from comms.scope import ScopeConfig
from comms.session import embedded_peer, embedded_router, free_tcp_port
from tests.conftest import wait_until
from trust.auth import load_auth
from trust.authority import throwaway_fleet
from trust.links import link_key, tag, x25519_private, x25519_public

FLEET = "links"
MS = 1_000_000


def raw(pub) -> bytes:
    return pub.public_bytes(Encoding.Raw, PublicFormat.Raw)


def state(vid: int, seq: int = 1, stamp_ns: int | None = None, n_m: float = 5.0) -> VehicleState:
    stamp = time.time_ns() if stamp_ns is None else stamp_ns
    return VehicleState(vid, seq, stamp, (n_m, 5.0, -10.0), (0.0, 0.0, 0.0), 0.0)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("links")
    return throwaway_fleet(d, FLEET, vehicles=[1, 2, 3, 4], stations=[1])


def auths(fleet, *ids: int):
    return [load_auth(str(fleet.member_path(Role.VEHICLE, v))) for v in ids]


# -- keys -------------------------------------------------------------------------------------
def test_x25519_twin_of_a_public_key_is_that_of_its_private_key() -> None:
    for _ in range(50):
        ed = Ed25519PrivateKey.generate()
        assert raw(x25519_public(ed.public_key())) == raw(x25519_private(ed).public_key())


def test_link_keys_agree_both_ways_and_differ_by_pair_and_fleet() -> None:
    a, b, c = (Ed25519PrivateKey.generate() for _ in range(3))
    xa, xb, xc = (x25519_private(k) for k in (a, b, c))
    pa, pb, pc = (x25519_public(k.public_key()) for k in (a, b, c))
    ab = link_key(xa, 1, pb, 2, FLEET)
    assert ab == link_key(xb, 2, pa, 1, FLEET)
    assert len(ab) == 32
    assert ab != link_key(xa, 1, pc, 3, FLEET)
    assert link_key(xc, 3, pb, 2, FLEET) not in (ab, link_key(xa, 1, pc, 3, FLEET))
    assert ab != link_key(xa, 1, pb, 2, "another-fleet")
    # the ids are bound too: the same keys under other ids give another key
    assert ab != link_key(xa, 5, pb, 2, FLEET)
    # a tag binds the direction, the receiver and every byte
    t = tag(ab, 1, 2, b"state bytes")
    assert t != tag(ab, 2, 1, b"state bytes")
    assert t != tag(ab, 1, 3, b"state bytes")
    assert t != tag(ab, 1, 2, b"state bytez")
    assert len(t) == 8


# -- sign and check ---------------------------------------------------------------------------
def test_a_right_tag_passes_without_the_signature(fleet) -> None:
    a, b = auths(fleet, 1, 2)
    signed = a.sign_state(state(1), receivers=[2, 3])
    assert len(signed.links) == 2 * LINK_ENTRY_BYTES
    # the signature is still right (the station checks it), and b passes the state by its tag
    assert b.check_state(signed) is None
    assert (b.links.tags_good, b.links.tags_bad) == (1, 0)
    # with the signature broken, the tag alone still passes it: b did not check the signature
    broken = dataclasses.replace(signed, sig=bytes(64))
    assert b.check_state(broken) is None
    assert b.links.tags_good == 2


def test_a_wrong_or_missing_tag_falls_back_to_the_signature(fleet) -> None:
    a, b = auths(fleet, 1, 2)
    signed = a.sign_state(state(1), receivers=[2])
    bad = bytearray(signed.links)
    bad[-1] ^= 0x01
    wrong = dataclasses.replace(signed, links=bytes(bad))
    assert b.check_state(wrong) is None  # the signature is right
    assert b.links.tags_bad == 1
    # wrong tag and wrong signature: refused
    assert "bad signature" in b.check_state(dataclasses.replace(wrong, sig=bytes(64)))
    # tagged for others only: the signature decides
    others = a.sign_state(state(1), receivers=[3, 4])
    good = b.links.tags_good
    assert b.check_state(others) is None
    assert "bad signature" in b.check_state(dataclasses.replace(others, sig=bytes(64)))
    assert b.links.tags_good == good


def test_another_vehicle_cannot_tag_for_a_third(fleet) -> None:
    """Vehicle 3 (compromised) makes a state claiming to be vehicle 1, tagged for vehicle 2
    with every key it has: 2 refuses it."""
    b, c = auths(fleet, 2, 3)
    forged = c.sign_state(state(1), receivers=[2])  # 3's key, 3's link key with 2
    forged = dataclasses.replace(forged, vehicle_id=1)
    assert forged.links  # it carries a tag for 2, made with link key (3, 2)
    assert "bad signature" in b.check_state(forged)
    assert b.links.tags_bad == 1 and b.links.tags_good == 0


def test_a_revoked_vehicle_s_tags_stop_passing(tmp_path) -> None:
    fleet = throwaway_fleet(tmp_path, FLEET, vehicles=[1, 2, 3], stations=[1])
    a, b = auths(fleet, 1, 2)
    assert b.check_state(a.sign_state(state(1), receivers=[2])) is None  # the key is cached
    fleet.revoke(Role.VEHICLE, 1)
    assert b.apply_roster(fleet.roster) is None
    why = b.check_state(a.sign_state(state(1, 2), receivers=[2]))
    assert why is not None and "unknown signer" in why


def test_a_station_tags_nothing_and_checks_by_signature(fleet) -> None:
    (a,) = auths(fleet, 1)
    station = load_auth(str(fleet.member_path(Role.STATION, 1)))
    assert station.links is None
    assert station.sign_state  # a station never publishes states; it checks them
    assert station.check_state(a.sign_state(state(1), receivers=[2])) is None
    assert "bad signature" in station.check_state(
        dataclasses.replace(a.sign_state(state(1), receivers=[2]), sig=bytes(64))
    )


def test_at_most_the_cap_of_tags_and_only_for_members(fleet) -> None:
    (a,) = auths(fleet, 1)
    # 1 (itself) and 99 (not in the roster) get none
    signed = a.sign_state(state(1), receivers=[1, 99, 2, 3, 4])
    ids = [int.from_bytes(signed.links[k : k + 2], "little") for k in range(0, 30, 10)]
    assert ids == [2, 3, 4]
    many = a.links.tags(b"x", [2, 3, 4] * 20)
    assert len(many) == MAX_LINK_TAGS * LINK_ENTRY_BYTES


def test_tags_from_the_kept_macs_equal_tag_on_random_states(fleet) -> None:
    """The fast path (LinkKeys keeps each link's keyed MAC and copies it) equals `tag`, the
    reference, for random state bytes and receiver lists, both ways."""
    a, b = auths(fleet, 1, 2)
    rng = random.Random(7)
    for _ in range(200):
        signed = rng.randbytes(rng.randrange(0, 300))
        receivers = [rng.choice([1, 2, 3, 4, 99]) for _ in range(rng.randrange(0, 8))]
        want = b"".join(
            rid.to_bytes(2, "little") + tag(key, 1, rid, signed)
            for rid in receivers
            if (key := a.links.key(rid)) is not None
        )[: MAX_LINK_TAGS * LINK_ENTRY_BYTES]
        got = a.links.tags(signed, receivers)
        assert got == want
        ok = 2 in receivers
        assert b.links.check(signed, 1, got) is (True if ok else None)


def test_the_gate_takes_a_tagged_state_and_refuses_its_replay(fleet) -> None:
    a, b = auths(fleet, 1, 2)
    gate = Gate(b, GateConfig())
    now = time.time_ns()
    s = a.sign_state(state(1, 1, now), receivers=[2])
    assert gate.admit_state(VehicleState.decode(s.encode()), now) is None
    assert gate.admit_state(VehicleState.decode(s.encode()), now) is not None  # replayed


# -- the wire ---------------------------------------------------------------------------------
def test_the_trailer_round_trips_and_bad_ones_are_refused_with_a_reason(fleet) -> None:
    (a,) = auths(fleet, 1)
    signed = a.sign_state(state(1), receivers=[2, 3])
    data = signed.encode()
    assert VehicleState.decode(data) == signed
    base = len(data) - 1 - len(signed.links)
    assert VehicleState.decode(data[:base]).links == b""  # an untagged state still decodes
    cases = {
        "count 0": data[:base] + b"\x00",
        "count past the entries": data[:base] + b"\x03" + signed.links,
        "count over the cap": data[:base] + bytes((MAX_LINK_TAGS + 1,)) + signed.links,
        "a cut entry": data[:-1],
    }
    for what, bad in cases.items():
        with pytest.raises(DecodeError, match="link tags"):
            VehicleState.decode(bad)
        assert what
    zero_id = data[:base] + b"\x01" + b"\x00\x00" + bytes(8)
    with pytest.raises(DecodeError, match="link tag receiver"):
        VehicleState.decode(zero_id)
    with pytest.raises(DecodeError, match="only on a signed state"):
        dataclasses.replace(state(1), links=signed.links[:LINK_ENTRY_BYTES]).encode()


def test_fuzzed_trailers_never_raise_anything_but_decode_errors(fleet) -> None:
    (a,) = auths(fleet, 1)
    data = a.sign_state(state(1), receivers=[2, 3]).encode()
    base = len(data) - 1 - 2 * LINK_ENTRY_BYTES
    rng = random.Random(35)
    kept = 0
    for _ in range(3000):
        tail = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 80)))
        try:
            s = VehicleState.decode(data[:base] + tail)
        except DecodeError:
            continue
        kept += 1
        assert VehicleState.decode(s.encode()) == s
    assert kept > 0  # some random trailers are well formed (count 1, a valid id)


# -- whom a vehicle tags for --------------------------------------------------------------------
def test_link_receivers_are_the_nearest_vehicles_without_traffic() -> None:
    pos = np.array([[10.0, 0, -5], [1.0, 0, -5], [5.0, 0, -5], [2.0, 0, -5]])
    snap = NeighbourSnapshot(
        pos,
        np.zeros((4, 3)),
        np.zeros(4),
        (7, 8, 9, 10),
        np.zeros(4),
        (),
        cooperative=np.array([True, False, True, True]),
    )
    assert link_receivers(snap, np.zeros(3), 2) == [10, 9]  # 8 is traffic
    assert sorted(link_receivers(snap, np.zeros(3), 32)) == [7, 9, 10]
    assert link_receivers(snap, np.zeros(3), 0) == []


def test_link_receivers_without_traffic_are_the_same_with_or_without_its_column() -> None:
    """No traffic (`cooperative` None, an agent's usual tick: the shortcut) or every row marked
    cooperative (the arrays): the same receivers, in the same order, within and over the limit."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        k = int(rng.integers(1, 12))
        pos = rng.uniform(-30, 30, (k, 3))
        ids = tuple(int(i) for i in rng.choice(np.arange(1, 200), k, replace=False))
        args = (pos, np.zeros((k, 3)), np.zeros(k), ids, np.zeros(k), ())
        plain = NeighbourSnapshot(*args)
        marked = NeighbourSnapshot(*args, cooperative=np.ones(k, bool))
        own = rng.uniform(-30, 30, 3)
        for limit in (1, k - 1, k, k + 3):
            got = link_receivers(plain, own, limit)
            assert got == link_receivers(marked, own, limit)
            assert len(got) == min(k, max(limit, 0))


# -- on a real Zenoh mesh -----------------------------------------------------------------------
def test_a_tagged_state_crosses_a_real_mesh_and_the_feed_carries_it_untagged(fleet) -> None:
    a, b = auths(fleet, 1, 2)
    port = free_tcp_port()
    got: list[VehicleState] = []
    feeds: list[bytes] = []
    with (
        Mesh(embedded_router(port, fleet=FLEET)) as hub,
        Mesh(embedded_peer(port, fleet=FLEET), auth=b) as rx,
        Mesh(embedded_peer(port, fleet=FLEET), auth=a) as tx,
    ):
        hub.session.declare_subscriber(
            keys.all_feeds(FLEET), lambda s: feeds.append(s.payload.to_bytes())
        )
        sub = rx.subscribe_cells(
            lambda s, _t: got.append(s), ScopeConfig().cells_around((0, 0)), polled=True
        )
        seq = 0

        def send() -> bool:
            nonlocal seq
            seq += 1
            tx.publish_state(state(1, seq), receivers=[2])
            sub.drain()
            return bool(got) and bool(feeds)

        assert wait_until(send, 10.0)
        assert b.links.tags_good >= 1 and b.links.tags_bad == 0
        entries = FeedBatch.decode(feeds[-1]).entries
        assert entries and all(VehicleState.decode(e.state).links == b"" for e in entries)
        assert rx.stats.states_refused == 0
