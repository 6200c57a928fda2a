"""Vehicles hold the fleet plan and refuse targets it rules out, with the reason in the ack:
the flight core on its own, a `covey fleet-sim` host, and a real keyed `covey agent` process that
gets the plan over Zenoh, refuses a goto into a keep-out zone, and refuses it again after a
reboot (it pulled the plan from the station at start)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from conftest import keyed_agent_argv

from agent.failsafe import FailsafeConfig
from agent.flight_core import CoreConfig, FlightCore
from agent.hosts import Fleet
from agent.shell_config import FleetSimConfig
from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.plan import Fence, FleetPlan, Zone
from comms.plan_sync import PlanSync
from comms.schema import AckResult, Command, CommandKind, Role
from comms.session import MeshConfig, embedded_router, free_tcp_port
from tests.test_plan_wire import sample_plan
from trust.auth import load_auth
from trust.authority import throwaway_fleet

FLEET = "planagent"


def _cmd(kind: CommandKind, *params: float, nonce: int = 1) -> Command:
    return Command(kind, nonce, 0, params=(*params, 0.0, 0.0, 0.0)[:3])


def test_the_core_refuses_zone_fence_ceiling_and_floor_targets_with_the_reason() -> None:
    core = FlightCore(CoreConfig(failsafe=FailsafeConfig(require_gcs=False)), 1, now_s=0.0)
    here = np.array([20.0, 20.0, 0.0])
    # Without a plan: today's circle (500 m) and altitude limits alone.
    assert "geofence" in core.command(0, _cmd(CommandKind.GOTO_LOCAL, 600, 0, -10), here).reason
    assert "landed" in core.command(0, _cmd(CommandKind.GOTO_LOCAL, 60, 60, -10), here).reason
    plan = dataclasses.replace(
        sample_plan(), fence=Fence(((0, 0), (0, 900), (900, 900), (900, 0)), 3.0, 50.0)
    )
    core.set_plan(plan)

    def reason(kind: CommandKind, *params: float) -> str:
        d = core.command(0, _cmd(kind, *params), here)
        assert d.result is AckResult.REJECTED
        return d.reason

    assert reason(CommandKind.GOTO_LOCAL, 60, 60, -10) == "target inside keep-out zone 'school'"
    assert reason(CommandKind.GOTO_LOCAL, -5, 60, -10) == "target outside the fence"
    assert reason(CommandKind.GOTO_LOCAL, 20, 20, -60) == "target above the 50 m ceiling"
    assert reason(CommandKind.GOTO_LOCAL, 20, 20, -2) == "target below the 3 m floor"
    # The polygon fence replaces the circle: 600 m out but inside the plan's fence is no
    # geofence refusal (only "landed": a goto needs a take-off first).
    assert "landed" in reason(CommandKind.GOTO_LOCAL, 600, 600, -10)
    assert reason(CommandKind.TAKEOFF, 60.0) == "cannot take off here: above the 50 m ceiling"
    inside = np.array([60.0, 60.0, 0.0])
    d = core.command(0, _cmd(CommandKind.TAKEOFF, 10.0), inside)
    assert d.reason == "cannot take off here: inside keep-out zone 'school'"
    core.set_plan(None)
    assert "geofence" in reason(CommandKind.GOTO_LOCAL, 600, 600, -10)


def test_a_fleet_sim_host_refuses_for_every_row() -> None:
    port = free_tcp_port()
    cfg = FleetSimConfig(vehicles=3, mesh=embedded_router(port, fleet=FLEET), spacing_m=10.0)
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: 0.0)
        plan = FleetPlan(FLEET, 1, 0, keep_out=(Zone(((-5, -5), (-5, 5), (5, 5), (5, -5)), "pad"),))
        fleet.plan.push(plan)
        for i in range(3):
            ack = fleet.handle_command(i, _cmd(CommandKind.GOTO_LOCAL, 0, 0, -10, nonce=i + 1))
            assert ack.result is AckResult.REJECTED
            assert ack.reason == "target inside keep-out zone 'pad'"


@pytest.mark.e2e
def test_a_keyed_agent_refuses_a_goto_into_a_zone_and_again_after_a_reboot(tmp_path, procs) -> None:
    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1])
    station = load_auth(str(authority.member_path(Role.STATION, 1)))
    port = free_tcp_port()
    router = MeshConfig(fleet=FLEET, mode="router", connect=(), listen=(f"tcp/127.0.0.1:{port}",))
    argv = [*keyed_agent_argv(authority, 1), "--fleet", FLEET, "--connect"]
    argv += [f"tcp/127.0.0.1:{port}", "--start-ne-m=20,20", "--no-gcs-failsafe"]

    def goto(mesh: Mesh, n: float, e: float, alt: float):
        cmd = Command.goto_local(n, e, -alt, nonce=new_nonce(), stamp_ns=0, targets=(1,))
        return mesh.send_command(cmd, timeout_s=5).outcomes[1]

    with Mesh(router, auth=station) as mesh, PlanSync(mesh.session, FLEET, station) as plans:
        presence = mesh.presence()
        agent = procs.start(*argv)
        assert presence.wait_for(lambda v, g: 1 in v, timeout_s=60), agent.output()
        plans.push(station.sign_plan(sample_plan(1, fleet=FLEET)))
        deadline = time.monotonic() + 10
        while (out := goto(mesh, 60, 60, 10)).status is not OutcomeStatus.REJECTED or (
            "keep-out" not in out.reason
        ):
            assert time.monotonic() < deadline, out
            time.sleep(0.1)
        assert out.reason == "target inside keep-out zone 'school'"
        assert goto(mesh, 300, 20, 10).reason == "target outside the fence"
        assert "landed" in goto(mesh, 30, 30, 10).reason  # allowed by the plan
        # Reboot: a new process with nothing but its key file pulls the plan at start.
        agent.kill()
        agent.wait(10)
        assert presence.wait_for(lambda v, g: 1 not in v, timeout_s=30)
        t0 = time.monotonic()
        procs.start(*argv)
        assert presence.wait_for(lambda v, g: 1 in v, timeout_s=60)
        out = goto(mesh, 60, 60, 10)
        print(f"rebooted agent answered {time.monotonic() - t0:.2f} s after start: {out.reason}")
        assert out.reason == "target inside keep-out zone 'school'"


@pytest.mark.e2e
def test_an_agent_started_with_a_plan_file_holds_it_and_a_forged_file_is_one_line(
    tmp_path, procs
) -> None:
    from comms.plan_io import write_signed_plan
    from trust.auth import sign_plan

    authority = throwaway_fleet(tmp_path / "keys", FLEET, vehicles=[1], stations=[1])
    station = load_auth(str(authority.member_path(Role.STATION, 1)))
    good = write_signed_plan(tmp_path / "plan.bin", sign_plan(authority.key, sample_plan(3, FLEET)))
    forged = dataclasses.replace(sign_plan(authority.key, sample_plan(3, FLEET)), keep_out=())
    bad = write_signed_plan(tmp_path / "forged.bin", forged)
    port = free_tcp_port()
    router = MeshConfig(fleet=FLEET, mode="router", connect=(), listen=(f"tcp/127.0.0.1:{port}",))
    argv = [*keyed_agent_argv(authority, 1), "--fleet", FLEET, "--connect"]
    argv += [f"tcp/127.0.0.1:{port}", "--start-ne-m=20,20", "--no-gcs-failsafe"]
    refused = procs.start(*argv, "--plan", str(bad))
    assert refused.wait(60) == 2
    lines = refused.output().strip().splitlines()
    assert "bad signature" in lines[-1] and "Traceback" not in refused.output(), lines
    with Mesh(router, auth=station) as mesh:  # a station that holds no plan
        presence = mesh.presence()
        procs.start(*argv, "--plan", str(good))
        assert presence.wait_for(lambda v, g: 1 in v, timeout_s=60)
        cmd = Command.goto_local(60, 60, -10, nonce=new_nonce(), stamp_ns=0, targets=(1,))
        out = mesh.send_command(cmd, timeout_s=5).outcomes[1]
        assert out.reason == "target inside keep-out zone 'school'"
