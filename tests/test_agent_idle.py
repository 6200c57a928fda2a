"""An idle vehicle (landed, disarmed, nothing under way) is cheap, on a real Zenoh mesh: it
publishes at the idle rate and hears no neighbours; the tick after a take-off command it publishes
at full rate again and subscribes again, and it hears a flying neighbour long before it has
climbed into that neighbour's vertical band. The station never calls an idle vehicle stale."""

from __future__ import annotations

import math
import threading
import time

import pytest
from conftest import views_by_id, wait_until

from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig
from agent.hosts import Agent
from agent.shell_config import AgentConfig
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import AckResult, Command, Mode, VehicleState
from comms.session import embedded_router, free_tcp_port
from comms.state_rate import MAX_HOLD_PERIOD_S, MAX_IDLE_PERIOD_S
from groundstation.fleet import FleetConfig, FleetModel

FLEET = "idle"
NO_GCS = FailsafeConfig(require_gcs=False)


class Seqs:
    """Every state's (vehicle id, seq, mode), as a subscriber on the mesh receives them."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.rows: list[tuple[int, int, Mode]] = []

    def on_state(self, s: VehicleState, _t: int) -> None:
        with self.lock:
            self.rows.append((s.vehicle_id, s.seq, s.mode))

    def of(self, vid: int) -> list[tuple[int, Mode]]:
        with self.lock:
            return [(seq, mode) for v, seq, mode in self.rows if v == vid]


def test_idle_rate_then_full_rate_from_the_tick_after_a_takeoff(mesh_trio) -> None:
    hub, a, _b = mesh_trio
    heard, station = Seqs(), FleetModel()
    hub.subscribe_states(heard.on_state)
    # the route from `a` to the hub's subscription must exist before the first counted state
    probe = VehicleState(99, 1, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0)
    for _ in range(100):
        a.publish_state(probe)
        if wait_until(lambda: heard.of(99), 0.1):
            break
    hub.subscribe_states(station.on_state, vehicle_id=1)
    sent0 = a.stats.states_sent
    t = [0.0]
    cfg = AgentConfig(vehicle_id=1, failsafe=NO_GCS)
    with Agent(cfg, SimBackend(SimConfig(), now_s=0.0), a, clock_s=lambda: t[0]) as agent:
        for _ in range(30):  # 3 s landed: states at 0.1, 1.1 and 2.1 s
            t[0] += 0.1
            agent.tick(t[0])
        assert a.stats.states_sent - sent0 == 3
        ack = agent.handle_command(Command.takeoff(10.0, nonce=new_nonce(), stamp_ns=0))
        assert ack.result is AckResult.ACCEPTED
        sent = []
        for _ in range(10):
            t[0] += 0.1
            agent.tick(t[0])
            sent.append(a.stats.states_sent - sent0)
        assert sent == list(range(4, 14)), "not a state on every tick after the takeoff"
        assert wait_until(lambda: len(heard.of(1)) == 13, 10), heard.of(1)
        got = heard.of(1)
        assert [seq for seq, _ in got] == list(range(1, 14))  # one seq per state: no gaps
        assert [m for _, m in got[:3]] == [Mode.LANDED] * 3 and got[3][1] is Mode.TAKING_OFF
        view = views_by_id(station.snapshot(time.time_ns()))[1]
        assert view.loss_pct == 0.0 and not view.stale


def test_an_idle_agent_hears_nobody_and_after_a_takeoff_hears_its_neighbour_in_time(
    mesh_trio,
) -> None:
    """Real time, the agent's own 10 Hz loop; a neighbour hovers 4 m away at the take-off
    altitude. Landed and idle, the agent receives none of its states; the take-off command's next
    tick subscribes, and the neighbour is heard within 1 + handover_s (docs/scaling.md) worth of
    ticks, while the vehicle is still below the neighbour's vertical band."""
    hub, a, b = mesh_trio
    alt_m, nbr_id = 10.0, 2
    stop_nbr = threading.Event()

    def neighbour() -> None:  # hovers at (4, 0) at the take-off altitude, 10 Hz
        seq = 0
        while not stop_nbr.wait(0.1):
            seq += 1
            b.publish_state(
                VehicleState(
                    nbr_id,
                    seq,
                    time.time_ns(),
                    (4.0, 0.0, -alt_m),
                    (0.0, 0.0, 0.0),
                    0.0,
                    mode=Mode.HOLDING,
                    armed=True,
                )
            )

    station = Seqs()
    hub.subscribe_states(station.on_state)
    cfg = AgentConfig(vehicle_id=1, failsafe=NO_GCS)
    agent = Agent(cfg, SimBackend(SimConfig(), now_s=time.monotonic()), a)
    ticks: list[tuple[float, bool]] = []  # per tick: altitude, neighbour heard
    inner = agent.tick

    def tick(now_s: float) -> None:
        inner(now_s)
        ticks.append((-agent.backend.telemetry().pos_ned_m[2], nbr_id in agent.table.latest()))

    agent.tick = tick
    stop = threading.Event()
    threads = [threading.Thread(target=agent.run, args=(stop,)), threading.Thread(target=neighbour)]
    for th in threads:
        th.start()
    try:
        # idle: the neighbour's states flow (the station hears them), the agent hears none
        assert wait_until(lambda: len(station.of(nbr_id)) >= 20 and len(ticks) >= 20, 20)
        assert a.stats.states_received == 0 and agent.states.cells == frozenset()
        assert not agent.table.latest()
        ack = agent.handle_command(Command.takeoff(alt_m, nonce=new_nonce(), stamp_ns=0))
        assert ack.result is AckResult.ACCEPTED
        at_command = len(ticks)
        assert wait_until(lambda: any(h for _, h in ticks[at_command:]), 10), "never heard"
        k = next(i for i, (_, h) in enumerate(ticks[at_command:]) if h)
        alt_heard_m = ticks[at_command + k][0]
        scope = agent.scope.cfg
        bound = 1 + math.ceil(scope.handover_s * cfg.tick_hz)
        print(f"heard the neighbour {k + 1} ticks after the takeoff, at {alt_heard_m:.2f} m")
        assert k + 1 <= bound, f"heard only {k + 1} ticks after the takeoff (bound {bound})"
        assert alt_heard_m < alt_m - agent.table.cfg.vertical_band_m
        assert agent.states.cells  # subscribed again
    finally:
        stop.set()
        stop_nbr.set()
        for th in threads:
            th.join(5)
        agent.close()


def test_the_station_waits_longer_for_an_idle_vehicle_and_a_holder_at_rest_only() -> None:
    cfg = FleetConfig()
    assert cfg.idle_stale_after_s >= 3 * MAX_IDLE_PERIOD_S
    assert cfg.hold_stale_after_s >= 3 * MAX_HOLD_PERIOD_S
    model = FleetModel(cfg)
    ns = 1_000_000_000
    landed = VehicleState(1, 1, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, mode=Mode.LANDED)
    armed = VehicleState(2, 1, 1, (5.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, armed=True)
    flying = VehicleState(
        3, 1, 1, (9.0, 0.0, -5.0), (0.5, 0.0, 0.0), 0.0, mode=Mode.HOLDING, armed=True
    )  # holding but not at rest (pushed): the steady rate at most
    holder = VehicleState(
        4, 1, 1, (14.0, 0.0, -5.0), (0.0, 0.05, 0.0), 0.0, mode=Mode.HOLDING, armed=True
    )  # at rest: every MAX_HOLD_PERIOD_S (comms/state_rate.py)
    for s in (landed, armed, flying, holder):
        model.on_state(s, 0)
    quiet_s = (cfg.stale_after_s + cfg.idle_stale_after_s) / 2  # between the two thresholds
    views = views_by_id(model.snapshot(int(quiet_s * ns)))
    assert not views[1].stale, "an idle vehicle was stale between two of its idle states"
    assert views[2].stale and views[3].stale  # armed on the ground, flying: the short threshold
    assert not views[4].stale, "a holder at rest was stale between two of its states"
    views = views_by_id(model.snapshot(int((cfg.idle_stale_after_s + 0.1) * ns)))
    assert views[1].stale
    assert cfg.hold_stale_after_s > cfg.idle_stale_after_s  # a holder speaks every 2 s
    assert not views[4].stale
    views = views_by_id(model.snapshot(int((cfg.hold_stale_after_s + 0.1) * ns)))
    assert views[4].stale
    # 1 Hz idle states with consecutive seqs are no loss, and the rate says 1 Hz
    model = FleetModel(cfg)
    for k in range(4):
        model.on_state(VehicleState(1, k + 1, k, landed.pos_ned_m, (0.0,) * 3, 0.0), k * ns)
    view = views_by_id(model.snapshot(3 * ns + ns // 2))[1]
    assert view.loss_pct == 0.0 and view.rate_hz == pytest.approx(1.0) and not view.stale


@pytest.mark.e2e
@pytest.mark.slow
def test_a_landed_covey_agent_is_never_stale_at_the_station(procs) -> None:
    """A real `covey agent` process, landed and idle: the station hears about one state a
    second, with no loss, and never marks it stale."""
    port = free_tcp_port()
    station = FleetModel()
    with Mesh(embedded_router(port, fleet=FLEET)) as hub:
        hub.subscribe_states(station.on_state)
        heard = Seqs()
        hub.subscribe_states(heard.on_state)
        procs.start(
            "-m",
            "covey_cli",
            "agent",
            "--id",
            "4",
            "--fleet",
            FLEET,
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--no-gcs-failsafe",
        )
        assert wait_until(lambda: len(heard.of(4)) >= 2, 60), "no states from the agent"
        first = len(heard.of(4))
        stale = []
        t_end = time.monotonic() + 4.0
        while time.monotonic() < t_end:
            view = views_by_id(station.snapshot(time.time_ns()))[4]
            stale.append(view.stale)
            time.sleep(0.1)
        got = heard.of(4)
        print(f"{len(got) - first} states in 4 s; loss {view.loss_pct:.0f} %")
        assert not any(stale), "the station called a landed, idle vehicle stale"
        assert 2 <= len(got) - first <= 7  # about 1 Hz, not 10
        assert view.loss_pct == 0.0 and view.mode is Mode.LANDED


def test_an_idle_agent_rests_between_ticks_and_a_command_wakes_it(mesh_trio) -> None:
    """The agent's own loop (`run`, real clock, real Zenoh): landed, it ticks at its idle rate
    (2 Hz, not 10); a takeoff sent by the station is answered from a tick run at once, and the
    ticks are back at full rate while it climbs."""
    hub, a, _b = mesh_trio
    cfg = AgentConfig(vehicle_id=1, failsafe=NO_GCS)
    assert cfg.resting_tick_hz == 2.0
    stop = threading.Event()
    with Agent(cfg, SimBackend(SimConfig(), now_s=time.monotonic()), a) as agent:
        loop = threading.Thread(target=agent.run, args=(stop,), daemon=True)
        loop.start()
        try:
            time.sleep(0.5)
            t0, ticks0 = time.monotonic(), agent.stats.ticks
            time.sleep(3.0)
            idle_ticks = agent.stats.ticks - ticks0
            idle_s = time.monotonic() - t0
            # resting: at most 2 Hz (+1 for the window's edges); a loaded machine ticks fewer
            assert 1 <= idle_ticks <= 2.0 * idle_s + 1, (idle_ticks, idle_s)
            for _ in range(50):  # the route from the station to the agent's queryable
                res = hub.send_command(
                    Command.takeoff(10.0, nonce=new_nonce(), stamp_ns=time.time_ns()),
                    expect=(1,),
                    timeout_s=2.0,
                )
                if res.ok:
                    break
            assert res.ok, res.summary()
            assert wait_until(lambda: agent.mode is not Mode.LANDED, 5.0)
            t1, ticks1 = time.monotonic(), agent.stats.ticks
            time.sleep(2.0)
            busy_ticks = agent.stats.ticks - ticks1
            busy_s = time.monotonic() - t1
            # flying: more than the idle rate allows (10 Hz, less on a loaded machine)
            assert busy_ticks > 2.0 * busy_s + 1, (busy_ticks, busy_s)
        finally:
            stop.set()
            loop.join(5.0)
        assert not loop.is_alive(), "the loop did not stop when asked"
