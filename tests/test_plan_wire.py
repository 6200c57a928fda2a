"""The fleet plan as a type, on the wire and signed: geometry checks, `plan_refusal`, the
PlanMessage round trip and its bounds, signatures by the authority and by roster stations, and
mutated or random bytes that only ever raise DecodeError."""

from __future__ import annotations

import dataclasses
import random

import pytest

from comms.plan import (
    MAX_PLAN_VERTICES,
    Fence,
    FleetPlan,
    RallyPoint,
    Zone,
    plan_refusal,
    point_in_polygon,
)
from comms.schema import MAX_PLAN_BYTES, DecodeError, PlanMessage, Role, decode
from trust.auth import FleetAuth, load_auth, sign_plan
from trust.authority import throwaway_fleet

SQUARE = ((0.0, 0.0), (0.0, 200.0), (200.0, 200.0), (200.0, 0.0))
SCHOOL = ((50.0, 50.0), (50.0, 80.0), (80.0, 80.0), (80.0, 50.0))
# A U-shaped (concave) zone: its notch at north 120..140, east 110..130 is outside it.
HANGAR = ((100.0, 100.0), (160.0, 100.0), (160.0, 140.0), (140.0, 140.0), (140.0, 110.0),
          (120.0, 110.0), (120.0, 140.0), (100.0, 140.0))  # fmt: skip


def sample_plan(version: int = 1, fleet: str = "planfleet") -> FleetPlan:
    return FleetPlan(
        fleet,
        version,
        1_700_000_000_000_000_000,
        Fence(SQUARE, floor_alt_m=2.0, ceiling_alt_m=120.0),
        (Zone(SCHOOL, "school"), Zone(HANGAR, "hangar", ceiling_alt_m=30.0)),
        (RallyPoint(10.0, 10.0, 0.0, "home"), RallyPoint(190.0, 10.0, 0.0, "north field")),
    )


def test_refusal_names_the_zone_the_fence_and_the_band() -> None:
    plan = sample_plan()
    assert plan_refusal(plan, (60.0, 60.0), 10.0) == "inside keep-out zone 'school'"
    assert plan_refusal(plan, (50.0, 65.0), 10.0) == "inside keep-out zone 'school'"  # on the edge
    assert plan_refusal(plan, (130.0, 120.0), 10.0) is None  # the U's notch is outside it
    assert plan_refusal(plan, (150.0, 120.0), 10.0) == "inside keep-out zone 'hangar'"
    assert plan_refusal(plan, (150.0, 120.0), 40.0) is None  # above the hangar's 30 m top
    assert plan_refusal(plan, (250.0, 20.0), 10.0) == "outside the fence"
    assert plan_refusal(plan, (20.0, 20.0), 130.0) == "above the 120 m ceiling"
    assert plan_refusal(plan, (20.0, 20.0), 1.0) == "below the 2 m floor"
    assert plan_refusal(plan, (20.0, 20.0), 10.0) is None
    assert plan_refusal(None, (1e5, 1e5), 1e4) is None  # no plan: the circular fence applies
    assert plan.home == RallyPoint(10.0, 10.0, 0.0, "home")


def test_point_in_polygon_matches_shapely_on_random_points() -> None:
    shapely = pytest.importorskip("shapely")
    poly = shapely.Polygon(HANGAR)
    rng = random.Random(7)
    for _ in range(2000):
        n, e = rng.uniform(90, 170), rng.uniform(90, 150)
        assert point_in_polygon(n, e, HANGAR) == poly.intersects(shapely.Point(n, e)), (n, e)


@pytest.mark.parametrize(
    "build, why",
    [
        (lambda: Fence(SQUARE[:2]), "3 to"),
        (lambda: Fence(((0, 0), (0, float("nan")), (1, 1))), "bad vertex"),
        (lambda: Fence(SQUARE, floor_alt_m=50.0, ceiling_alt_m=20.0), "below its ceiling"),
        (lambda: Zone(SCHOOL, "x" * 65), "at most 64 bytes"),
        (lambda: Zone(SCHOOL, "bad\nname"), "printable"),
        (lambda: RallyPoint(float("inf"), 0.0), "finite"),
        (lambda: FleetPlan("f", 0, 0), "version"),
        (lambda: FleetPlan("f", 1, 0, keep_out=(Zone(SQUARE),) * 65), "at most 64"),
        (
            lambda: FleetPlan("f", 1, 0, keep_out=(Zone(((0, 0),) * 256),) * 9),
            f"at most {MAX_PLAN_VERTICES} vertices",
        ),
    ],
)
def test_bad_geometry_is_one_clear_value_error(build, why) -> None:
    with pytest.raises(ValueError, match=why):
        build()


def test_plan_round_trips_and_is_bounded() -> None:
    plan = sample_plan()
    data = PlanMessage(plan).encode()
    back = decode(data)
    assert isinstance(back, PlanMessage)
    assert dataclasses.replace(back.plan, signature=b"") == plan
    assert back.encode() == data
    head = PlanMessage.peek(data)
    assert (head.fleet, head.version, head.signer_id) == (plan.fleet, 1, 0)
    # The largest plan the type allows fits MAX_PLAN_BYTES exactly.
    ring = tuple((float(i), float(i * i % 7)) for i in range(MAX_PLAN_VERTICES // 64))
    biggest = FleetPlan(
        "f" * 32,
        2**32 - 1,
        2**64 - 1,
        None,
        tuple(Zone(ring, "z" * 64, 0.0, 1.0) for _ in range(64)),
        tuple(RallyPoint(0, 0, 0, "r" * 64) for _ in range(32)),
    )
    big = PlanMessage(biggest).encode()
    assert len(big) <= MAX_PLAN_BYTES and decode(big).plan.keep_out == biggest.keep_out
    with pytest.raises(DecodeError, match="at most"):
        PlanMessage.peek(data + bytes(MAX_PLAN_BYTES))


def test_mutated_and_random_plans_only_raise_decode_error() -> None:
    rng = random.Random(20261125)
    seed = PlanMessage(sample_plan()).encode()
    decoded = refused = 0
    for i in range(6000):
        data = bytearray(seed)
        if i % 3 == 0:
            data = data[: rng.randrange(3, len(data))]
        for _ in range(rng.randint(1, 4)):
            data[rng.randrange(2, len(data))] = rng.randrange(256)
        try:
            msg = decode(bytes(data))
        except DecodeError as exc:
            assert str(exc)
            refused += 1
            continue
        assert isinstance(msg, PlanMessage)
        assert decode(msg.encode()) == msg
        decoded += 1
    for _ in range(2000):
        try:
            decode(bytes([11, 1]) + rng.randbytes(rng.randrange(400)))
        except DecodeError:
            refused += 1
    assert decoded > 50 and refused > 1000


@pytest.fixture
def fleet(tmp_path):
    authority = throwaway_fleet(tmp_path / "keys", "planfleet", vehicles=[1], stations=[1, 2])
    vehicle = load_auth(str(authority.member_path(Role.VEHICLE, 1)))
    station = load_auth(str(authority.member_path(Role.STATION, 1)))
    return authority, vehicle, station


def check(auth: FleetAuth, plan: FleetPlan) -> str | None:
    head = PlanMessage.peek(PlanMessage(plan).encode())
    return auth.check_plan(head.signer_id, head.signed, head.sig)


def test_authority_and_station_signatures_verify_others_do_not(fleet) -> None:
    authority, vehicle, station = fleet
    by_authority = sign_plan(authority.key, sample_plan())
    assert by_authority.signer_id == 0 and check(vehicle, by_authority) is None
    by_station = station.sign_plan(sample_plan(2))
    assert by_station.signer_id == 1 and check(vehicle, by_station) is None
    # Tampered geometry, a claimed signer that did not sign, a vehicle's key, an unsigned plan.
    moved = dataclasses.replace(by_station, keep_out=by_station.keep_out[1:])
    assert "bad signature" in check(vehicle, moved)
    assert "bad signature" in check(vehicle, dataclasses.replace(by_station, signer_id=2))
    assert "unknown signer" in check(vehicle, dataclasses.replace(by_station, signer_id=9))
    assert "authority" in check(vehicle, dataclasses.replace(by_authority, version=5))
    assert check(vehicle, sample_plan()) is not None
    with pytest.raises(ValueError, match="only a station key signs plans"):
        vehicle.sign_plan(sample_plan())
    # A roster station's plan stops verifying once that station is revoked.
    authority.revoke(Role.STATION, 1)
    assert vehicle.apply_roster(authority.roster) is None
    assert "unknown signer" in check(vehicle, by_station)
    assert check(vehicle, by_authority) is None
