"""A state as a polled receiver heard it: its bytes and what its head says, decoded only when
chosen.

An agent's tick drains every state that came since the last one (comms/mesh.py
`CellSubscription.drain`), several of the same vehicle when it ticks slower than its relay, and
goes on with each vehicle's newest one that passes the gate. Which one that is, and whether the
gate would thin or refuse it (comms/gate.py `Gate.admit_head`), needs only the vehicle id,
seq, stamp and whether it is signed: `VehicleState.peek` reads them from the head, and the
state is decoded (and placed: comms/relay.py `decode_placed`) only when it is tried. A
superseded or thinned state is never decoded (round thirteen, docs/companion.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple, cast

from comms import keys
from comms.schema import _STATE_HEAD, VehicleState


class Heard(NamedTuple):
    """One state's payload as heard, with its head (`VehicleState.peek`) read (a named tuple:
    a tick builds one per state it drains)."""

    vehicle_id: int
    seq: int
    stamp_ns: int
    signed: bool
    payload: bytes
    key: str
    """The key it came on: its own state key, or the relay block's key."""
    block: tuple[int, keys.Cell] | None = None
    """The relay block (k, anchor cell) it came in (comms/relay.py); None: on its own key."""
    place: int = 0
    """Its place in the relay batch (for reports)."""

    @classmethod
    def of(
        cls, key: str, payload: bytes, block: tuple[int, keys.Cell] | None = None, place: int = 0
    ) -> Heard | None:
        """`payload` as heard on `key`; None if its head is not a state's (decoding it says
        why: comms/mesh.py reports it)."""
        head = VehicleState.peek(payload)
        if head is None:
            return None
        vid, seq, stamp_ns, signed = head
        return cls(vid, seq, stamp_ns, signed, payload, key, block, place)

    @property
    def where(self) -> str:
        """Where it came, as a report names it."""
        return where(self.key, self.block, self.place)


def where(key: str, block: tuple[int, keys.Cell] | None, place: int) -> str:
    """Where a state came, as a report names it: its key, or its place in a relay batch."""
    return key if block is None else f"{key} state {place}"


_new_heard = cast(Callable[[type[Heard], tuple], Heard], tuple.__new__)
"""A Heard from a tuple of its fields, without the named tuple's __new__ (`hear_all`)."""


def hear_all(
    key: str, payloads: Sequence[bytes], block: tuple[int, keys.Cell] | None = None
) -> tuple[list[Heard], list[int]]:
    """`Heard.of(key, payload, block, i)` of each `payloads[i]`, in one loop (a tick hears a
    relay batch of states at once): those whose head is a state's, in order, and the places of
    the others. Equal to `Heard.of` one by one (tests/test_receive_fast.py); `VehicleState.peek`
    is the reference of the head's reading."""
    size, kind, version = VehicleState._FMT.size, int(VehicleState.TYPE), VehicleState.VERSION
    head = _STATE_HEAD.unpack_from
    got: list[Heard] = []
    bad: list[int] = []
    for i, payload in enumerate(payloads):
        if len(payload) < size or payload[0] != kind or payload[1] != version:
            bad.append(i)
            continue
        _, _, vid, seq, stamp_ns = head(payload)
        got.append(
            _new_heard(Heard, (vid, seq, stamp_ns, len(payload) > size, payload, key, block, i))
        )
    return got, bad
