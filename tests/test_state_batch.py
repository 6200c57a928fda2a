"""recording/state_batch.py equals schema.VehicleState.decode: the same states kept, the same values,
on valid states, every limit's edge and random corruptions (the arrays alone, and with the
reference's fallback)."""

from __future__ import annotations

import math
import random

import numpy as np

from comms import schema
from recording.state_batch import _DTYPE, StateRow, _valid, decode_states

FMT = schema.VehicleState._FMT
F32_2PI = float(np.float32(2 * math.pi))  # the float32 nearest 2*pi lies above it


def _fields(rng: random.Random) -> list:
    return [
        schema.MsgType.VEHICLE_STATE,
        schema.VehicleState.VERSION,
        rng.randint(1, schema.MAX_VEHICLE_ID),
        rng.randint(0, 2**32 - 1),
        rng.randint(0, 2**64 - 1),
        *(rng.uniform(-100, 100) for _ in range(3)),
        *(rng.uniform(-10, 10) for _ in range(3)),
        rng.uniform(-6, 6),
        *(rng.uniform(-100, 100) for _ in range(3)),
        rng.choice(list(schema.Mode)),
        rng.randint(0, 1),
        rng.randint(0, 0xFF),
        rng.uniform(0, 100),
        *((k := rng.randint(0, 7)), rng.randint(max(0, k - 1), 9)),  # mission item, items
        rng.uniform(0, 3),  # pos_sigma_m
    ]


EDGES = {  # field index -> values around its limits
    0: [0, 2, 5],
    1: [0, 2],
    2: [0, 1, schema.MAX_VEHICLE_ID, schema.MAX_VEHICLE_ID + 1, 0xFFFF],
    5: [math.nan, math.inf, -math.inf, 1e6, -1e6, 1.0000001e6, 3e38],
    9: [1000.0, -1000.0, 1000.0001, math.nan],
    11: [2 * math.pi, -2 * math.pi, F32_2PI, -F32_2PI, 6.2831, math.inf],
    14: [1e6, 1.01e6, -math.inf],
    15: [6, 7, 255],
    16: [0, 1, 2, 255],
    17: [0xFF, 0x100, 0xFFFF],
    18: [0.0, 100.0, -0.0, 100.00001, -1e-7, math.nan],
    19: [0, 10, 11, 255],
    20: [0, 100, 101, 255],
    21: [0.0, -0.0, 1000.0, 1000.0001, -1e-7, math.nan, math.inf],
}


def _payloads(n: int = 3000, seed: int = 11) -> list[bytes]:
    rng = random.Random(seed)
    out = []
    for k in range(n):
        f = _fields(rng)
        if k % 3 == 1:  # one field at a limit's edge
            idx = rng.choice(list(EDGES))
            f[idx] = rng.choice(EDGES[idx])
        data = bytearray(FMT.pack(*f))
        if k % 3 == 2:  # random corruption
            for _ in range(rng.randint(1, 3)):
                data[rng.randrange(len(data))] = rng.getrandbits(8)
        if k % 17 == 0:
            data += bytes(rng.choice([schema.TAG_BYTES, 1, 63]))  # signed, or a bad length
        if k % 13 == 0:  # signed with a link trailer: well formed, or not (trust/links.py)
            count = rng.choice([1, 2, schema.MAX_LINK_TAGS, 0, schema.MAX_LINK_TAGS + 1])
            ids = [rng.choice([1, 7, schema.MAX_VEHICLE_ID, 0, 0xFFFF]) for _ in range(count)]
            entries = b"".join(i.to_bytes(2, "little") + rng.randbytes(8) for i in ids)
            cut = rng.choice([0, 0, 0, 1, schema.LINK_ENTRY_BYTES])
            data += rng.randbytes(schema.TAG_BYTES) + bytes((count % 256,)) + entries
            data = data[: len(data) - cut]
        if k % 29 == 0:
            data = data[: rng.randrange(len(data))]
        out.append(bytes(data))
    return out


def _reference(p: bytes) -> StateRow | None:
    try:
        msg = schema.decode(p)
    except schema.DecodeError:
        return None
    return StateRow.of(msg) if isinstance(msg, schema.VehicleState) else None


def test_the_batch_keeps_what_decode_keeps_with_the_same_values():
    payloads = _payloads()
    want = [_reference(p) for p in payloads]
    assert 500 < sum(w is not None for w in want) < len(payloads) - 500  # both kinds, plenty
    assert decode_states(payloads) == want
    assert decode_states([]) == []


def test_the_arrays_alone_agree_with_decode():
    """The fallback to schema.decode is for safety; the arrays' verdict already matches."""
    payloads = [p for p in _payloads(seed=12) if len(p) in (FMT.size, FMT.size + schema.TAG_BYTES)]
    a = np.frombuffer(b"".join(p[: FMT.size] for p in payloads), dtype=_DTYPE)
    assert _valid(a).tolist() == [_reference(p) is not None for p in payloads]


def test_float32_values_at_the_limits():
    base = _fields(random.Random(1))
    cases = {11: [F32_2PI, 2 * math.pi, -F32_2PI], 18: [100.0, 100.00001]}
    for idx, values in cases.items():
        for v in values:
            f = list(base)
            f[idx] = v
            p = FMT.pack(*f)
            assert decode_states([p]) == [_reference(p)], (idx, v)
    f = list(base)
    f[11] = F32_2PI
    assert decode_states([FMT.pack(*f)]) == [None]  # above 2*pi once widened, as decode says
