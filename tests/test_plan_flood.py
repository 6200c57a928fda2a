"""The attack on the fleet plan: an outsider on the mesh floods the plan key with forged plans of
the largest size (each newer than the last, so each must be verified) while a station pushes a
genuine one. The genuine plan is applied at once, every forged one is refused, and the vehicle
reports the flood as a few summary lines, not one per message. Prints the numbers."""

from __future__ import annotations

import dataclasses
import threading
import time

import pytest

from comms.doc_sync import RosterSyncConfig
from comms.mesh import Mesh
from comms.plan import FleetPlan, RallyPoint, Zone
from comms.plan_sync import PlanSync, publish_plan
from comms.schema import MAX_PLAN_BYTES, PlanMessage, Role
from comms.session import MeshConfig, free_tcp_port
from tests.conftest import wait_until
from trust.auth import load_auth
from trust.authority import throwaway_fleet

pytestmark = [pytest.mark.e2e, pytest.mark.slow]
FLEET = "planflood"
FLOOD_S = 4.0


def biggest_forged(version: int) -> FleetPlan:
    ring = tuple((float(i), float(i * i % 7)) for i in range(32))
    plan = FleetPlan(
        FLEET,
        version,
        time.time_ns(),
        None,
        tuple(Zone(ring, "z" * 64, 0.0, 1.0) for _ in range(64)),
        tuple(RallyPoint(0, 0, 0, "r" * 64) for _ in range(32)),
        signer_id=1,
        signature=bytes(range(64)),
    )
    assert len(PlanMessage(plan).encode()) == MAX_PLAN_BYTES - 18  # all but a fence header
    return plan


def test_a_flood_of_forged_plans_never_delays_the_genuine_one(tmp_path) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1])
    station = load_auth(str(authority.member_path(Role.STATION, 1)))
    vehicle = load_auth(str(authority.member_path(Role.VEHICLE, 1)))
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    lines: list[str] = []
    sent = [0]
    stop = threading.Event()
    with (
        Mesh(MeshConfig(fleet=FLEET, mode="router", connect=(), listen=(ep,))) as router,
        Mesh(MeshConfig(fleet=FLEET, mode="client", connect=(ep,)), auth=vehicle) as v,
        PlanSync(
            v.session,
            FLEET,
            vehicle,
            RosterSyncConfig(pull_every_s=60.0),
            on_summary=lines.append,
        ) as follower,
        Mesh(MeshConfig(fleet=FLEET, mode="client", connect=(ep,))) as attacker,
    ):
        assert wait_until(lambda: follower.counts().get("pulls", 0) >= 1, 5)
        template = PlanMessage(biggest_forged(1)).encode()

        def flood() -> None:
            version = 10
            while not stop.is_set():
                version += 1
                forged = dataclasses.replace(biggest_forged(version), stamp_ns=version)
                attacker.session.put(f"covey/{FLEET}/plan", PlanMessage(forged).encode())
                sent[0] += 1

        assert len(template) == MAX_PLAN_BYTES - 18
        quiet = station.sign_plan(FleetPlan(FLEET, 4, time.time_ns()))
        t0 = time.monotonic()
        publish_plan(router.session, quiet)
        assert wait_until(lambda: follower.plan is not None, 10, 0.001), follower.counts()
        quiet_ms = (time.monotonic() - t0) * 1e3
        t = threading.Thread(target=flood, daemon=True)
        t.start()
        time.sleep(FLOOD_S / 2)
        genuine = station.sign_plan(
            FleetPlan(FLEET, 5, time.time_ns(), keep_out=(Zone(((0, 0), (0, 9), (9, 9)), "a"),))
        )
        t0 = time.monotonic()
        publish_plan(router.session, genuine)
        assert wait_until(lambda: follower.plan.version == 5, 10, 0.001), follower.counts()
        took_ms = (time.monotonic() - t0) * 1e3
        time.sleep(FLOOD_S / 2)
        stop.set()
        t.join(5)
        time.sleep(0.5)
    counts = follower.counts()
    refused = sum(n for k, n in counts.items() if k.startswith("refused"))
    print(
        f"forged plans sent {sent[0]} ({sent[0] * MAX_PLAN_BYTES / FLOOD_S / 1e6:.1f} MB/s), "
        f"refused {refused}, older-dropped {counts.get('older', 0)}, genuine applied "
        f"{took_ms:.1f} ms after it was put (quiet: {quiet_ms:.1f} ms), {len(lines)} summary lines; counts {counts}"
    )
    assert follower.plan.version == 5 and follower.plan.signer_id == 1
    assert counts.get("applied") == 2 and refused >= 1
    assert len(lines) <= FLOOD_S + 3  # at most one line a second per cause
