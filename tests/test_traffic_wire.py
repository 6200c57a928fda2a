"""TrafficReport on the wire and who is believed: round trip, a fuzzed decoder, the ADS-B marking
(Python against the C core), and keyed members that take only roster members' fresh signed reports
(real Zenoh sessions)."""

from __future__ import annotations

import dataclasses
import random
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from comms import adsb
from comms.schema import (
    DecodeError,
    Role,
    TrafficFlag,
    TrafficReport,
    TrafficSource,
    decode,
)
from comms.traffic import TrafficListener, TrafficTable, publish_report
from tests.conftest import wait_until
from tests.test_fuzz_decoders import mutate
from trust.auth import load_auth
from trust.authority import throwaway_fleet

FLEET = "covey"
f32 = st.floats(-1e5, 1e5, allow_nan=False, width=32)


@settings(max_examples=200, deadline=None)
@given(
    st.builds(
        TrafficReport,
        reporter_role=st.sampled_from(Role),
        reporter_id=st.integers(1, 65000),
        track_id=st.integers(0, 2**32 - 1),
        source=st.sampled_from(TrafficSource),
        stamp_ns=st.integers(0, 2**64 - 1),
        pos_ned_m=st.tuples(f32, f32, f32),
        vel_ned_m_s=st.tuples(*[st.floats(-900, 900, width=32)] * 3),
        emitter_type=st.integers(0, 19),
        flags=st.sampled_from(TrafficFlag),
        sig=st.sampled_from([b""]) | st.binary(min_size=64, max_size=64),
    )
)
def test_a_traffic_report_round_trips(r: TrafficReport) -> None:
    assert decode(r.encode()) == r


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"reporter_id": 0}, "reporter_id"),
        ({"track_id": 2**32}, "32 bits"),
        ({"emitter_type": 20}, "emitter_type"),
        ({"pos_ned_m": (float("nan"), 0.0, 0.0)}, "finite"),
        ({"vel_ned_m_s": (2000.0, 0.0, 0.0)}, "outside"),
        ({"flags": 2}, "unknown bits"),
        ({"sig": b"x"}, "signature"),
    ],
)
def test_bad_reports_are_refused_with_the_reason(change, why) -> None:
    good = TrafficReport(Role.STATION, 1, 5, TrafficSource.SIM, 1, (0.0, 0.0, -5.0), (1.0, 0, 0))
    with pytest.raises(DecodeError, match=why):
        dataclasses.replace(good, **change).encode()


def test_the_decoder_raises_only_decode_errors_on_mutated_reports() -> None:
    rng = random.Random(35)
    base = TrafficReport(
        Role.VEHICLE, 3, 0x3C6444, TrafficSource.ADSB, 7, (10.0, -4.0, -60.0), (-30, 40, 0), 1
    ).encode()
    for _ in range(3000):
        data = mutate(base, rng)
        try:
            decode(data)
        except DecodeError:
            pass


def test_adsb_marking_in_python_and_c_agree() -> None:
    """comms/adsb.py and covey_traffic.c (what the PX4 module runs) tell covey's own reports
    and manned emitters alike."""
    import ctypes

    from firmware.cpolicy import load_library

    lib = load_library()
    lib.covey_traffic_is_covey.restype = ctypes.c_int32
    lib.covey_traffic_is_covey.argtypes = [ctypes.c_uint32, ctypes.c_char_p, ctypes.c_int32]
    lib.covey_emitter_is_manned.restype = ctypes.c_int32
    lib.covey_emitter_is_manned.argtypes = [ctypes.c_int32]

    def traffic_is_covey(icao: int, callsign: str, emitter: int) -> bool:
        return bool(lib.covey_traffic_is_covey(icao, callsign.encode(), emitter))

    cases = [
        (adsb.covey_icao(7), "CVY7", 14),
        (adsb.covey_icao(7), "CVY7", 1),  # covey's block, a manned emitter: not ours
        (adsb.covey_icao(7), "DLH7", 14),
        (7, "CVY7", 14),  # a real 24-bit address
        (0x3C6444, "DEGAB", 1),
        (0x0200_0001, "TRF200001", 0),
        (0x0100_FFFF, "CVY65535", 14),
        (0x01FF_FFFF, "CVY65535", 14),  # outside the block's 16 id bits
        (adsb.covey_icao(3), "", 14),
        (adsb.covey_icao(3), "CV", 14),
    ]
    for icao, callsign, emitter in cases:
        assert traffic_is_covey(icao, callsign, emitter) == adsb.is_covey_report(
            icao, callsign, emitter
        ), (icao, callsign, emitter)
    for emitter in range(20):
        assert bool(lib.covey_emitter_is_manned(emitter)) == adsb.is_manned(emitter), emitter


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("traffic") / "keys"
    return throwaway_fleet(d, FLEET, vehicles=[1, 2], stations=[1])


@pytest.mark.e2e
def test_keyed_members_take_only_fresh_reports_signed_by_a_roster_member(fleet, tmp_path) -> None:
    from comms.mesh import Mesh
    from comms.session import embedded_peer, embedded_router, free_tcp_port
    from trust.authority import throwaway_fleet as other_fleet

    port = free_tcp_port()
    station = load_auth(str(fleet.member_path(Role.STATION, 1)))
    vehicle = load_auth(str(fleet.member_path(Role.VEHICLE, 2)))
    stranger = load_auth(
        str(other_fleet(tmp_path / "other", FLEET, stations=[1]).member_path(Role.STATION, 1))
    )
    report = TrafficReport(
        Role.STATION, 1, 0x2000001, TrafficSource.SIM, 0, (0.0, 5.0, -5.0), (2.0, 0.0, 0.0)
    )
    table = TrafficTable()
    with (
        Mesh(embedded_router(port, fleet=FLEET), auth=vehicle) as rx_mesh,
        TrafficListener(rx_mesh, table, time.monotonic) as rx,
        Mesh(embedded_peer(port, fleet=FLEET), auth=station) as gcs,
        Mesh(embedded_peer(port, fleet=FLEET)) as open_peer,
        Mesh(embedded_peer(port, fleet=FLEET), auth=stranger) as impostor,
    ):
        time.sleep(0.3)
        now = time.time_ns()
        publish_report(open_peer, dataclasses.replace(report, stamp_ns=now))  # unsigned
        publish_report(impostor, dataclasses.replace(report, stamp_ns=now + 1))  # other key
        publish_report(gcs, dataclasses.replace(report, stamp_ns=now - 60 * 10**9))  # stale
        assert wait_until(lambda: sum(rx.refused.values()) >= 3, 10), rx.refused
        assert len(table) == 0 and rx.accepted == 0
        publish_report(gcs, dataclasses.replace(report, stamp_ns=time.time_ns()))
        assert wait_until(lambda: rx.accepted == 1, 10), rx.refused
        (track,) = table.tracks(time.monotonic())
        assert track.track_id == 0x2000001 and track.source is TrafficSource.SIM
        # a vehicle relays what its receiver heard, signed with its own key
        publish_report(
            rx_mesh,
            TrafficReport(
                Role.VEHICLE,
                2,
                0x3C6444,
                TrafficSource.ADSB,
                time.time_ns(),
                (40.0, -10.0, -60.0),
                (-30.0, 40.0, 0.0),
                1,
                TrafficFlag.MANNED,
            ),
        )
        assert wait_until(lambda: rx.accepted == 2, 10), rx.refused
        with pytest.raises(ValueError, match="needs that member's key"):
            publish_report(gcs, dataclasses.replace(report, reporter_id=9))
    assert rx.refused == {"unsigned": 1, "forged or unknown signer": 1, "stale": 1}


@pytest.mark.e2e
def test_shipped_router_acls_let_stations_and_vehicles_report_traffic_and_no_one_else(
    tmp_path,
) -> None:
    """Through the shipped usrpwd router (comms/zenoh_configs): station gcs-1 reports on its
    traffic key, vehicle 2 on its own; vehicle 2 may not put on a station's key."""
    from test_trust_mesh import Setup

    from comms.mesh import Mesh

    setup = Setup("usrpwd", tmp_path)
    report = TrafficReport(
        Role.STATION, 1, 0x2000001, TrafficSource.SIM, 1, (0.0, 5.0, -5.0), (2.0, 0.0, 0.0)
    )
    table = TrafficTable()
    got: list[TrafficReport] = []
    with (
        Mesh(setup.router()),
        Mesh(setup.client("vehicle-1")) as v1,
        TrafficListener(v1, table, time.monotonic, lambda _t, r: got.append(r)),
        Mesh(setup.client("gcs-1")) as gcs,
        Mesh(setup.client("vehicle-2")) as v2,
    ):
        time.sleep(0.5)
        publish_report(v2, dataclasses.replace(report, track_id=66))  # posing as station 1
        publish_report(gcs, report)
        vehicle_report = dataclasses.replace(report, reporter_role=Role.VEHICLE, reporter_id=2)
        publish_report(v2, dataclasses.replace(vehicle_report, track_id=77))
        assert wait_until(lambda: {r.track_id for r in got} >= {0x2000001, 77}, 10), got
        time.sleep(0.3)
    assert 66 not in {r.track_id for r in got}, "a vehicle put on a station's traffic key"
