"""VehicleState v3 carries the position uncertainty (pos_sigma_m): round trip, limits with a
reason, a v2 state refused naming its version, random corruption never raising anything but
DecodeError, and the batch decoder agreeing."""

from __future__ import annotations

import math
import random
import struct

import pytest

from comms import schema
from comms.schema import DecodeError, VehicleState, decode
from recording.state_batch import decode_states


def _state(**kw) -> VehicleState:
    base = {
        "vehicle_id": 4,
        "seq": 9,
        "stamp_ns": 123,
        "pos_ned_m": (1.0, 2.0, -3.0),
        "vel_ned_m_s": (0.5, 0.0, 0.0),
        "heading_rad": 0.25,
    }
    return VehicleState(**{**base, **kw})


def test_round_trip_and_default():
    assert _state().pos_sigma_m == 0.0
    for sigma in (0.0, 0.05, 0.5, 2.5, 1000.0):
        s = _state(pos_sigma_m=sigma)
        back = decode(s.encode())
        assert back.pos_sigma_m == pytest.approx(sigma, rel=1e-6)
        assert decode_states([s.encode()])[0] is not None
    assert len(_state().encode()) == 70 and schema.VehicleState.VERSION == 3


@pytest.mark.parametrize(
    ("sigma", "why"),
    [
        (-0.1, "pos_sigma_m=-0.1 is outside"),
        (1000.5, "pos_sigma_m=1000.5 is outside"),
        (math.nan, "pos_sigma_m must be finite"),
        (math.inf, "pos_sigma_m must be finite"),
    ],
)
def test_bad_uncertainty_is_refused_with_the_reason(sigma, why):
    with pytest.raises(DecodeError, match=why):
        _state(pos_sigma_m=sigma).encode()
    raw = bytearray(_state().encode())
    raw[66:70] = struct.pack("<f", sigma)
    with pytest.raises(DecodeError, match="pos_sigma_m"):
        decode(bytes(raw))
    assert decode_states([bytes(raw)]) == [None]


def test_a_v2_state_is_refused_naming_its_version():
    raw = bytearray(_state().encode())
    raw[1] = 2
    with pytest.raises(DecodeError, match="unsupported VEHICLE_STATE version 2 .*speaks 3"):
        decode(bytes(raw[:66]))


def test_random_corruption_only_ever_raises_decode_error():
    rng = random.Random(35)
    good = _state(pos_sigma_m=0.5).encode()
    kept = 0
    for _ in range(3000):
        b = bytearray(good)
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(2, len(b))] = rng.randrange(256)
        try:
            s = decode(bytes(b))
        except DecodeError:
            assert decode_states([bytes(b)]) == [None]
            continue
        kept += 1
        assert 0.0 <= s.pos_sigma_m <= schema.POS_SIGMA_LIMIT_M
    assert kept > 100
