"""The flight core: one behaviour for every shell.

The same commands on the same state give the same answers and the same flight in `covey agent`
(a core of one vehicle around `SimBackend`) and in `covey fleet-sim` (a core of N rows around
`SimFleet`); the batched guidance equals the single-vehicle fast path; a failed autopilot action
rolls the mode back.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig
from agent.flight_core import FLYING, ActionKind, CoreConfig, FlightCore, Observed, mode_mask
from agent.guidance import BatchGuidance, GuidanceConfig, NeighbourViews
from agent.hosts import Agent, Fleet
from agent.modes import AIRBORNE
from agent.shell_config import AgentConfig, FleetSimConfig
from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandKind, Mode
from comms.session import MeshConfig

TICK_S = 0.1
ISOLATED = MeshConfig(mode="peer", connect=(), listen=("tcp/127.0.0.1:0",))
FENCE = FailsafeConfig(require_gcs=False, geofence_radius_m=300.0)


def _cmd(kind: CommandKind, *params: float, nonce: int) -> Command:
    return Command(kind, nonce, 0, params=(*params, 0.0, 0.0, 0.0)[:3])


# (command, ticks to fly after it)
SCRIPT = [
    (_cmd(CommandKind.GOTO_LOCAL, 5, 5, -5, nonce=1), 1),  # refused: landed
    (_cmd(CommandKind.TAKEOFF, 6.0, nonce=2), 60),
    (_cmd(CommandKind.TAKEOFF, 8.0, nonce=3), 1),  # refused: already airborne
    (_cmd(CommandKind.GOTO_LOCAL, 900, 0, -6, nonce=4), 1),  # refused: outside the fence
    (_cmd(CommandKind.GOTO_LOCAL, 12, -4, -7, nonce=5), 40),
    (_cmd(CommandKind.HOLD, nonce=6), 20),
    (_cmd(CommandKind.GOTO_LOCAL, 12, -4, -7, nonce=7), 120),  # arrives, then holds there
    # home on its layer (id 7: 34 m, agent/returning.py), then lands
    (_cmd(CommandKind.RETURN, nonce=8), 900),
    (_cmd(CommandKind.LAND, nonce=9), 5),
]


def test_agent_and_fleet_sim_answer_and_fly_the_same() -> None:
    clock = [1000.0]
    with Mesh(ISOLATED) as mesh_a, Mesh(ISOLATED) as mesh_f:
        fleet = Fleet(
            FleetSimConfig(
                vehicles=2,
                first_id=7,  # row 0 is vehicle 7, as the agent: the same return layer
                spacing_m=250.0,
                mesh=ISOLATED,
                see_others=False,
                failsafe=FENCE,
                max_neighbours=None,
            ),
            mesh_f,
            clock_s=lambda: clock[0],
        )
        backend = SimBackend(SimConfig(), now_s=clock[0])
        cfg = AgentConfig(vehicle_id=7, mesh=ISOLATED, failsafe=FENCE)
        with Agent(cfg, backend, mesh_a, clock_s=lambda: clock[0]) as agent:
            top_m = 0.0
            for cmd, ticks in SCRIPT:
                a = agent.handle_command(cmd)
                f = fleet.handle_command(0, cmd)
                assert agent.actions.wait_idle(5.0)
                assert (a.result, a.reason, a.mode) == (f.result, f.reason, f.mode), cmd.kind
                for _ in range(ticks):
                    clock[0] += TICK_S
                    agent.tick(clock[0])
                    assert agent.actions.wait_idle(5.0)  # its queue runs off the tick: let it
                    fleet.tick(clock[0])
                    if cmd.kind is CommandKind.RETURN:
                        top_m = max(top_m, -fleet.pos_m[0, 2])
                pa = np.array(backend.telemetry().pos_ned_m)
                np.testing.assert_allclose(pa, fleet.pos_m[0], atol=1e-6, err_msg=str(cmd.kind))
                assert agent.mode is fleet.modes[0], cmd.kind
            assert agent.mode is Mode.LANDED and not backend.telemetry().armed
            assert top_m == pytest.approx(34.0, abs=0.6)  # the return flew vehicle 7's layer
            results = [agent.handle_command(c).result for c, _ in SCRIPT[:1]]
            assert results == [AckResult.REJECTED]


def _views(rng: np.random.Generator, k: int, width: int) -> NeighbourViews:
    pos = rng.uniform(-12, 12, (k, width, 3))
    pos[..., 2] = -5.0
    valid = rng.random((k, width)) < 0.8
    return NeighbourViews(
        pos,
        rng.uniform(-1, 1, (k, width, 3)),
        rng.uniform(-math.pi, math.pi, (k, width)),
        valid,
        valid & (rng.random((k, width)) < 0.2),
    )


def test_batched_guidance_equals_the_single_vehicle_path() -> None:
    """The fast path of one row (what `covey agent` runs) and the batched path of many rows
    (what `covey fleet-sim` runs) give the same setpoints."""
    rng = np.random.default_rng(5)
    cfg = GuidanceConfig()
    k = 12
    views = _views(rng, k, 6)
    pos = np.column_stack([rng.uniform(-3, 3, (k, 2)), np.full(k, -5.0)])
    vel = np.column_stack([rng.uniform(-1, 1, (k, 2)), np.zeros(k)])
    heading = rng.uniform(-math.pi, math.pi, k)
    target = np.column_stack([rng.uniform(-30, 30, (k, 2)), np.full(k, -6.0)])
    holding = rng.random(k) < 0.3
    batch = BatchGuidance(cfg, k)
    out = batch.step(0.0, np.arange(k), pos, vel, heading, target, holding, views)
    assert out.decided[~holding].all() and not out.decided[holding].any()
    assert out.filtered.any(), "the scene should make the filter act somewhere"
    for r in range(k):
        one = BatchGuidance(cfg, 1, batch.policy)
        row = NeighbourViews(
            *(
                a[r : r + 1]
                for a in (views.pos_m, views.vel_m_s, views.heading_rad, views.valid, views.stale)
            )
        )
        o = one.step(
            0.0,
            np.zeros(1, int),
            pos[r : r + 1],
            vel[r : r + 1],
            heading[r : r + 1],
            target[r : r + 1],
            holding[r : r + 1],
            row,
        )
        np.testing.assert_allclose(
            o.vel_ned_m_s[0], out.vel_ned_m_s[r], atol=1e-6, err_msg=f"row {r}"
        )
        assert o.heading_rad[0] == pytest.approx(out.heading_rad[r], abs=1e-5)
        assert (o.filtered[0], o.slowed_for_stale[0]) == (out.filtered[r], out.slowed_for_stale[r])


def _observed(pos: np.ndarray, armed: bool, in_air: bool) -> Observed:
    n = len(pos)
    return Observed(
        pos,
        np.zeros((n, 3)),
        np.full(n, armed),
        np.full(n, in_air),
        np.full(n, 90.0),
        np.ones(n, bool),
    )


def test_a_failed_action_rolls_the_mode_back() -> None:
    core = FlightCore(CoreConfig(failsafe=FENCE), 2, now_s=0.0)
    ground = np.zeros(3)
    d = core.command(1, _cmd(CommandKind.TAKEOFF, 5.0, nonce=11), ground)
    assert d.result is AckResult.ACCEPTED and d.mode is Mode.TAKING_OFF
    (takeoff,) = d.actions
    assert (takeoff.kind, takeoff.alt_m, takeoff.nonce, takeoff.index) == (
        ActionKind.TAKEOFF,
        5.0,
        11,
        1,
    )
    assert core.action_failed(takeoff, "arming denied")
    assert core.modes == [Mode.LANDED, Mode.LANDED]
    notes = [n.text for n in core.drain_notes()]
    assert any("taking_off -> landed (takeoff failed)" in t for t in notes), notes
    # A failure that comes after another command changed the mode does not undo that command.
    d = core.command(1, _cmd(CommandKind.TAKEOFF, 5.0, nonce=12), ground)
    core.command(1, _cmd(CommandKind.KILL, nonce=13), ground)
    assert not core.action_failed(d.actions[0], "arming denied")
    assert core.mode_of(1) is Mode.KILLED


def test_onboard_guidance_gets_goto_actions_and_global_targets_pass_through() -> None:
    """In onboard mode (the relay to a PX4 that runs the policy in C) a goto is an autopilot
    action; a goto-global keeps its global target, so the relay need not convert it back."""
    core = FlightCore(CoreConfig(failsafe=FENCE), 1, now_s=0.0, velocity_mode=False)
    air = np.array([[0.0, 0.0, -5.0]])
    core.command(0, _cmd(CommandKind.TAKEOFF, 5.0, nonce=1), np.zeros(3))
    core.observe(1.0, _observed(air, True, True), True)
    assert core.mode_of(0) is Mode.HOLDING
    lat, lon = core.cfg.origin.lat_deg + 1e-4, core.cfg.origin.lon_deg
    d = core.command(
        0, _cmd(CommandKind.GOTO_GLOBAL, lat, lon, core.cfg.origin.alt_m + 8.0, nonce=2), air[0]
    )
    (goto,) = d.actions
    assert goto.kind is ActionKind.GOTO and goto.target_global == (
        lat,
        lon,
        core.cfg.origin.alt_m + 8.0,
    )
    assert goto.target_ned_m[0] == pytest.approx(11.1, abs=0.1) and goto.target_ned_m[
        2
    ] == pytest.approx(-8.0)
    d = core.command(0, _cmd(CommandKind.HOLD, nonce=3), air[0])
    assert [a.kind for a in d.actions] == [ActionKind.HOLD]


def test_vehicle_events_come_from_telemetry_for_every_row() -> None:
    core = FlightCore(CoreConfig(failsafe=FENCE), 3, now_s=0.0)
    for i in range(3):
        core.command(i, _cmd(CommandKind.TAKEOFF, 4.0, nonce=20 + i), np.zeros(3))
    pos = np.array([[0.0, 0.0, -3.9], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0]])
    core.observe(1.0, _observed(pos, True, True), True)
    assert core.modes == [Mode.HOLDING, Mode.TAKING_OFF, Mode.TAKING_OFF]
    assert core.hold_m[0, 2] == -4.0  # holds at the take-off altitude, not where it was


def test_mode_masks_equal_isin() -> None:
    """The lookup tables the core tests modes with (fast at N = 1) equal `np.isin`."""
    modes = np.array([int(m) for m in Mode] * 3, np.int8)
    for subset in (FLYING, AIRBORNE, (Mode.LANDING, Mode.KILLED), ()):
        np.testing.assert_array_equal(
            mode_mask(subset)[modes], np.isin(modes, [int(m) for m in subset])
        )


def test_poor_gnss_is_told_once_each_way() -> None:
    """A vehicle whose position 1-sigma goes beyond the preset's 0.5 m (by the warning share)
    gets one warning naming the berth the filter then keeps, and one note when it is back
    within 0.5 m; a sigma wandering between the two says nothing more."""
    from dataclasses import replace

    core = FlightCore(CoreConfig(failsafe=FENCE), 2, now_s=0.0)
    ground = np.zeros((2, 3))

    def tick(t: float, sigmas) -> list:
        core.observe(
            t, replace(_observed(ground, False, False), pos_sigma_m=np.array(sigmas)), True
        )
        return core.drain_notes()

    assert tick(0.1, [0.5, 0.3]) == []
    (warn,) = tick(0.2, [0.5, 1.0])
    assert warn.index == 1 and warn.severity.name == "WARNING"
    # 3.6 m + 4 sqrt(2) x 1 m between estimates
    assert "GNSS 1-sigma 1.00 m" in warn.text and "9.3 m" in warn.text and "RTK" in warn.text
    assert tick(0.3, [0.5, 1.2]) == []  # still poor: said already
    assert tick(0.4, [0.58, 0.55]) == []  # row 0 below the warning share; row 1 not yet back
    (back,) = tick(0.5, [0.5, 0.45])
    assert back.index == 1 and "back within 0.5 m" in back.text
    assert tick(0.6, [0.5, 0.55]) == []
    (again,) = tick(0.7, [0.5, 0.61])
    assert again.index == 1
