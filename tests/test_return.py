"""The coordinated return (agent/returning.py) in the flight core: layers from ids, the climb
to the layer, the level leg, the landing order; then a fleet of 12 simulated vehicles (the
fleet-sim code, a real Zenoh mesh, injected time) told `covey cmd return --to all` through
the real CLI: no pair below the separation, each on its layer, all landed at home."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from agent.failsafe import FailsafeConfig
from agent.guidance import GuidanceConfig
from agent.hosts import Fleet
from agent.returning import CLIMB, CRUISE, ReturnConfig, Returns
from agent.shell_config import FleetSimConfig
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandKind, Mode
from comms.session import embedded_router, free_tcp_port
from groundstation.ops import cmd_cli

SEPARATION_M = 3.0


def test_layers_and_pads_come_from_the_id() -> None:
    cfg = ReturnConfig(return_layer_m=4.0, return_layers=3, return_base_alt_m=8.0)
    assert [cfg.layer_alt_m(v) for v in (1, 2, 3, 4)] == [8.0, 12.0, 16.0, 8.0]
    pads = {cfg.pad_ne_m(v) for v in range(1, 26)}
    assert len(pads) == 25 and (0.0, 0.0) in pads  # 5 x 5 around the point
    for bad in ({"return_layer_m": -1.0}, {"return_base_alt_m": 0.0}, {"return_layers": 0}):
        with pytest.raises(ValueError):
            ReturnConfig(**bad)


def test_enter_climbs_first_then_flies_level() -> None:
    r = Returns(ReturnConfig(return_layer_m=5.0, return_layers=4, return_base_alt_m=10.0), [1, 2])
    home = np.array([0.0, 0.0, 0.0])
    goal = r.enter(1, np.array([20.0, 5.0, -30.0]), home, [], 1.0, 0.5)
    assert r.phase[1] == CLIMB and goal.tolist() == [20.0, 5.0, -15.0]  # down to layer 1 first
    goals = np.array([[0.0, 0.0, 0.0], goal])
    arrived, turned = r.arrivals(
        np.array([False, True]), np.array([False, True]), np.array([[0, 0, 0], goal]), goals
    )
    assert turned == [1] and not arrived[1] and r.phase[1] == CRUISE
    assert goals[1].tolist() == [0.0, 0.0, -15.0]
    # already on the layer: straight to the spot; a rally point nearer than home is taken
    goal = r.enter(0, np.array([50.0, 0.0, -10.2]), home, [(60.0, 0.0)], 1.0, 0.5)
    assert r.phase[0] == CRUISE and goal[2] == -10.0
    assert np.hypot(*(goal[:2] - (60.0, 0.0))) <= 15.0  # its pad around the rally point
    off = Returns(ReturnConfig(return_layer_m=0.0, land_radius_m=0.0), [1])
    assert off.enter(0, np.array([5.0, 5.0, -7.0]), home, [], 1.0, 0.5).tolist() == [0, 0, -7.0]
    # a layer above the ceiling is flown just under it (less the arrival tolerance)
    high = Returns(ReturnConfig(), [8])  # default layer of vehicle 8: 10 + 7 x 4 = 38 m
    assert high.enter(0, np.array([5.0, 5.0, -7.0]), home, [], 1.0, 0.5, 30.0)[2] == -29.5


def test_the_coordinated_return_is_on_by_default_and_can_be_turned_off() -> None:
    """The real parsers of covey agent, covey agent --ids (the host), covey fleet-sim and
    covey demo: layers 4 m apart from 10 m and a landing order within 8 m unless
    --no-coordinated-return; that flag with a layer flag is refused, not half-used."""
    from agent import agent_cli
    from agent import agent_cli as host_cli
    from groundstation import demo

    assert ReturnConfig().coordinated
    assert (ReturnConfig().return_layer_m, ReturnConfig().land_radius_m) == (4.0, 8.0)
    base = ["--id", "3"]
    args = agent_cli.parser().parse_args(base)
    on = agent_cli.failsafe_from_args(args).returning
    assert (on.return_layer_m, on.return_base_alt_m, on.land_radius_m) == (4.0, 10.0, 8.0)
    assert on.layer_alt_m(3) == 18.0
    args = agent_cli.parser().parse_args([*base, "--no-coordinated-return"])
    off = agent_cli.failsafe_from_args(args).returning
    assert not off.coordinated
    args = agent_cli.parser().parse_args([*base, "--no-coordinated-return", "--land-radius-m", "5"])
    with pytest.raises(ValueError, match="no-coordinated-return"):
        agent_cli.failsafe_from_args(args)
    p = host_cli.fleet_sim_parser()
    for argv, want in (([], True), (["--no-coordinated-return"], False)):
        cfg = host_cli.host_config(p, p.parse_args(argv), (1, 2), 10.0)
        assert cfg.failsafe.returning.coordinated is want, argv
    assert demo.parser().parse_args([]).coordinated_return is True
    assert demo.parser().parse_args(["--no-coordinated-return"]).coordinated_return is False


def test_lowest_lands_first_within_the_radius() -> None:
    r = Returns(ReturnConfig(return_layer_m=4.0, return_layers=4, land_radius_m=5.0), [1, 2, 3])
    for i in range(3):
        r.spot_ne_m[i] = (0.0, 4.0 * i)
    pos = np.array([[0.0, 0.0, -10.0], [0.0, 4.0, -14.0], [0.0, 8.0, -18.0]])
    assert r.blocker(0, pos, None, None) is None
    assert r.blocker(1, pos, None, None) == 1
    assert r.blocker(2, pos, None, None) == 2  # 3 waits for 2 (4 m away), not for 1 (8 m)
    pos[0, 2] = 0.0  # landed: no longer in the way
    assert r.blocker(1, pos, None, None) is None
    # a neighbour of another process, level and of a lower id, goes first
    assert r.blocker(0, pos, np.array([[0.0, 1.0, 0.2 - pos[0, 2] * 0 - 0.2]]), [9]) is None
    assert r.blocker(1, pos, np.array([[0.0, 5.0, -14.2]]), np.array([1])) == 1


def _cmd(kind: CommandKind, *params: float) -> Command:
    return Command(kind, new_nonce(), 0, params=tuple(params) + (0.0,) * (3 - len(params)))


def _random_targets(rng, n: int) -> np.ndarray:
    pts: list[np.ndarray] = []
    while len(pts) < n:
        p = np.array([rng.uniform(-30, 40), rng.uniform(-30, 40), -rng.uniform(4, 25)])
        if all(np.hypot(*(p[:2] - q[:2])) >= 8.0 for q in pts):
            pts.append(p)
    return np.array(pts)


class Ticker:
    """Ticks a fleet on injected time in a thread (ten sim seconds in about one wall second on
    an idle machine) and records what the test judges, on true positions, after every tick."""

    def __init__(self, fleet: Fleet, clock: list[float]) -> None:
        self.fleet, self.clock = fleet, clock
        self.stop = threading.Event()
        self.min_pair_m = math.inf
        self.off_layer_m = 0.0
        self.cruised = np.zeros(fleet.cfg.vehicles, bool)
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        f = self.fleet
        while not self.stop.is_set():
            self.clock[0] += 0.1
            f.tick(self.clock[0])
            pos = f.pos_m
            up = (-pos[:, 2] > 0.3) & f.armed
            if up.sum() > 1:
                p = pos[up]
                d = np.linalg.norm(p[:, None] - p[None], axis=2) + np.eye(len(p)) * 1e9
                self.min_pair_m = min(self.min_pair_m, float(d.min()))
            r = f.core.returns
            cruise = (r.phase == CRUISE) & (f.core.mode == int(Mode.RETURNING))
            if cruise.any():
                self.cruised |= cruise
                dev = np.abs(-pos[cruise, 2] - r.layer_alt_m[cruise])
                self.off_layer_m = max(self.off_layer_m, float(dev.max()))
            self.stop.wait(0.002)


@pytest.mark.e2e
def test_return_of_12_from_random_positions_on_layers() -> None:
    clock = [0.0]
    port = free_tcp_port()
    fleet_name = "returning"
    returning = ReturnConfig(
        return_layer_m=4.0, return_layers=12, return_base_alt_m=8.0, land_radius_m=4.0
    )
    cfg = FleetSimConfig(
        ids=tuple(range(1, 13)),
        mesh=embedded_router(port, fleet=fleet_name),
        spacing_m=6.0,
        guidance=GuidanceConfig(cruise_speed_m_s=3.0),
        failsafe=FailsafeConfig(require_gcs=False, geofence_radius_m=2000.0, returning=returning),
    )
    rng = np.random.default_rng(36)
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0])
        for i in range(12):
            assert (
                fleet.handle_command(i, _cmd(CommandKind.TAKEOFF, 5.0)).result is AckResult.ACCEPTED
            )
        for _ in range(80):
            clock[0] += 0.1
            fleet.tick(clock[0])
        for i, t in enumerate(_random_targets(rng, 12)):
            ack = fleet.handle_command(i, _cmd(CommandKind.GOTO_LOCAL, *t))
            assert ack.result is AckResult.ACCEPTED, ack.reason
        for _ in range(600):
            clock[0] += 0.1
            fleet.tick(clock[0])
            if fleet.modes == [Mode.HOLDING] * 12:
                break
        assert fleet.modes == [Mode.HOLDING] * 12, fleet.modes
        homes = fleet.home_m.copy()
        ticker = Ticker(fleet, clock)
        ticker.thread.start()
        try:
            rc = cmd_cli(
                ["return", "--to", "all", "--fleet", fleet_name]
                + ["--connect", f"tcp/127.0.0.1:{port}"]
            )
            assert rc == 0
            end = clock[0] + 300.0
            while clock[0] < end and fleet.modes != [Mode.LANDED] * 12:
                ticker.stop.wait(0.05)
        finally:
            ticker.stop.set()
            ticker.thread.join(5)
        print(
            f"return of 12: closest pair {ticker.min_pair_m:.2f} m, furthest off its layer "
            f"{ticker.off_layer_m:.2f} m, {clock[0]:.0f} s of sim time"
        )
        assert fleet.modes == [Mode.LANDED] * 12, fleet.modes
        assert ticker.cruised.all()  # every one flew a level leg on its layer
        assert ticker.off_layer_m <= 1.0
        assert ticker.min_pair_m >= SEPARATION_M, ticker.min_pair_m
        assert np.allclose(fleet.pos_m[:, :2], homes[:, :2], atol=1.0)


def test_close_homes_land_one_at_a_time() -> None:
    """Four vehicles whose homes are 4 to 5.7 m apart, land radius 8 m (the filter may push a
    waiting vehicle a metre off its spot): never two coming down at once (airborne in LANDING);
    lowest layer first."""
    clock = [0.0]
    port = free_tcp_port()
    returning = ReturnConfig(
        return_layer_m=4.0, return_layers=4, return_base_alt_m=6.0, land_radius_m=8.0
    )
    cfg = FleetSimConfig(
        ids=(4, 3, 2, 1),
        mesh=embedded_router(port, fleet="landorder"),
        spacing_m=4.0,
        guidance=GuidanceConfig(cruise_speed_m_s=3.0),
        failsafe=FailsafeConfig(require_gcs=False, returning=returning),
    )
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0])
        for i in range(4):
            assert (
                fleet.handle_command(i, _cmd(CommandKind.TAKEOFF, 5.0)).result is AckResult.ACCEPTED
            )
        for _ in range(80):
            clock[0] += 0.1
            fleet.tick(clock[0])
        for i in range(4):
            assert fleet.handle_command(i, _cmd(CommandKind.RETURN)).result is AckResult.ACCEPTED
        order: list[int] = []
        most_landing = 0
        for _ in range(3000):
            clock[0] += 0.1
            fleet.tick(clock[0])
            coming_down = [
                int(fleet.ids[i])
                for i, m in enumerate(fleet.modes)
                if m is Mode.LANDING and -fleet.pos_m[i, 2] > 0.3
            ]
            most_landing = max(most_landing, len(coming_down))
            order += [v for v in coming_down if v not in order]
            if fleet.modes == [Mode.LANDED] * 4:
                break
        assert fleet.modes == [Mode.LANDED] * 4
        assert most_landing == 1 and order == [1, 2, 3, 4], (most_landing, order)


@pytest.mark.e2e
def test_two_agents_return_on_their_layers_and_land_in_order(procs) -> None:
    """Two real `covey agent` processes (one vehicle each, homes 5 m apart): a return to all puts
    vehicle 1 on the 6 m layer and vehicle 2 on the 10 m one, and 2 comes down only once 1 is
    down, each knowing the other from its neighbour table alone (before the landing order read
    every height, 2 came down with 1 still 3.4 m up: the guidance's table keeps a 5 m band)."""
    from conftest import wait_until

    from comms.schema import VehicleState

    port = free_tcp_port()
    fleet_name = "returnagents"
    seen: dict[int, list[tuple[float, Mode]]] = {1: [], 2: []}
    when_2_came_down: list[float] = []  # vehicle 1's altitude when 2 began to land
    lock = threading.Lock()

    def on_state(s: VehicleState, _t: int) -> None:
        with lock:
            seen[s.vehicle_id].append((-s.pos_ned_m[2], s.mode))
            if s.vehicle_id == 2 and s.mode is Mode.LANDING and not when_2_came_down:
                when_2_came_down.append(seen[1][-1][0] if seen[1] else math.nan)

    def latest() -> dict[int, tuple[float, Mode]]:
        with lock:
            return {v: xs[-1] for v, xs in seen.items() if xs}

    # layers 4 m apart and the 8 m landing order are the defaults (on without a flag)
    flags = ["--return-layers", "2", "--return-base-alt-m", "6"]
    flags += ["--no-gcs-failsafe", "--cruise-speed-m-s", "2"]
    mesh = ["--fleet", fleet_name, "--connect", f"tcp/127.0.0.1:{port}"]
    with Mesh(embedded_router(port, fleet=fleet_name)) as station:
        station.subscribe_states(on_state)
        for vid, start in ((1, "0,0"), (2, "0,5")):
            procs.start(
                "-m", "covey_cli", "agent", "--id", str(vid), f"--start-ne-m={start}", *flags, *mesh
            )
        assert wait_until(lambda: len(latest()) == 2, 60), latest()
        assert cmd_cli(["takeoff", "4", "--to", "all", *mesh]) == 0
        assert wait_until(lambda: all(m is Mode.HOLDING for _, m in latest().values()), 30)
        with lock:
            for xs in seen.values():
                xs.clear()
        assert cmd_cli(["return", "--to", "all", *mesh]) == 0
        assert wait_until(
            lambda: all(m is Mode.LANDED for _, m in latest().values()) and len(latest()) == 2, 90
        ), latest()
    with lock:
        tops = {v: max(a for a, _ in xs) for v, xs in seen.items()}
    print(f"two agents: tops {tops}, vehicle 1 at {when_2_came_down} m when 2 came down")
    assert abs(tops[1] - 6.0) <= 0.8 and abs(tops[2] - 10.0) <= 0.8, tops
    # vehicle 2 waits until 1 is below 0.3 m; the station's last state of 1 is up to a tick
    # older (1 m/s down): within a metre of the ground
    assert when_2_came_down and when_2_came_down[0] <= 1.0, when_2_came_down
