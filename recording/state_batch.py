"""VehicleStates decoded a batch at a time with numpy, for the Foxglove worker.

Decoding one state with schema.VehicleState.decode (header, struct, enums, a frozen dataclass,
then validate()) was half of what converting it to Foxglove's messages cost
(bench/foxglove.py). Here a flush's states are unpacked and checked as arrays, and each valid
one becomes a `StateRow`: the VehicleState fields the conversion reads, under the same names.

The rules are validate()'s, applied in float64 (a float32 compared against 2*pi in float32
would let a heading through that validate() refuses). Whatever the arrays refuse goes to
schema.decode itself, so a state is never dropped here that the reference would keep; the
tests fuzz both to show that the arrays keep nothing the reference refuses, with equal values.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from comms import schema

_DTYPE = np.dtype(
    [
        ("type", "u1"),
        ("version", "u1"),
        ("vehicle_id", "<u2"),
        ("seq", "<u4"),
        ("stamp_ns", "<u8"),
        ("pos", "<f4", (3,)),
        ("vel", "<f4", (3,)),
        ("heading", "<f4"),
        ("goal", "<f4", (3,)),
        ("mode", "u1"),
        ("armed", "u1"),
        ("flags", "<u2"),
        ("battery", "<f4"),
        ("mission_item", "u1"),
        ("mission_items", "u1"),
        ("pos_sigma", "<f4"),
    ]
)
_SIZE = schema.VehicleState._FMT.size
assert _DTYPE.itemsize == _SIZE, "the dtype must match VehicleState's struct layout"
_SIZES = (_SIZE, _SIZE + schema.TAG_BYTES)
_MODES: list[schema.Mode | None] = [None] * 256
for _m in schema.Mode:
    _MODES[_m] = _m


class StateRow(NamedTuple):
    """A decoded, valid VehicleState's fields, named as VehicleState names them."""

    vehicle_id: int
    seq: int
    stamp_ns: int
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    heading_rad: float
    mode: schema.Mode
    armed: bool
    battery_pct: float
    flags: int
    goal_ned_m: tuple[float, float, float]
    pos_sigma_m: float = 0.0

    @classmethod
    def of(cls, s: schema.VehicleState) -> StateRow:
        return cls(
            s.vehicle_id,
            s.seq,
            s.stamp_ns,
            s.pos_ned_m,
            s.vel_ned_m_s,
            s.heading_rad,
            s.mode,
            s.armed,
            s.battery_pct,
            int(s.flags),
            s.goal_ned_m,
            s.pos_sigma_m,
        )


def _within(a: np.ndarray, limit: float) -> np.ndarray:
    """Finite and within [-limit, limit], in float64, over the last axis if there is one."""
    a = a.astype(np.float64)
    ok = np.isfinite(a) & (a >= -limit) & (a <= limit)
    return ok.all(axis=-1) if a.ndim > 1 else ok


def _valid(a: np.ndarray) -> np.ndarray:
    """validate() and decode()'s checks, row by row (one bool per state)."""
    with np.errstate(invalid="ignore"):  # corrupt bytes make signalling NaNs; they fail isfinite
        return _checks(a)


def _checks(a: np.ndarray) -> np.ndarray:
    ok = (a["type"] == schema.MsgType.VEHICLE_STATE) & (a["version"] == schema.VehicleState.VERSION)
    ok &= (a["vehicle_id"] >= 1) & (a["vehicle_id"] <= schema.MAX_VEHICLE_ID)
    ok &= _within(a["pos"], schema.POSITION_LIMIT_M) & _within(a["goal"], schema.POSITION_LIMIT_M)
    ok &= _within(a["vel"], schema.SPEED_LIMIT_M_S)
    ok &= _within(a["heading"], 2 * math.pi)
    battery = a["battery"].astype(np.float64)
    ok &= np.isfinite(battery) & (battery >= 0.0) & (battery <= 100.0)
    ok &= np.isin(a["mode"], [int(m) for m in schema.Mode])
    ok &= (a["armed"] <= 1) & (a["flags"] <= 0xFF)
    n_items = a["mission_items"].astype(np.int64)
    ok &= (n_items <= schema.MAX_MISSION_ITEMS) & (a["mission_item"] <= n_items + 1)
    sigma = a["pos_sigma"].astype(np.float64)
    ok &= np.isfinite(sigma) & (sigma >= 0.0) & (sigma <= schema.POS_SIGMA_LIMIT_M)
    return ok


_SIGNED_END = _SIZE + schema.TAG_BYTES


def _fits(p: bytes) -> bool:
    """The payload has a state's size: unsigned, signed, or signed with a well-formed link
    trailer (schema.links_ok: count byte, entries, receiver ids), which the arrays then skip."""
    if len(p) in _SIZES:
        return True
    if len(p) <= _SIGNED_END:
        return False
    count, links = p[_SIGNED_END], p[_SIGNED_END + 1 :]
    return (
        count >= 1
        and len(links) == count * schema.LINK_ENTRY_BYTES
        and schema.links_ok(links, p[_SIZE:_SIGNED_END])
    )


def decode_states(payloads: Sequence[bytes]) -> list[StateRow | None]:
    """One entry per payload: its StateRow, or None where schema.decode refuses it."""
    out: list[StateRow | None] = [None] * len(payloads)
    fits = [i for i, p in enumerate(payloads) if _fits(p)]
    if fits:
        a = np.frombuffer(b"".join(payloads[i][:_SIZE] for i in fits), dtype=_DTYPE)
        ok = _valid(a)
        good = a[ok]
        rows = zip(
            good["vehicle_id"].tolist(),
            good["seq"].tolist(),
            good["stamp_ns"].tolist(),
            map(tuple, good["pos"].tolist()),
            map(tuple, good["vel"].tolist()),
            good["heading"].tolist(),
            good["mode"].tolist(),
            good["armed"].tolist(),
            good["battery"].tolist(),
            good["flags"].tolist(),
            map(tuple, good["goal"].tolist()),
            good["pos_sigma"].tolist(),
            strict=True,
        )
        kept = [i for i, k in zip(fits, ok.tolist(), strict=True) if k]
        for i, (vid, seq, stamp, pos, vel, hdg, mode, armed, batt, flags, goal, sig) in zip(
            kept, rows, strict=True
        ):
            out[i] = StateRow(
                vid, seq, stamp, pos, vel, hdg, _MODES[mode], armed == 1, batt, flags, goal, sig
            )
    for i, row in enumerate(out):
        if row is None:  # refused above, or not a state's size: the reference decides
            try:
                msg = schema.decode(payloads[i])
            except schema.DecodeError:
                continue
            if isinstance(msg, schema.VehicleState):
                out[i] = StateRow.of(msg)
    return out
