"""`covey fleet-sim`: one process, many vehicles, each a citizen of the mesh on its own."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import holds, wait_until

from agent.agent_cli import fleet_sim_parser as parser
from agent.guidance import GuidanceConfig
from agent.hosts import Fleet
from agent.shell_config import FleetSimConfig, start_grid
from comms.commands import OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandKind, Mode, VehicleState
from comms.session import embedded_peer, embedded_router, free_tcp_port
from policy.runtime import FILTERED_BERTH_SHARE

N = 20
IDS = tuple(range(101, 101 + N))
ALT_M = 6.0


class Latest:
    """Latest state per vehicle, as seen over the mesh by this test process."""

    def __init__(self, mesh: Mesh) -> None:
        self.lock = threading.Lock()
        self.states: dict[int, VehicleState] = {}
        mesh.subscribe_states(self.on_state)

    def on_state(self, s: VehicleState, _t: int) -> None:
        with self.lock:
            self.states[s.vehicle_id] = s

    def wait(self, pred, timeout_s: float, what: str) -> dict[int, VehicleState]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                snap = dict(self.states)
            if holds(pred, snap):
                return snap
            time.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}: {sorted(snap)}")


def test_start_grid_is_square_and_spaced() -> None:
    g = start_grid(5, 4.0, (10.0, 20.0))
    assert g.shape == (5, 3)
    assert g[:, 2].tolist() == [0.0] * 5
    assert g[0].tolist() == [10.0, 20.0, 0.0] and g[3].tolist() == [14.0, 20.0, 0.0]


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="vehicles"):
        FleetSimConfig(vehicles=0)
    with pytest.raises(ValueError, match="rate_hz"):
        FleetSimConfig(rate_hz=0.0)
    with pytest.raises(ValueError):
        FleetSimConfig(first_id=64_990, vehicles=20)  # ids past the schema's limit


def _fly(fleet: Fleet, clock: list[float], seconds: float) -> None:
    for _ in range(round(seconds * 10)):
        clock[0] += 0.1
        fleet.tick(clock[0])


def _cmd(kind: CommandKind, *params: float) -> Command:
    return Command(kind, new_nonce(), 0, params=tuple(params) + (0.0,) * (3 - len(params)))


def test_fleet_in_process_follows_the_agents_mode_machine() -> None:
    """Injected time, no child process: takeoff, a refused goto, kill one, return the others."""
    clock = [0.0]
    port = free_tcp_port()
    cfg = FleetSimConfig(
        vehicles=3, first_id=7, mesh=embedded_router(port, fleet="unit"), spacing_m=10.0
    )
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0])
        assert (
            fleet.handle_command(0, _cmd(CommandKind.GOTO_LOCAL, 5, 5, -5)).result
            is AckResult.REJECTED
        )
        for i in range(3):
            ack = fleet.handle_command(i, _cmd(CommandKind.TAKEOFF, 5.0))
            assert (
                ack.result is AckResult.ACCEPTED
                and ack.vehicle_id == 7 + i
                and ack.mode is Mode.TAKING_OFF
            )
        _fly(fleet, clock, 8.0)
        assert fleet.modes == [Mode.HOLDING] * 3 and np.allclose(fleet.pos_m[:, 2], -5.0, atol=0.3)
        far = fleet.handle_command(1, _cmd(CommandKind.GOTO_LOCAL, 5000, 0, -5))
        assert far.result is AckResult.REJECTED and "geofence" in far.reason
        assert fleet.handle_command(0, _cmd(CommandKind.KILL)).result is AckResult.ACCEPTED
        for i in (1, 2):
            assert (
                fleet.handle_command(i, _cmd(CommandKind.GOTO_LOCAL, 20.0, 10.0 * i, -5)).result
                is AckResult.ACCEPTED
            )
        # The policy decides once per decision period (1 s here) and its velocity is held.
        _fly(fleet, clock, 0.1)
        decided = fleet._decided_s.copy()
        assert decided[1:].tolist() == [clock[0]] * 2  # the new goal: decided at once
        _fly(fleet, clock, 0.5)
        assert np.array_equal(fleet._decided_s, decided)
        _fly(fleet, clock, 0.5)
        assert (fleet._decided_s[1:] > decided[1:]).all()
        _fly(fleet, clock, 2.9)
        assert fleet.modes[0] is Mode.KILLED and fleet.pos_m[0, 2] == 0.0 and not fleet.armed[0]
        assert all(fleet.pos_m[i, 0] > 3.0 for i in (1, 2)), fleet.pos_m
        for i in (1, 2):
            assert fleet.handle_command(i, _cmd(CommandKind.RETURN)).result is AckResult.ACCEPTED
        _fly(fleet, clock, 100.0)  # each on its layer (14 and 18 m), then down
        assert fleet.modes[1:] == [Mode.LANDED, Mode.LANDED] and not fleet.armed[1:].any()
        assert np.allclose(fleet.pos_m[1:, :2], fleet.home_m[1:, :2], atol=1.0)
        assert fleet.stats.ticks == 1120


def test_idle_rows_publish_at_the_idle_rate_with_their_own_seqs() -> None:
    """The agent's rule (comms/state_rate.py) row by row: landed rows at 1 Hz, a row that takes
    off at full rate from the next tick on; each vehicle's seq grows by one per state it sends."""
    clock = [0.0]
    port = free_tcp_port()
    cfg = FleetSimConfig(vehicles=3, first_id=1, mesh=embedded_router(port, fleet="unitidle"))
    seqs: dict[int, list[int]] = {}
    lock = threading.Lock()

    def on_state(s: VehicleState, _t: int) -> None:
        with lock:
            seqs.setdefault(s.vehicle_id, []).append(s.seq)

    with (
        Mesh(cfg.mesh) as mesh,
        Mesh(embedded_peer(port, fleet="unitidle")) as station,
    ):
        station.subscribe_states(on_state)
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0])
        _fly(fleet, clock, 3.0)  # landed: states at 0.1, 1.1 and 2.1 s
        assert fleet.handle_command(0, _cmd(CommandKind.TAKEOFF, 5.0)).result is AckResult.ACCEPTED
        _fly(fleet, clock, 0.5)  # row 0: 3.1 .. 3.5 s; the others once, at 3.1 s
        want = {1: list(range(1, 9)), 2: [1, 2, 3, 4], 3: [1, 2, 3, 4]}

        def complete() -> bool:
            with lock:
                return all(len(seqs.get(v, [])) >= len(w) for v, w in want.items())

        assert wait_until(complete, 10), seqs
        time.sleep(0.3)  # nothing more may come
        with lock:
            assert seqs == want


@pytest.mark.e2e
@pytest.mark.slow
def test_fleet_sim_answers_broadcasts_and_flies(procs) -> None:
    port = free_tcp_port()
    with Mesh(embedded_router(port, fleet="fs")) as mesh:
        latest = Latest(mesh)
        presence = mesh.presence()
        sim = procs.start(
            "-m",
            "covey_cli",
            "fleet-sim",
            "--vehicles",
            str(N),
            "--first-id",
            str(IDS[0]),
            "--fleet",
            "fs",
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--cruise-speed-m-s",
            "3",
            # goals 15 m apart: the policy treats neighbours inside 10 m as conflicts and may
            # circle a goal that has hovering neighbours closer than that
            "--spacing-m",
            "15",
        )
        sim.wait_for("READY", timeout_s=60)
        assert presence.wait_for(lambda v, _g: v >= set(IDS), timeout_s=30), "tokens missing"
        latest.wait(lambda s: set(s) >= set(IDS), 20, "a state from every vehicle")

        # A goto while landed is refused by every vehicle, with the agent's reason.
        refused = mesh.send_command(
            Command.goto_local(0, 0, -5, nonce=new_nonce(), stamp_ns=0), expect=IDS, timeout_s=10
        )
        assert refused.by_status(OutcomeStatus.REJECTED) == list(IDS)
        assert "landed" in refused.outcomes[IDS[0]].reason

        # One broadcast, twenty acks.
        up = mesh.send_command(
            Command.takeoff(ALT_M, nonce=new_nonce(), stamp_ns=0), expect=IDS, timeout_s=10
        )
        assert up.ok and sorted(up.outcomes) == list(IDS), up.summary()
        at_alt = latest.wait(
            lambda s: all(s[v].mode is Mode.HOLDING for v in IDS), 60, "all holding"
        )
        assert all(abs(at_alt[v].pos_ned_m[2] + ALT_M) < 0.6 for v in IDS)
        before = {v: np.array(at_alt[v].pos_ned_m) for v in IDS}

        # A goto to each vehicle's own point 15 m north of its start moves all of them.
        for v in IDS:
            n, e, _ = before[v]
            r = mesh.send_command(
                Command.goto_local(n + 15, e, -ALT_M, nonce=new_nonce(), stamp_ns=0, targets=(v,)),
                timeout_s=10,
            )
            assert r.ok, r.summary()
        moved = latest.wait(
            lambda s: all(s[v].pos_ned_m[0] - before[v][0] > 5.0 for v in IDS),
            60,
            "all moved north",
        )
        assert all(moved[v].mode in (Mode.GOTO, Mode.HOLDING) for v in IDS)
        arrived = latest.wait(
            lambda s: all(s[v].mode is Mode.HOLDING for v in IDS), 90, "all arrived"
        )
        for v in IDS:
            assert (
                np.hypot(
                    arrived[v].pos_ned_m[0] - before[v][0] - 15,
                    arrived[v].pos_ned_m[1] - before[v][1],
                )
                < 1.5
            )

        # Land all; every vehicle touches down and disarms.
        down = mesh.send_command(
            Command(CommandKind.LAND, new_nonce(), 0), expect=IDS, timeout_s=10
        )
        assert down.ok, down.summary()
        latest.wait(
            lambda s: all(s[v].mode is Mode.LANDED and not s[v].armed for v in IDS),
            90,
            "all landed",
        )


def test_fleet_tells_the_policy_its_berth_and_filters_at_the_separation() -> None:
    """--policy-separation-m reaches the fleet's network; the filter keeps --separation-m."""
    args = parser().parse_args(["--policy-separation-m", "2.5"])
    assert args.policy_separation_m == 2.5 and parser().parse_args([]).policy_separation_m is None
    for ps, told_m in ((None, 3.0 * FILTERED_BERTH_SHARE), (2.5, 2.5)):
        cfg = FleetSimConfig(
            vehicles=2,
            first_id=7,
            mesh=embedded_router(free_tcp_port(), fleet="unit"),
            guidance=GuidanceConfig(policy_separation_m=ps),
        )
        with Mesh(cfg.mesh) as mesh:
            fleet = Fleet(cfg, mesh, clock_s=lambda: 0.0)
            assert fleet.policy.dist_scale_m == pytest.approx(told_m / 3.0)
            assert fleet.core.guidance.safety_cfg.radius_m == 3.0
