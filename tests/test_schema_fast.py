"""The receive path's fast code against its reference: VehicleState.decode builds the state
without the dataclass's __init__ (equal to the plain construction), the link trailer's receiver
ids are read with one Struct (equal to the entry-by-entry parse), and a vehicle finds its own
link tag with bytes.find (equal to the entry-by-entry search)."""

from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pytest

from comms.schema import (
    LINK_ENTRY_BYTES,
    LINK_TAG_BYTES,
    MAX_LINK_TAGS,
    MAX_VEHICLE_ID,
    TAG_BYTES,
    DecodeError,
    Mode,
    StateFlag,
    VehicleState,
    link_receivers,
    links_ok,
)


def _reference_ids(links: bytes) -> list[int]:
    return [
        int.from_bytes(links[k : k + 2], "little") for k in range(0, len(links), LINK_ENTRY_BYTES)
    ]


def _reference_links_ok(links: bytes, sig: bytes) -> bool:
    n, rest = divmod(len(links), LINK_ENTRY_BYTES)
    return (
        not rest
        and n <= MAX_LINK_TAGS
        and len(sig) == TAG_BYTES
        and all(1 <= rid <= MAX_VEHICLE_ID for rid in _reference_ids(links))
    )


def _links(rng, ids) -> bytes:
    return b"".join(
        int(i).to_bytes(2, "little") + rng.bytes(LINK_TAG_BYTES) for i in np.asarray(ids).tolist()
    )


def test_link_ids_equal_the_reference_parse():
    rng = np.random.default_rng(370)
    edge = [0, 1, 2, MAX_VEHICLE_ID, MAX_VEHICLE_ID + 1, 65535]
    for _ in range(400):
        n = int(rng.integers(0, MAX_LINK_TAGS + 3))
        ids = rng.choice(edge, n) if rng.random() < 0.3 else rng.integers(1, 65536, n)
        links = _links(rng, ids)
        if rng.random() < 0.1 and links:
            links = links[: -int(rng.integers(1, LINK_ENTRY_BYTES))]  # a cut entry
        sig = bytes(TAG_BYTES) if rng.random() < 0.9 else b""
        assert links_ok(links, sig) == _reference_links_ok(links, sig)
        if len(links) % LINK_ENTRY_BYTES == 0:
            assert link_receivers(links) == _reference_ids(links)
    too_long = _links(rng, range(1, MAX_LINK_TAGS + 6))
    assert link_receivers(too_long) == _reference_ids(too_long)
    assert not links_ok(too_long, bytes(TAG_BYTES))


def _state(rng) -> VehicleState:
    items = int(rng.integers(0, 5))
    n = int(rng.integers(0, MAX_LINK_TAGS + 1))
    signed = rng.random() < 0.8
    return VehicleState(
        vehicle_id=int(rng.integers(1, MAX_VEHICLE_ID + 1)),
        seq=int(rng.integers(0, 2**32)),
        stamp_ns=int(rng.integers(0, 2**63)),
        pos_ned_m=tuple(float(np.float32(x)) for x in rng.uniform(-500, 500, 3)),
        vel_ned_m_s=tuple(float(np.float32(x)) for x in rng.uniform(-5, 5, 3)),
        heading_rad=float(np.float32(rng.uniform(-3, 3))),
        mode=Mode(int(rng.choice([int(m) for m in Mode]))),
        armed=bool(rng.random() < 0.5),
        battery_pct=float(np.float32(rng.uniform(0, 100))),
        flags=StateFlag(int(rng.integers(0, 256))),
        goal_ned_m=tuple(float(np.float32(x)) for x in rng.uniform(-500, 500, 3)),
        sig=rng.bytes(TAG_BYTES) if signed else b"",
        mission_item=int(rng.integers(0, items + 2)),
        mission_items=items,
        pos_sigma_m=float(np.float32(rng.uniform(0, 3))),
        links=_links(rng, rng.integers(1, MAX_VEHICLE_ID + 1, n)) if signed else b"",
    )


def test_decode_equals_the_plain_construction():
    rng = np.random.default_rng(371)
    for _ in range(300):
        st = _state(rng)
        got = VehicleState.decode(st.encode())
        assert got == st and hash(got) == hash(st) and repr(got) == repr(st)
        plain = VehicleState(**{f.name: getattr(got, f.name) for f in dataclasses.fields(got)})
        assert plain == got
        assert type(got.mode) is Mode and type(got.flags) is StateFlag
        assert type(got.armed) is bool
        with pytest.raises(dataclasses.FrozenInstanceError):
            got.seq = 1  # type: ignore[misc]


def test_decode_still_refuses_with_the_reason():
    rng = np.random.default_rng(372)
    st = _state(rng)
    raw = bytearray(VehicleState.decode(st.encode()).signed_bytes() + st.sig)
    bad_mode = bytearray(raw)
    bad_mode[struct.calcsize("<BBHIQ3f3ff3f")] = 200  # the mode byte
    with pytest.raises(DecodeError, match="mode=200 is not a valid Mode"):
        VehicleState.decode(bytes(bad_mode))


def test_own_tag_found_as_the_entry_by_entry_search():
    from trust.links import LinkKeys

    rng = np.random.default_rng(373)
    for _ in range(300):
        me = int(rng.integers(1, 300))
        ids = rng.integers(1, 300, int(rng.integers(0, 8)))
        links = bytearray(_links(rng, ids))
        if rng.random() < 0.5 and links:  # my id inside someone's tag
            k = int(rng.integers(0, len(links) // LINK_ENTRY_BYTES)) * LINK_ENTRY_BYTES
            links[k + 3 : k + 5] = me.to_bytes(2, "little")
        links = bytes(links)
        ref = next(
            (
                k
                for k in range(0, len(links), LINK_ENTRY_BYTES)
                if links[k : k + 2] == me.to_bytes(2, "little")
            ),
            None,
        )
        keys = LinkKeys.__new__(LinkKeys)
        keys.own_id, keys.tags_good, keys.tags_bad = me, 0, 0
        keys._macs_with = lambda _sender: None  # no key: a found entry is "wrong"
        assert keys.check(b"x", 7, links) is (None if ref is None else False)
