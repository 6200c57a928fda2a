"""A state that FleetAuth.sign_state signs keeps the bytes it signed, and its encode() sends
those (packed once, not twice): the wire bytes equal the reference's, made independently here
(every field packed again, an Ed25519 signature over them, the link tags, the trailer), for
random states; Mesh.publish_state puts exactly those bytes on the state's cell key and offers
the feed the untagged ones; a copy with a field changed packs its own fields again."""

from __future__ import annotations

import copy
import dataclasses
import pickle
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from comms import keys
from comms.mesh import Mesh
from comms.schema import (
    LINK_ENTRY_BYTES,
    MAX_MISSION_ITEMS,
    Mode,
    Role,
    StateFlag,
    VehicleState,
)
from comms.session import embedded_router, free_tcp_port
from trust.auth import FleetAuth, load_auth
from trust.authority import Authority, throwaway_fleet
from trust.identity import signed_message

FLEET = "signonce"
VEHICLES = range(1, 12)
_WIRE = struct.Struct("<BBHIQ3f3ff3fBBHfBBf")
"""A VehicleState's signed part as comms/schema.py packs it (v3), written out again here."""


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Authority:
    return throwaway_fleet(tmp_path_factory.mktemp("keys"), FLEET, vehicles=VEHICLES, stations=[1])


def auth_of(fleet: Authority, role: Role, member: int) -> FleetAuth:
    auth = load_auth(str(fleet.member_path(role, member)))
    assert auth is not None
    return auth


def packed(s: VehicleState) -> bytes:
    """The reference signed bytes: every field packed from the state as it is."""
    return _WIRE.pack(
        int(VehicleState.TYPE),
        3,
        s.vehicle_id,
        s.seq,
        s.stamp_ns,
        *s.pos_ned_m,
        *s.vel_ned_m_s,
        s.heading_rad,
        *s.goal_ned_m,
        int(s.mode),
        int(s.armed),
        int(s.flags),
        s.battery_pct,
        s.mission_item,
        s.mission_items,
        s.pos_sigma_m,
    )


def reference(auth: FleetAuth, s: VehicleState, receivers: list[int]) -> tuple[bytes, bytes]:
    """(wire, feed): the state signed and tagged as sign_state did with dataclasses.replace, and
    encoded as encode() did: signed bytes, signature, count byte and tags; the feed's untagged."""
    signed = packed(s)
    sig = auth.key.private_key.sign(signed_message("state", FLEET, signed))  # Ed25519: the same
    tags = auth.links.tags(signed, receivers) if auth.links is not None else b""
    feed = signed + sig
    return (feed + bytes((len(tags) // LINK_ENTRY_BYTES,)) + tags if tags else feed), feed


def random_state(rng: np.random.Generator, vid: int) -> VehicleState:
    def f(lo: float, hi: float) -> float:
        return -0.0 if rng.random() < 0.05 else float(rng.uniform(lo, hi))

    items = int(rng.integers(0, MAX_MISSION_ITEMS + 1)) if rng.random() < 0.5 else 0
    return VehicleState(
        vehicle_id=vid,
        seq=int(rng.integers(0, 2**32)),
        stamp_ns=int(rng.integers(0, 2**64, dtype=np.uint64)),
        pos_ned_m=(f(-3000, 3000), f(-3000, 3000), f(-200, 0)),
        vel_ned_m_s=(f(-20, 20), f(-20, 20), f(-5, 5)),
        heading_rad=f(-3.2, 3.2),
        mode=list(Mode)[int(rng.integers(len(Mode)))],
        armed=bool(rng.integers(0, 2)),
        battery_pct=f(0, 100),
        flags=StateFlag(int(rng.integers(0, 256))),
        goal_ned_m=(f(-3000, 3000), f(-3000, 3000), f(-200, 0)),
        mission_item=int(rng.integers(0, items + 2)),
        mission_items=items,
        pos_sigma_m=f(0, 1000) * (rng.random() < 0.5),
    )


def receivers_of(rng: np.random.Generator, me: int) -> list[int]:
    """Nearest first: some of the fleet's vehicles, maybe one not in it (no link key)."""
    others = [v for v in VEHICLES if v != me]
    picked = [int(v) for v in rng.permutation(others)[: int(rng.integers(0, len(others) + 1))]]
    if rng.random() < 0.3:
        picked.insert(int(rng.integers(0, len(picked) + 1)), 99)
    return picked


@pytest.mark.parametrize("seed", range(40))
def test_the_signed_state_encodes_the_reference_bytes(fleet: Authority, seed: int) -> None:
    rng = np.random.default_rng(seed)
    me = int(rng.choice(list(VEHICLES)))
    auth = auth_of(fleet, Role.VEHICLE, me)
    state = random_state(rng, me)
    before = copy.deepcopy(state)
    receivers = receivers_of(rng, me)
    wire, _ = reference(auth, state, receivers)
    signed = auth.sign_state(state, receivers)
    assert type(signed) is VehicleState
    assert signed.signed_bytes() == packed(state)
    assert signed.encode() == wire
    # the same fields as dataclasses.replace gives, and the state given is left as it was
    ref = dataclasses.replace(state, sig=signed.sig, links=signed.links)
    assert signed == ref and ref.encode() == wire
    assert state == before and state.encode() == packed(state)
    # what a receiver decodes is the state signed (to float32), its signature and tags right
    got = VehicleState.decode(wire)
    assert got.encode() == wire and (got.sig, got.links) == (signed.sig, signed.links)
    station = auth_of(fleet, Role.STATION, 1)
    assert station.check_state(got) is None
    tagged = [r for r in receivers if r != 99]
    if tagged:
        peer = auth_of(fleet, Role.VEHICLE, tagged[0])
        assert peer.check_state(got) is None
        assert (peer.links.tags_good, peer.links.tags_bad) == (1, 0)


@pytest.mark.parametrize("seed", range(10))
def test_a_copy_with_a_field_changed_packs_its_own_fields(fleet: Authority, seed: int) -> None:
    """The bytes a signed state keeps never travel to a state whose fields differ
    (dataclasses.replace builds a new one); a copy or a pickle keeps the same fields."""
    rng = np.random.default_rng(seed)
    auth = auth_of(fleet, Role.VEHICLE, 2)
    signed = auth.sign_state(random_state(rng, 2), [3, 4])
    wire = signed.encode()
    for change in (
        {"seq": (signed.seq + 1) % 2**32},
        {"vehicle_id": 5},
        {"pos_ned_m": (1.0, 2.0, -3.0)},
        {"flags": StateFlag.REPLAY},
    ):
        changed = dataclasses.replace(signed, **change)
        assert changed.signed_bytes() == packed(changed) != signed.signed_bytes(), change
        assert changed.encode() != wire
        # its signature no longer covers it: refused by the station (no tag for it)
        station = auth_of(fleet, Role.STATION, 1)
        assert "bad signature" in (station.check_state(VehicleState.decode(changed.encode())) or "")
    for same in (copy.copy(signed), pickle.loads(pickle.dumps(signed))):
        assert same == signed and same.encode() == wire


@pytest.mark.parametrize("keyed", [True, False])
def test_publish_state_puts_the_reference_bytes(
    fleet: Authority, keyed: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Keyed: each published state's bytes on its cell's key are the reference's, and the feed
    is offered the same less the link trailer; open: the state's own bytes, unsigned."""
    rng = np.random.default_rng(7 if keyed else 8)
    me = 6
    auth = auth_of(fleet, Role.VEHICLE, me) if keyed else None
    mirror = auth_of(fleet, Role.VEHICLE, me)  # the reference's own copy of the keys
    puts: list[tuple[str, bytes]] = []
    offered: list[tuple[int, bytes]] = []

    class Recording:
        """The session, its publishers recording what they put."""

        def __init__(self, real: object) -> None:
            self.real = real

        def declare_publisher(self, key: str, **kw: object) -> SimpleNamespace:
            return SimpleNamespace(
                put=lambda payload: puts.append((key, bytes(payload))), undeclare=lambda: None
            )

        def __getattr__(self, name: str) -> object:
            return getattr(self.real, name)

    with Mesh(embedded_router(free_tcp_port(), fleet=FLEET), auth=auth) as mesh:
        monkeypatch.setattr(mesh, "_session", Recording(mesh.session))
        offer = mesh._feed.offer

        def offering(vid: int, payload: bytes, now_ns: int) -> list[bytes]:
            offered.append((vid, payload))
            return offer(vid, payload, now_ns)

        monkeypatch.setattr(mesh._feed, "offer", offering)
        want: list[tuple[str, bytes, bytes]] = []
        for _ in range(30):
            state = random_state(rng, me)
            receivers = receivers_of(rng, me)
            mesh.publish_state(state, receivers=receivers)
            key = keys.state(FLEET, me, keys.cell_of(state.pos_ned_m))
            if keyed:
                wire, feed = reference(mirror, state, receivers)
            else:
                wire = feed = packed(state)
            want.append((key, wire, feed))
        monkeypatch.undo()
    feed_key = keys.feed(FLEET, me)
    assert [put for put in puts if put[0] != feed_key] == [(key, wire) for key, wire, _ in want]
    assert offered == [(me, feed) for _, _, feed in want]
    assert mesh.stats.states_sent == len(want)
    assert any(len(wire) > len(feed) for _, wire, feed in want) is keyed


def test_a_signed_state_is_packed_once(fleet: Authority, monkeypatch: pytest.MonkeyPatch) -> None:
    """Signing and encoding a state packs its fields once (the signed bytes are kept), and a
    state not signed is packed by each call as before."""
    packs: list[int] = []
    real = VehicleState._FMT

    class Counting:
        size = real.size

        def pack(self, *fields: object) -> bytes:
            packs.append(1)
            return real.pack(*fields)

        def __getattr__(self, name: str) -> object:
            return getattr(real, name)

    auth = auth_of(fleet, Role.VEHICLE, 4)
    state = random_state(np.random.default_rng(1), 4)
    monkeypatch.setattr(VehicleState, "_FMT", Counting())
    wire = auth.sign_state(state, [5, 6]).encode()
    assert len(packs) == 1
    monkeypatch.undo()
    assert wire == reference(auth, state, [5, 6])[0]
    monkeypatch.setattr(VehicleState, "_FMT", Counting())
    state.encode()
    state.encode()
    assert len(packs) == 3
