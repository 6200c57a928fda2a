"""Calm ticks (agent/calm.py): a flying vehicle with nothing near may tick at 3.3 Hz; a
neighbour, traffic, a keep-out zone, its goal or an autopilot action near enough for the filter
or the arrival to need 10 Hz ends it. In-process agents on a real mesh with injected time, then
a real agent loop on the real clock."""

from __future__ import annotations

import math
import threading
import time

import pytest
from conftest import wait_until

from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig
from agent.hosts import Agent, Fleet
from agent.shell_config import AgentConfig, FleetSimConfig
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.plan import FleetPlan, Zone
from comms.schema import AckResult, Command, CommandKind, Mode, TrafficSource, VehicleState
from comms.session import embedded_router, free_tcp_port
from comms.traffic import TrafficTrack

FLEET = "calm"
NO_GCS = FailsafeConfig(require_gcs=False)


def fly(agent: Agent, t: list[float], goal_ne_m=(400.0, 0.0)) -> None:
    """Take off, hold, then a goto far north; ticks on the injected clock."""
    agent.handle_command(Command.takeoff(10.0, nonce=new_nonce(), stamp_ns=0))
    for _ in range(600):
        t[0] += 0.1
        agent.tick(t[0])
        if agent.mode is Mode.HOLDING:
            break
    assert agent.mode is Mode.HOLDING
    ack = agent.handle_command(Command.goto_local(*goal_ne_m, -10.0, nonce=new_nonce(), stamp_ns=0))
    assert ack.result is AckResult.ACCEPTED, ack.reason
    for _ in range(30):  # up to speed
        t[0] += 0.1
        agent.tick(t[0])


SEQ = [0]


def neighbour(agent: Agent, t: list[float], dn_m: float, de_m: float, vel=(0.0, 0.0, 0.0)):
    here = agent.vehicles.read().pos_m[0]
    SEQ[0] += 1
    s = VehicleState(
        50,
        SEQ[0],
        int(t[0] * 1e9),
        (float(here[0] + dn_m), float(here[1] + de_m), float(here[2])),
        vel,
        0.0,
        mode=Mode.GOTO,
        armed=True,
    )
    agent.table.update(s, t[0])


def tick(agent: Agent, t: list[float], n: int = 1) -> None:
    for _ in range(n):
        t[0] += 0.1
        agent.tick(t[0])


@pytest.fixture
def agent(mesh_trio):
    _hub, a, _b = mesh_trio
    t = [0.0]
    with Agent(
        AgentConfig(vehicle_id=1, failsafe=NO_GCS),
        SimBackend(SimConfig(), now_s=0.0),
        a,
        clock_s=lambda: t[0],
    ) as ag:
        yield ag, t


def test_a_vehicle_flying_alone_is_calm_and_a_holding_one_too(agent) -> None:
    ag, t = agent
    assert ag.cfg.calm_every == 3
    fly(ag, t)
    assert ag.mode is Mode.GOTO and ag._calm
    ag.handle_command(Command(kind=CommandKind.HOLD, nonce=new_nonce(), stamp_ns=0))
    tick(ag, t, 20)
    assert ag.mode is Mode.HOLDING and ag._calm


def test_a_neighbour_within_the_filter_s_reach_ends_calm(agent) -> None:
    """The pair's closest approach within the 4 s horizon at the velocities now (agent/calm.py
    `closest_approach_m`) against 3.6 + (1 + 1) x 0.6 + 1 = 5.8 m: a neighbour the vehicle
    flies towards ends calm further out than one it passes or leaves behind."""
    ag, t = agent
    fly(ag, t)  # north at 1 m/s
    for dn_m, de_m, vel, calm in (
        (9.0, 0.0, (0.0, 0.0, 0.0), False),  # at rest ahead: 9 - 1 x 4 = 5 m
        (11.0, 0.0, (0.0, 0.0, 0.0), True),  # 7 m
        (0.0, 9.0, (0.0, 0.0, 0.0), True),  # abeam at rest: 9 m, and opening
        (0.0, 5.5, (0.0, 0.0, 0.0), False),  # abeam, inside 5.8 m already
        (-6.5, 0.0, (0.0, 0.0, 0.0), True),  # behind: left behind
        (13.0, 0.0, (-1.0, 0.0, 0.0), False),  # head-on: 13 - 2 x 4 = 5 m
        (15.0, 0.0, (-1.0, 0.0, 0.0), True),  # 7 m
        (0.0, 18.0, (0.0, -5.0, 0.0), False),  # crossing fast: 3.5 m, within 3.6 + 6 x 0.6 + 1
    ):
        ag.table.forget(50)
        neighbour(ag, t, dn_m, de_m, vel=vel)
        tick(ag, t)
        assert ag._calm is calm, (dn_m, de_m, vel)


def test_closest_approach_equals_a_fine_walk_along_the_relative_path() -> None:
    """`closest_approach_m` against the reference: the pair's distance sampled every ms."""
    import numpy as np

    from agent.calm import closest_approach_m

    rng = np.random.default_rng(7)
    pos, vel = rng.uniform(-20, 20, (4, 3)), rng.uniform(-3, 3, (4, 3))
    o_pos, o_vel = rng.uniform(-20, 20, (6, 3)), rng.uniform(-3, 3, (6, 3))
    o_vel[0] = vel[0]  # no relative velocity: the gap now
    got = closest_approach_m(pos, vel, o_pos, o_vel, 4.0)
    ts = np.linspace(0.0, 4.0, 4001)
    for i in range(4):
        for j in range(6):
            p = o_pos[j, :2] - pos[i, :2]
            v = o_vel[j, :2] - vel[i, :2]
            want = np.hypot(p[0] + v[0] * ts, p[1] + v[1] * ts).min()
            assert got[i, j] == pytest.approx(want, abs=1e-5)
            assert got[i, j] <= np.hypot(*p) + 1e-12


def test_a_neighbour_flying_alongside_is_calm_beyond_the_pair_s_own_berth(agent) -> None:
    """Side by side at the same velocity (a formation in transit): no relative velocity, so
    only what either can fly in H: 3.6 + 0 + (1 + 1) x 0.6 + 1 = 5.8 m."""
    ag, t = agent
    fly(ag, t)
    v = tuple(float(x) for x in ag.vehicles.read().vel_m_s[0])
    neighbour(ag, t, 0.0, 7.0, vel=v)
    tick(ag, t)
    assert ag._calm
    neighbour(ag, t, 0.0, 5.0, vel=v)
    tick(ag, t)
    assert not ag._calm


def test_holding_beside_holding_neighbours_is_calm_until_one_moves(agent) -> None:
    """A hovering grid 8 m apart (covey demo): 3.6 + 0 + (0 + 1) x 0.6 + 1 = 5.2 m at rest."""
    ag, t = agent
    fly(ag, t)
    ag.handle_command(Command(kind=CommandKind.HOLD, nonce=new_nonce(), stamp_ns=0))
    tick(ag, t, 30)
    assert ag.mode is Mode.HOLDING
    for dn_m, de_m in ((8.0, 0.0), (0.0, 8.0), (-8.0, 0.0), (0.0, -8.0)):
        neighbour(ag, t, dn_m, de_m)
    tick(ag, t)
    assert ag._calm
    neighbour(ag, t, 0.0, 8.0, vel=(0.0, -1.0, 0.0))  # one starts towards it
    tick(ag, t)
    assert not ag._calm
    neighbour(ag, t, 0.0, 5.0)  # at rest, but within 5.2 m
    tick(ag, t)
    assert not ag._calm


def test_a_holder_at_rest_with_nobody_near_ticks_at_the_hold_rate(agent) -> None:
    """The hold tier (agent/calm.py `holding_at_rest`, 1 Hz): holding at rest with neighbours
    at rest beyond 3.6 + 0 + (0 + 1) x 2 + 1 = 6.6 m (8 m: the demo's grid), a hold tick is
    ten grid periods; a neighbour at 6 m keeps the calm tier (3 periods; 5.2 m), one setting
    off towards it ends calm, and flying (not at rest) is the calm tier only."""
    ag, t = agent
    assert (ag.cfg.calm_every, ag.cfg.hold_every) == (3, 10)
    fly(ag, t)
    assert ag._calm and ag._calm_periods == 3  # in a goto: never the hold tier
    ag.handle_command(Command(kind=CommandKind.HOLD, nonce=new_nonce(), stamp_ns=0))
    tick(ag, t, 30)
    assert ag.mode is Mode.HOLDING and ag._calm and ag._calm_periods == 10
    for dn_m, de_m in ((8.0, 0.0), (0.0, 8.0), (-8.0, 0.0), (0.0, -8.0)):
        neighbour(ag, t, dn_m, de_m)
    tick(ag, t)
    assert ag._calm and ag._calm_periods == 10
    neighbour(ag, t, 0.0, 6.0)  # at rest within 6.6 m, beyond 5.2 m: the calm tier
    tick(ag, t)
    assert ag._calm and ag._calm_periods == 3
    neighbour(ag, t, 0.0, 8.0, vel=(0.0, -1.0, 0.0))  # sets off towards it
    tick(ag, t)
    assert not ag._calm


def test_the_hold_tier_follows_its_settings() -> None:
    from agent.shell_config import AgentConfig as Cfg
    from comms.state_rate import SteadyConfig

    assert Cfg(vehicle_id=1, hold_tick_hz=2.0).hold_every == 5
    assert Cfg(vehicle_id=1, hold_tick_hz=5.0).hold_every == 3  # never above the calm rate
    steady = SteadyConfig(hold_state_hz=2.0)  # never below the hold state rate
    assert Cfg(vehicle_id=1, steady=steady).hold_every == 5
    with pytest.raises(ValueError, match="hold_tick_hz must be within \\[0.5, 100\\]"):
        Cfg(vehicle_id=1, hold_tick_hz=0.4)


def test_traffic_that_does_not_cooperate_is_taken_at_its_speed(agent) -> None:
    ag, t = agent
    fly(ag, t)
    here = ag.vehicles.read().pos_m[0]
    track = TrafficTrack(
        900,
        (float(here[0]), float(here[1] + 40.0), float(here[2])),
        (0.0, -8.0, 0.0),
        TrafficSource.SIM,
        False,
        t[0],
    )
    ag.traffic.put(track)
    tick(ag, t)
    assert not ag._calm  # 8 m/s toward it, 40 m away: within 3.6 + 12.5 x 4.6 m


def test_its_goal_a_keep_out_zone_and_an_action_end_calm(agent) -> None:
    ag, t = agent
    fly(ag, t, goal_ne_m=(40.0, 0.0))
    assert ag._calm
    # nearing the goal: within 1 m + 1.6 m of it the ticks are back at 10 Hz to arrive
    for _ in range(600):
        tick(ag, t)
        pos = ag.vehicles.read().pos_m[0]
        if math.hypot(40.0 - pos[0], pos[1]) < 2.5:
            break
    assert not ag._calm
    # a zone 6 m ahead of a vehicle flying north: within 1.8 + 1 x 4.6 + 1 = 7.4 m
    ag.handle_command(Command.goto_local(200.0, 0.0, -10.0, nonce=new_nonce(), stamp_ns=0))
    tick(ag, t, 30)
    assert ag._calm
    pos = ag.vehicles.read().pos_m[0]
    n0 = float(pos[0]) + 6.0
    zone = Zone(((n0, -20.0), (n0, 20.0), (n0 + 5.0, 20.0), (n0 + 5.0, -20.0)), name="pad")
    ag.core.set_plan(FleetPlan(FLEET, 1, 0, keep_out=(zone,)))
    tick(ag, t)
    assert not ag._calm
    ag.core.set_plan(None)
    tick(ag, t)
    assert ag._calm
    ag.handle_command(Command(kind=CommandKind.LAND, nonce=new_nonce(), stamp_ns=0))
    tick(ag, t)
    assert not ag._calm


def test_a_real_agent_loop_ticks_at_the_calm_rate_alone_and_at_10_hz_near_another(
    mesh_trio,
) -> None:
    """The agent's own loop (real clock, real Zenoh): hovering alone at rest it ticks about once
    a second (the hold tier) and a goto is taken at once; flying alone it ticks about 3.3 times
    a second; with a neighbour 8 m off flying the other way it ticks at 10 Hz (fewer on a loaded
    machine, but more than the calm rate allows)."""
    hub, a, b = mesh_trio
    stop = threading.Event()
    cfg = AgentConfig(vehicle_id=1, failsafe=NO_GCS)
    with Agent(cfg, SimBackend(SimConfig(), now_s=time.monotonic()), a) as ag:
        loop = threading.Thread(target=ag.run, args=(stop,), daemon=True)
        loop.start()
        try:
            for cmd in (
                Command.takeoff(6.0, nonce=new_nonce(), stamp_ns=time.time_ns()),
                Command.goto_local(300.0, 0.0, -6.0, nonce=new_nonce(), stamp_ns=time.time_ns()),
            ):
                wait_until(lambda: ag.mode in (Mode.LANDED, Mode.HOLDING), 20.0)
                if ag.mode is Mode.HOLDING:  # hovering alone at rest: the 1 Hz hold tier
                    assert wait_until(lambda: ag._calm_periods == 10, 10.0)
                    t0, n0 = time.monotonic(), ag.stats.ticks
                    time.sleep(3.0)
                    hold_hz = (ag.stats.ticks - n0) / (time.monotonic() - t0)
                    assert hold_hz <= 1.0 + 0.5, hold_hz
                for _ in range(50):
                    res = hub.send_command(cmd, expect=(1,), timeout_s=2.0)
                    if res.ok:
                        break
                    time.sleep(0.1)  # the route from the station to the agent's queryable
                assert res.ok, res.summary()
            assert wait_until(lambda: ag.mode is Mode.GOTO and ag._calm, 10.0)
            t0, n0 = time.monotonic(), ag.stats.ticks
            time.sleep(2.0)
            calm_hz = (ag.stats.ticks - n0) / (time.monotonic() - t0)
            assert calm_hz <= 10.0 / 3 + 0.6, calm_hz
            # a neighbour 12 m ahead, 2 m east, flying south, on the mesh: it would pass 4.5 m
            # away within 4 s (calm needs 5.8 m)
            stop_nb = threading.Event()

            def beside() -> None:
                seq = 0
                while not stop_nb.is_set():
                    seq += 1
                    p = ag.vehicles.read().pos_m[0]
                    b.publish_state(
                        VehicleState(
                            2,
                            seq,
                            time.time_ns(),
                            (float(p[0]) + 12.0, float(p[1]) + 2.0, float(p[2])),
                            (-1.0, 0.0, 0.0),
                            0.0,
                            mode=Mode.GOTO,
                            armed=True,
                        )
                    )
                    time.sleep(0.1)

            nb = threading.Thread(target=beside, daemon=True)
            nb.start()
            try:
                assert wait_until(lambda: not ag._calm, 10.0)
                t1, n1 = time.monotonic(), ag.stats.ticks
                time.sleep(2.0)
                busy_hz = (ag.stats.ticks - n1) / (time.monotonic() - t1)
                assert busy_hz > 10.0 / 3 + 1.0, (busy_hz, calm_hz)
            finally:
                stop_nb.set()
                nb.join(2.0)
        finally:
            stop.set()
            loop.join(5.0)


@pytest.mark.parametrize(("spacing_m", "calm_expected"), [(4.0, False), (20.0, True)])
def test_a_host_s_own_vehicles_are_each_other_s_neighbours(spacing_m, calm_expected) -> None:
    """`covey fleet-sim` / `--ids`: two holding vehicles of one process 4 m apart keep it at
    10 Hz (within 5.2 m of each other); 20 m apart it is calm."""
    t = [0.0]
    cfg = FleetSimConfig(
        vehicles=2, mesh=embedded_router(free_tcp_port(), fleet=FLEET), spacing_m=spacing_m
    )
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: t[0])
        for i in range(2):
            ack = fleet.handle_command(
                i,
                Command(
                    kind=CommandKind.TAKEOFF, params=(5.0, 0.0, 0.0), nonce=new_nonce(), stamp_ns=0
                ),
            )
            assert ack.result is AckResult.ACCEPTED, ack.reason
        for _ in range(300):
            t[0] += 0.1
            fleet.tick(t[0])
            if fleet.modes == [Mode.HOLDING] * 2:
                break
        assert fleet.modes == [Mode.HOLDING] * 2
        t[0] += 0.1
        fleet.tick(t[0])
        assert fleet._calm is calm_expected
