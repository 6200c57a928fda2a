"""The fleet plan follows the roster's road (comms/plan_sync.py over trust/roster_sync.py's
DocSync), on real Zenoh sessions on loopback: a station's push reaches a vehicle, forged and
older plans are refused, a rebooted vehicle catches up from the station, open mode accepts."""

from __future__ import annotations

import dataclasses
import time

from comms.doc_sync import Offer, RosterSyncConfig
from comms.mesh import Mesh
from comms.plan_sync import PlanSync, plan_confirmations, publish_plan
from comms.schema import PlanMessage, Role
from comms.session import MeshConfig, free_tcp_port
from tests.conftest import wait_until
from tests.test_plan_wire import sample_plan
from trust.auth import load_auth, sign_plan
from trust.authority import throwaway_fleet

FLEET = "planfleet"
SLOW = RosterSyncConfig(pull_every_s=60.0)
"""Periodic pulls a minute apart: what the tests see comes from pushes, start and link pulls."""


def peer(port: int, connect: int | None = None, auth=None) -> Mesh:
    cfg = MeshConfig(
        fleet=FLEET,
        mode="peer",
        connect=(f"tcp/127.0.0.1:{connect}",) if connect else (),
        listen=(f"tcp/127.0.0.1:{port}",),
    )
    return Mesh(cfg, auth=auth, roster_sync=SLOW)


def test_push_reaches_a_vehicle_forged_and_older_refused_a_rebooted_one_catches_up(
    tmp_path,
) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1])
    station = load_auth(str(authority.member_path(Role.STATION, 1)))
    vehicle_key = str(authority.member_path(Role.VEHICLE, 1))
    port = free_tcp_port()
    with peer(port, auth=station) as gcs, PlanSync(gcs.session, FLEET, station, SLOW) as gcs_plan:
        seen = []
        vehicle = load_auth(vehicle_key)
        with (
            peer(free_tcp_port(), port, vehicle) as v,
            PlanSync(v.session, FLEET, vehicle, SLOW, on_plan=seen.append) as v_plan,
        ):
            assert wait_until(lambda: v_plan.counts().get("pulls", 0) >= 1, 5)
            plan = station.sign_plan(sample_plan(3))
            assert gcs_plan.push(plan) is Offer.APPLIED
            assert wait_until(lambda: v_plan.plan is not None, 5), v_plan.counts()
            assert v_plan.plan.version == 3 and v_plan.plan.keep_out == plan.keep_out
            assert [p.version for p in seen] == [3]
            assert {c.version for c in plan_confirmations(gcs.session, FLEET, 3)} == {3}
            # A forged plan (the vehicle's own key cannot sign one; a bit flipped in a station's
            # signature), a plan for another fleet, an older one: all refused, the held one kept.
            forged = dataclasses.replace(station.sign_plan(sample_plan(4)), signature=bytes(64))
            publish_plan(gcs.session, forged)
            other = sign_plan(authority.key, sample_plan(5, fleet="elsewhere"))
            assert v_plan.offer(PlanMessage(other).encode()) is Offer.REFUSED
            assert v_plan.offer(PlanMessage(sample_plan(2)).encode()) is Offer.OLDER
            assert wait_until(lambda: v_plan.counts().get("refused: forged", 0) >= 1, 5)
            assert v_plan.plan.version == 3
            # The authority's plan replaces a station's.
            newer = sign_plan(authority.key, sample_plan(6))
            publish_plan(gcs.session, newer)
            assert wait_until(lambda: v_plan.plan.version == 6, 5)
            assert wait_until(lambda: gcs_plan.plan.version == 6, 5)
        # The vehicle reboots (nothing kept but its key file) and pulls the plan at start.
        t0 = time.monotonic()
        with (
            peer(free_tcp_port(), port, load_auth(vehicle_key)) as v2,
            PlanSync(v2.session, FLEET, v2.auth, SLOW) as v2_plan,
        ):
            assert wait_until(lambda: v2_plan.plan is not None, 10), v2_plan.counts()
            took_s = time.monotonic() - t0
            assert v2_plan.plan.version == 6 and v2_plan.plan.signer_id == 0
    print(f"a rebooted vehicle held plan v6 {took_s:.2f} s after its mesh opened")


def test_open_mode_applies_an_unsigned_plan(tmp_path) -> None:
    port = free_tcp_port()
    with (
        peer(port) as a,
        PlanSync(a.session, FLEET, None, SLOW) as a_plan,
        peer(free_tcp_port(), port) as b,
        PlanSync(b.session, FLEET, None, SLOW) as b_plan,
    ):
        assert wait_until(lambda: b_plan.counts().get("pulls", 0) >= 1, 5)
        assert a_plan.push(sample_plan(1)) is Offer.APPLIED
        assert wait_until(lambda: b_plan.plan is not None, 5), b_plan.counts()
        assert b_plan.plan.keep_out == sample_plan(1).keep_out
