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


def _random_snapshot(rng, k: int, own_pos, own_vel):
    """k neighbours around the vehicle, 1 m to 200 m off, at rest, alongside or at random
    velocities, with the sigma, cooperative and manned columns each absent, full, short or of
    another dtype."""
    import numpy as np

    from agent.neighbours import NeighbourSnapshot

    dist = np.exp(rng.uniform(0.0, np.log(200.0), k))
    bearing = rng.uniform(0.0, 2.0 * np.pi, k)
    pos = np.c_[
        own_pos[0] + dist * np.cos(bearing),
        own_pos[1] + dist * np.sin(bearing),
        own_pos[2] + rng.uniform(-3.0, 3.0, k),
    ]
    vel = [np.zeros((k, 3)), np.tile(own_vel, (k, 1)), rng.uniform(-8.0, 8.0, (k, 3))][
        rng.integers(3)
    ]

    def column(values):
        other = values.astype(np.float32 if values.dtype == float else np.int8)
        return [None, values, values[: rng.integers(0, k + 1)], other][rng.integers(4)]

    return NeighbourSnapshot(
        pos_ned_m=pos,
        vel_ned_m_s=vel,
        heading_rad=np.zeros(k),
        ids=tuple(range(100, 100 + k)),
        age_s=np.zeros(k),
        stale_ids=(),
        pos_sigma_m=column(rng.choice([0.0, 0.5, 3.0]) * rng.uniform(0.0, 1.0, k)),
        cooperative=column(rng.uniform(size=k) < 0.7),
        manned=column(rng.uniform(size=k) < 0.2),
    )


def test_calm_s_one_vehicle_path_answers_as_the_arrays_do() -> None:
    """`calm` of one vehicle (`_calm_one`, plain floats, the rare near tie left to the arrays)
    and `holding_at_rest` against `calm_reference` and `hold_rows` on random states: modes,
    holding or flying, speeds, goals near and far, flags, geofence, a keep-out zone, neighbours
    near and far (traffic, manned, sigmas), and ties placed exactly on a calm distance."""
    import numpy as np

    from agent.calm import BUFFER_M, _calm_one, calm, calm_reference, holding_at_rest
    from agent.flight_core import CoreConfig, FlightCore, Observed
    from agent.guidance import GuidanceConfig
    from agent.neighbours import NeighbourSnapshot
    from comms.state_rate import hold_rows
    from policy.safety import pair_radius_m

    cores = [
        FlightCore(CoreConfig(failsafe=FailsafeConfig(geofence_radius_m=0.0)), 1, now_s=0.0),
        FlightCore(
            CoreConfig(
                failsafe=FailsafeConfig(geofence_radius_m=150.0),
                guidance=GuidanceConfig(cruise_speed_m_s=2.0, non_cooperative_separation_m=8.0),
            ),
            1,
            now_s=0.0,
        ),
        FlightCore(CoreConfig(), 1, now_s=0.0),
    ]
    zone = Zone(((30.0, -20.0), (30.0, 20.0), (40.0, 20.0), (40.0, -20.0)), name="pad")
    cores[2].set_plan(FleetPlan(FLEET, 1, 0, keep_out=(zone,)))
    assert cores[2].router is not None
    modes = [Mode.GOTO, Mode.HOLDING, Mode.MISSION, Mode.RETURNING, Mode.LANDING, Mode.LANDED]
    rng = np.random.default_rng(37)
    seen: dict = {True: 0, False: 0, None: 0, "calm with neighbours": 0}
    for case in range(3000):
        core = cores[case % 3]
        core.mode[0] = int(modes[rng.choice(6, p=[0.4, 0.3, 0.1, 0.1, 0.05, 0.05])])
        core.velocity_mode = bool(rng.uniform() > 0.03)
        core.mission_waiting[0] = rng.uniform() < 0.2
        core.pos_sigma_m[0] = rng.choice([0.0, 0.5, rng.uniform(0.0, 3.0)])
        pos = np.r_[rng.uniform(-160.0, 160.0, 2), -10.0]
        speed = rng.choice([0.0, 0.05, 1.0, 2.0, rng.uniform(0.0, 6.0)])
        heading = rng.uniform(0.0, 2.0 * np.pi)
        vel = np.array([speed * np.cos(heading), speed * np.sin(heading), 0.0])
        goal = pos + np.r_[rng.normal(0.0, rng.choice([2.0, 20.0, 200.0]), 2), 0.0]
        if rng.uniform() < 0.05:
            goal[0] = np.nan
        core.goal_m[0] = core.hold_m[0] = goal
        flags = [np.array([rng.uniform() > 0.03]) for _ in range(3)]
        obs = Observed(
            pos_m=pos[None, :].copy(),
            vel_m_s=vel[None, :].copy(),
            armed=flags[0],
            in_air=flags[1],
            battery_pct=np.array([80.0]),
            link_ok=flags[2],
        )
        odd = rng.uniform() < 0.02  # a NaN velocity, or a tie below: the arrays decide
        if odd:
            obs.vel_m_s[0, rng.integers(0, 2)] = np.nan
        busy, corrected = (np.array([rng.uniform() < 0.03]) for _ in range(2))
        horizon_s = float(rng.choice([0.6, 2.0, rng.uniform(0.0, 3.0)]))
        k = int(rng.choice([0, 1, 3, 12, 30]))
        ext = _random_snapshot(rng, k, pos, vel)
        if k and not odd and rng.uniform() < 0.1:  # alongside, exactly at its calm distance
            odd = True
            r = pair_radius_m(
                core.safety_cfg,
                core.pos_sigma_m[:1],
                ext.column("pos_sigma_m", 0.0)[:1],
                np.array([True]),
                np.array([False]),
            )[0][0]
            own_s = float(np.hypot(vel[0], vel[1]))
            o_s = max(own_s, core.cfg.guidance.cruise_speed_m_s)
            own_b = own_s if core.mode[0] == int(Mode.HOLDING) else o_s
            need = r + 0.0 * core.safety_cfg.time_horizon_s + (own_b + o_s) * horizon_s + BUFFER_M
            ext.pos_ned_m[0] = pos + np.r_[need, 0.0, 0.0]
            ext.vel_ned_m_s[0] = vel
            ext = NeighbourSnapshot(**{**ext.__dict__, "cooperative": None, "manned": None})
        want = calm_reference(core, obs, busy, corrected, ext, horizon_s)
        one = _calm_one(core, obs, busy, corrected, ext, horizon_s)
        assert one in (None, want) and (one is not None or odd), case
        assert calm(core, obs, busy, corrected, ext, horizon_s) is want, case
        assert holding_at_rest(core, obs) is bool(hold_rows(core.mode, obs.vel_m_s).all())
        seen[one] += 1
        seen["calm with neighbours"] += bool(one and k)
    assert min(seen.values()) > 50 and seen[True] > 300 and seen[False] > 1000, seen


def test_the_scalar_pair_radius_and_closest_approach_equal_the_arrays() -> None:
    """policy/safety.py `pair_radius_one_m` against `pair_radius_m` bit for bit (every berth,
    cooperative, traffic, manned), and agent/calm.py `closest_approach_one_m` against
    `closest_approach_m` (math.hypot for np.hypot: within an ulp or two)."""
    import dataclasses

    import numpy as np

    from agent.calm import closest_approach_m, closest_approach_one_m
    from policy.safety import SafetyConfig, pair_radius_m, pair_radius_one_m

    rng = np.random.default_rng(38)
    base = SafetyConfig()
    for cfg in (
        base,
        dataclasses.replace(base, non_cooperative_radius_m=8.0, sigma_k=0.0),
        dataclasses.replace(base, manned_radius_m=None, margin=0.15, radius_m=2.5),
    ):
        own = rng.choice([0.0, 0.5, 2.0])
        nbr = np.r_[0.0, rng.uniform(0.0, 5.0, 63)]
        coop, manned = rng.uniform(size=64) < 0.5, rng.uniform(size=64) < 0.3
        r, _share = pair_radius_m(cfg, own, nbr, coop, manned)
        for j in range(64):
            one = pair_radius_one_m(cfg, own, float(nbr[j]), bool(coop[j]), bool(manned[j]))
            assert one == r[j], (cfg, j)
    pos, vel = rng.uniform(-50, 50, (1, 3)), rng.uniform(-5, 5, (1, 3))
    o_pos, o_vel = rng.uniform(-50, 50, (200, 3)), rng.uniform(-5, 5, (200, 3))
    o_vel[:20] = vel  # no relative velocity
    want = closest_approach_m(pos, vel, o_pos, o_vel, 4.0)[0]
    for j in range(200):
        p, v = o_pos[j] - pos[0], o_vel[j] - vel[0]
        got = closest_approach_one_m(p[0], p[1], v[0], v[1], 4.0)
        assert abs(got - want[j]) <= 2 * math.ulp(want[j])


def test_a_neighbour_on_its_calm_distance_to_the_last_bit_is_left_to_the_arrays() -> None:
    """math.hypot and np.hypot may differ in the last bit: a neighbour placed where they
    disagree on which side of its calm distance it is gets the arrays' answer (`_calm_one`
    leaves it open)."""
    import numpy as np

    from agent.calm import BUFFER_M, _calm_one, calm, calm_reference
    from agent.flight_core import CoreConfig, FlightCore, Observed
    from agent.neighbours import NeighbourSnapshot
    from policy.safety import pair_radius_m

    core = FlightCore(CoreConfig(failsafe=FailsafeConfig(geofence_radius_m=0.0)), 1, now_s=0.0)
    core.mode[0] = int(Mode.GOTO)
    core.goal_m[0] = (1000.0, 0.0, -10.0)
    horizon_s, cruise_m_s, s = 0.6, core.cfg.guidance.cruise_speed_m_s, core.safety_cfg
    r = pair_radius_m(s, 0.0, np.zeros(1), np.ones(1, bool), np.zeros(1, bool))[0][0]
    need_m = r + 0.0 * s.time_horizon_s + (cruise_m_s + cruise_m_s) * horizon_s + BUFFER_M
    ys = np.random.default_rng(39).uniform(0.1, 0.9 * need_m, 20000)
    xs = np.sqrt(need_m * need_m - ys * ys)
    xs, ys = np.r_[xs, np.nextafter(xs, 0.0), np.nextafter(xs, np.inf)], np.r_[ys, ys, ys]
    near = np.hypot(xs, ys) <= need_m
    split = [
        (x, y)
        for x, y, n in zip(xs.tolist(), ys.tolist(), near.tolist(), strict=True)
        if (math.hypot(x, y) <= need_m) != n
    ]
    if not split:
        pytest.skip("math.hypot and np.hypot agree here")
    for x, y in split[:20]:
        obs = Observed(
            pos_m=np.array([[0.0, 0.0, -10.0]]),
            vel_m_s=np.zeros((1, 3)),
            armed=np.ones(1, bool),
            in_air=np.ones(1, bool),
            battery_pct=np.array([80.0]),
            link_ok=np.ones(1, bool),
        )
        ext = NeighbourSnapshot(
            np.array([[x, y, -10.0]]), np.zeros((1, 3)), np.zeros(1), (7,), np.zeros(1), ()
        )
        args = (core, obs, np.zeros(1, bool), np.zeros(1, bool), ext, horizon_s)
        assert _calm_one(*args) is None
        assert calm(*args) is calm_reference(*args)


@pytest.mark.parametrize("beyond_m", [0.5, -0.5])
def test_a_host_s_rows_keep_each_their_own_position_sigma(beyond_m: float) -> None:
    """Two vehicles of one process, sigma 0 and 3 m, 500 m apart; a neighbour alongside the
    first, `beyond_m` beyond its calm distance at sigma 0: calm exactly when it is beyond. The
    second vehicle's larger sigma is not the first one's (it would add 12 m)."""
    import numpy as np

    from agent.calm import BUFFER_M, calm_reference
    from agent.flight_core import CoreConfig, FlightCore, Observed
    from agent.neighbours import NeighbourSnapshot

    core = FlightCore(CoreConfig(failsafe=FailsafeConfig(geofence_radius_m=0.0)), 2, now_s=0.0)
    core.mode[:] = int(Mode.GOTO)
    core.pos_sigma_m[:] = (0.0, 3.0)
    pos = np.array([[0.0, 0.0, -10.0], [0.0, 500.0, -10.0]])
    vel = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    core.goal_m[:] = pos + np.array([400.0, 0.0, 0.0])
    horizon_s = 0.6
    cruise = core.cfg.guidance.cruise_speed_m_s
    s = core.safety_cfg
    need = s.radius_m * (1.0 + s.margin) + 2 * max(1.0, cruise) * horizon_s + BUFFER_M
    ext = NeighbourSnapshot(
        pos_ned_m=np.array([[0.0, need + beyond_m, -10.0]]),
        vel_ned_m_s=vel[:1].copy(),
        heading_rad=np.zeros(1),
        ids=(100,),
        age_s=np.zeros(1),
        stale_ids=(),
        pos_sigma_m=np.zeros(1),
    )
    obs = Observed(pos, vel, np.ones(2, bool), np.ones(2, bool), np.full(2, 80.0), np.ones(2, bool))
    quiet = np.zeros(2, bool)
    assert calm_reference(core, obs, quiet, quiet, ext, horizon_s) is (beyond_m > 0)
