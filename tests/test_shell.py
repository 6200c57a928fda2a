"""The vehicle shell's rows: a simulated fleet read from its arrays (the fast path) equals one
`telemetry()` call per backend (the reference path), setpoints alike; the state builder clamps
and wraps what a state carries."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.autopilots import Autopilots
from agent.backends.sim import SimBackend, SimConfig, SimFleet
from agent.flight_core import CoreConfig, FlightCore, Observed
from agent.shell_config import FleetSimConfig, ShellConfig, start_grid
from agent.shell_rows import vehicle_states
from comms.schema import POS_SIGMA_LIMIT_M, StateFlag
from policy.pointmass import VehicleModel


class _Row(SimBackend):
    """A simulator row that is not a plain SimBackend: read one call at a time."""


def _fleet(seed: int) -> SimFleet:
    cfg = SimConfig(vehicle=VehicleModel.realistic())
    return SimFleet(cfg, start_grid(4, 6.0, (0.0, 0.0)), now_s=0.0, rng=np.random.default_rng(seed))


def _fields(obs: Observed) -> list[np.ndarray]:
    return [obs.pos_m, obs.vel_m_s, obs.armed, obs.in_air, obs.battery_pct, obs.link_ok]


def test_a_simulated_fleets_arrays_read_and_steer_as_its_backends_do() -> None:
    fast_sim, each_sim = _fleet(7), _fleet(7)
    fast = Autopilots([SimBackend(fleet=fast_sim, index=i) for i in range(4)])
    each = Autopilots([_Row(fleet=each_sim, index=i) for i in range(4)])
    assert fast.sim is fast_sim and each.sim is None
    for sim in (fast_sim, each_sim):
        sim.takeoff(1, 5.0)
        sim.takeoff(2, 3.0)
        sim.close(3)
    rows = np.array([1, 2])
    for k in range(1, 60):
        fast.step(k * 0.1)
        each.step(k * 0.1)
        if k >= 30:  # both airborne: fly them
            vel = np.array([[1.0, 0.5, 0.0], [-0.5, 1.0, -0.2]]) * math.sin(k / 9)
            hdg = np.array([0.3, -2.0])
            fast.set_velocities(rows, vel, hdg)
            each.set_velocities(rows, vel, hdg)
        a, b, c = fast.read(), fast.read_each(), each.read()
        assert a is not None and b is not None and c is not None
        for x, y, z in zip(_fields(a), _fields(b), _fields(c), strict=True):
            np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(x, z)
        np.testing.assert_array_equal(fast.pos_sigma_m, each.pos_sigma_m)
    assert a.in_air[1] and a.in_air[2] and not a.in_air[0] and not a.link_ok[3]
    assert fast.pos_sigma_m.max() > 0  # the realistic model reports its drift


def test_rows_of_another_fleet_or_out_of_order_are_read_one_by_one() -> None:
    sim = _fleet(1)
    assert Autopilots([SimBackend(fleet=sim, index=i) for i in (1, 0, 2, 3)]).sim is None
    assert Autopilots([SimBackend(fleet=sim, index=i) for i in range(3)]).sim is None
    assert Autopilots([SimBackend(SimConfig())]).sim is not None  # a fleet of one
    with pytest.raises(ValueError, match="at least one"):
        Autopilots([])


def test_states_carry_a_clamped_battery_and_sigma_and_a_wrapped_heading() -> None:
    n = 3
    core = FlightCore(CoreConfig(), n, now_s=0.0, vehicle_ids=(4, 5, 6))
    core.heading_rad[:] = [3.5, -7.0, math.pi]
    obs = Observed(
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        np.zeros(n, bool),
        np.zeros(n, bool),
        np.array([130.0, -4.0, 55.5]),
        np.array([True, False, True]),
    )
    sigma = np.array([0.2, 1e9, -1.0])
    rows = np.array([0, 1, 2])
    bits = np.full(n, int(StateFlag.OPEN_MODE))
    states = vehicle_states(core, obs, sigma, np.array([4, 5, 6]), np.arange(n), rows, bits, 99)
    assert [s.battery_pct for s in states] == [100.0, 0.0, 55.5]
    assert [s.pos_sigma_m for s in states] == [0.2, POS_SIGMA_LIMIT_M, 0.0]
    for s, h in zip(states, core.heading_rad, strict=True):
        assert -math.pi <= s.heading_rad < math.pi
        assert math.isclose(math.cos(s.heading_rad), math.cos(h), abs_tol=1e-12)
        assert math.isclose(math.sin(s.heading_rad), math.sin(h), abs_tol=1e-12)
        assert s.flags & StateFlag.OPEN_MODE and s.stamp_ns == 99
    assert states[1].flags & StateFlag.FAILSAFE_LINK_LOST
    assert not states[0].flags & StateFlag.FAILSAFE_LINK_LOST
    for s in states:
        s.encode()  # every one is a state the wire carries


def test_one_config_for_one_vehicle_and_many() -> None:
    one = ShellConfig(ids=(3,))
    assert (one.vehicles, one.vehicle_id, one.rate_hz) == (1, 3, 10.0)
    host = FleetSimConfig(vehicles=3, first_id=7, rate_hz=5.0)
    assert host.ids == (7, 8, 9) and (host.tick_hz, host.state_hz) == (5.0, 5.0)
    assert host.guidance.max_neighbours == 10 and not host.failsafe.require_gcs
    with pytest.raises(ValueError, match="one vehicle only"):
        ShellConfig(ids=(1, 2), link="xbee")
    with pytest.raises(ValueError, match="one per process"):
        ShellConfig(ids=(1, 2), vehicle="mavsdk:udpin://0.0.0.0:14540")
    with pytest.raises(ValueError, match="unknown vehicle"):
        ShellConfig(ids=(1,), vehicle="gazebo")


AGENT_FLAGS = [
    "--id",
    "--ids",
    "--vehicle",
    "--vehicle-model",
    "--start-ne-m",
    "--origin",
    "--separation-m",
    "--cruise-speed-m-s",
    "--no-safety-filter",
    "--decision-period-s",
    "--policy",
    "--policy-separation-m",
    "--sparse-rule",
    "--no-sparse-rule",
    "--non-cooperative-separation-m",
    "--manned-separation-m",
    "--geofence-radius-m",
    "--return-layer-m",
    "--return-layers",
    "--return-base-alt-m",
    "--land-radius-m",
    "--rally-pad-spacing-m",
    "--rally-pads",
    "--no-coordinated-return",
    "--gcs-lost-hold-s",
    "--gcs-lost-land-s",
    "--no-gcs-failsafe",
    "--idle-state-hz",
    "--steady-state-hz",
    "--hold-state-hz",
    "--one-zenoh-thread",
    "--duration-s",
    "--verbose",
    "--link",
    "--tick-hz",
    "--state-hz",
    "--plan",
    "--trace-guidance",
    "--spacing-m",
    "--max-neighbours",
    "--no-see-others",
    "--fleet",
    "--connect",
    "--mesh-mode",
    "--listen",
    "--zenoh-config",
    "--key-file",
    "--key-dir",
]
"""The flags `covey agent` had when its flags were written by hand (README and tests use them)."""


def test_the_flags_generated_from_the_configs_keep_their_names_and_defaults() -> None:
    from agent import agent_cli

    p = agent_cli.parser()
    shown = {o for a in p._actions for o in a.option_strings}
    assert set(AGENT_FLAGS) <= shown, sorted(set(AGENT_FLAGS) - shown)
    one = agent_cli.config_from_args(p.parse_args(["--id", "3"]))
    many = agent_cli.config_from_args(p.parse_args(["--ids", "3-5"]))
    fs = agent_cli.fleet_sim_parser()
    sim = agent_cli.host_config(fs, fs.parse_args([]), (1, 2), 10.0)
    for cfg in (one, many, sim):
        g = cfg.guidance
        assert (g.separation_m, g.cruise_speed_m_s, g.safety_filter, g.policy_path) == (
            3.0,
            1.0,
            True,
            None,
        )
        assert (cfg.tick_hz, cfg.state_hz, cfg.idle_state_hz, cfg.spacing_m) == (10, 10, 1, 8)
        assert cfg.see_others and cfg.link == "perfect" and not cfg.trace_guidance
    assert one.ids == (3,) and many.ids == (3, 4, 5) and sim.ids == (1, 2)
    assert one.guidance.max_neighbours is None and many.guidance.max_neighbours == 10
    for cfg in (one, many):
        f = cfg.failsafe
        assert (f.require_gcs, f.gcs_lost_hold_s, f.gcs_lost_land_s) == (True, 5.0, 30.0)
        assert f.geofence_radius_m == 500.0
    assert not sim.failsafe.require_gcs and sim.failsafe.geofence_radius_m == 2000.0
    off = agent_cli.config_from_args(p.parse_args(["--id", "3", "--no-safety-filter"]))
    assert not off.guidance.safety_filter
    nogcs = agent_cli.config_from_args(p.parse_args(["--id", "3", "--no-gcs-failsafe"]))
    assert not nogcs.failsafe.require_gcs


def test_the_hold_rate_flag_reaches_the_steady_rule_and_a_bad_one_is_refused() -> None:
    from agent import agent_cli

    p = agent_cli.parser()
    cfg = agent_cli.config_from_args(p.parse_args(["--id", "3", "--steady-state-hz", "3"]))
    assert cfg.steady is not None and cfg.steady.hold_state_hz == 0.5
    args = p.parse_args(["--id", "3", "--steady-state-hz", "3", "--hold-state-hz", "2"])
    assert agent_cli.config_from_args(args).steady.hold_state_hz == 2.0
    args = p.parse_args(["--id", "3", "--steady-state-hz", "3", "--hold-state-hz", "0.4"])
    with pytest.raises(ValueError, match="hold_state_hz must be within"):
        agent_cli.config_from_args(args)


def test_zenoh_pools_are_asked_for_and_the_users_setting_wins(monkeypatch) -> None:
    from comms.session import AGENT_RUNTIME, ONE_THREAD_RUNTIME, RUNTIME_ENV, use_zenoh_runtime

    monkeypatch.delenv(RUNTIME_ENV, raising=False)
    assert use_zenoh_runtime() == ONE_THREAD_RUNTIME
    assert "handover: app" in ONE_THREAD_RUNTIME and "worker_threads: 1" in ONE_THREAD_RUNTIME
    monkeypatch.delenv(RUNTIME_ENV)
    assert use_zenoh_runtime(AGENT_RUNTIME) == AGENT_RUNTIME == "(rx: (handover: app))"
    monkeypatch.setenv(RUNTIME_ENV, "(rx: (worker_threads: 4))")
    assert use_zenoh_runtime(AGENT_RUNTIME) == "(rx: (worker_threads: 4))"


def test_an_agent_asked_for_two_kinds_of_zenoh_pools_says_which_clash(capsys) -> None:
    from agent import agent_cli

    with pytest.raises(SystemExit) as exit_:
        agent_cli.cli(["--id", "3", "--one-zenoh-thread", "--zenoh-default-pools"])
    assert exit_.value.code == 2
    assert "--one-zenoh-thread and --zenoh-default-pools" in capsys.readouterr().err


@pytest.mark.parametrize("model", [None, VehicleModel.realistic()], ids=["ideal", "realistic"])
def test_a_fleet_of_one_reads_as_its_rows_and_its_backend_do(model) -> None:
    """An agent's one vehicle (`Autopilots._read_one`, its flags as Python bools) equals the
    rows path and `read_each`: on the ground, climbing, flying in gusts, closed."""
    cfg = SimConfig(vehicle=model)
    fast_sim = SimFleet(cfg, now_s=0.0, rng=np.random.default_rng(3))
    each_sim = SimFleet(cfg, now_s=0.0, rng=np.random.default_rng(3))
    fast, each = Autopilots([SimBackend(fleet=fast_sim)]), Autopilots([_Row(fleet=each_sim)])
    assert fast.sim is fast_sim and each.sim is None
    seen = set()
    for k in range(1, 80):
        for sim, ap in ((fast_sim, fast), (each_sim, each)):
            if k == 5:
                sim.takeoff(0, 4.0)
            if 40 <= k < 75:  # guided rows only: armed and linked (FlightCore.guided_rows)
                vel = np.array([[1.5, -0.5, 0.1]]) * math.cos(k / 7)
                ap.set_velocities(np.array([0]), vel, np.array([0.4]))
            if k == 75:
                sim.close(0)
            ap.step(k * 0.1)
        with fast_sim.lock:
            one, rows = fast._read_one(fast_sim), fast._read_rows(fast_sim)
        ref = each.read_each()
        assert ref is not None
        got = fast.read()
        assert got is not None
        for x, y, z, w in zip(_fields(one), _fields(rows), _fields(ref), _fields(got), strict=True):
            np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(x, z)
            np.testing.assert_array_equal(x, w)
        np.testing.assert_array_equal(fast.pos_sigma_m, each.pos_sigma_m)
        seen.add((bool(got.in_air[0]), bool(got.link_ok[0])))
    assert seen == {(False, True), (True, True), (True, False)}
    assert not got.in_air.flags.writeable and not fast.pos_sigma_m.flags.writeable
