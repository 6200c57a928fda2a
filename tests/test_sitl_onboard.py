"""Onboard mode: the emulator flies goto targets with a policy, around ADSB_VEHICLE traffic.

The pure tests run the guidance plumbing (traffic -> local neighbours -> policy -> vehicle) on
injected time, with a stand-in policy and with the C policy. The e2e test runs an emulator
process in --onboard mode behind the relay backend.
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from agent.backends.base import Traffic
from agent.backends.relay import RelayBackend, RelayConfig
from comms.adsb import covey_icao
from comms.geo import GeoOrigin
from firmware.sitl.onboard import PolicyGuidance
from firmware.sitl.process import REPO_ROOT, SitlProcess, free_udp_port
from firmware.sitl.px4 import Px4Mode
from firmware.sitl.traffic import TrafficEntry, TrafficStore
from firmware.sitl.vehicle import Vehicle, VehicleParams
from policy.observation import Observation

HOME = GeoOrigin(48.7490, 9.1050, 450.0)
PARAMS = VehicleParams(accel_m_s2=10.0, pos_gain_1_s=2.0)
WEIGHTS = REPO_ROOT / "policy" / "weights" / "policy.npz"
TRAINED_EPISODES = 50_000
"""Below this the shipped weights are a placeholder that is not expected to avoid anything."""


def trained_episodes(path: Path = WEIGHTS) -> int:
    try:
        return int(json.loads(str(np.load(path)["config"])).get("trained_episodes", 10**9))
    except (OSError, KeyError, ValueError):
        return 0


def c_policy_or_skip():
    try:
        from firmware.cpolicy import CPolicy  # noqa: F401
    except ImportError as exc:
        pytest.skip(f"firmware/cpolicy.py (the C policy wrapper) is not available yet: {exc}")
    from firmware.sitl.onboard import load_c_policy

    try:
        return load_c_policy(None, separation_m=4.0, cruise_speed_m_s=3.0)
    except (OSError, RuntimeError) as exc:  # no C compiler, no weights
        pytest.skip(f"the C policy cannot be built here: {exc}")


class Recorder:
    """A stand-in policy that records its inputs and flies straight at the goal at 2 m/s."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def command(self, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad):
        self.calls.append(
            (np.array(pos_m), np.array(nbr_pos_m), np.array(nbr_vel_m_s), np.array(nbr_heading_rad))
        )
        d = np.asarray(goal_m) - np.asarray(pos_m)
        return 2.0 * d / max(np.linalg.norm(d), 1e-9)


class Repulsion:
    """A stand-in policy with a known avoidance: goal attraction plus a lateral push from neighbours."""

    def command(self, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad):
        to_goal = np.asarray(goal_m) - pos_m
        v = to_goal / max(np.linalg.norm(to_goal), 1e-9)
        for p in np.asarray(nbr_pos_m).reshape(-1, 2):
            away = pos_m - p
            d = np.linalg.norm(away)
            if d < 8.0:
                right = np.array([-v[1], v[0]])  # evade to the right, as the paper's policy does
                v = v + (8.0 - d) / 4.0 * (away / d + right)
        return 2.0 * v / max(np.linalg.norm(v), 1.0)


def entry(
    icao: int, n_m: float, e_m: float, d_m: float, t_s: float, heading_rad=0.0, speed_m_s=0.0
) -> TrafficEntry:
    """Covey vehicle `icao` as the relay reports it (covey's marking: comms/adsb.py)."""
    lat, lon, alt = HOME.to_global(n_m, e_m, d_m)
    return TrafficEntry(
        covey_icao(icao), lat, lon, alt, heading_rad, speed_m_s, 0.0, f"CVY{icao}", t_s
    )


def airborne(guidance) -> Vehicle:
    v = Vehicle(params=PARAMS, guidance=guidance)
    assert v.arm(0.0).ok and v.takeoff(5.0, 0.0).ok
    t = 0.0
    while v.mode is not Px4Mode.HOLD:
        t += 0.05
        v.step(t)
    return v


def fly_goto(
    v: Vehicle,
    store: TrafficStore,
    goal,
    neighbour_ned,
    heading_rad: float = math.pi,
    timeout_s: float = 120.0,
) -> float:
    """Fly a goto with one standing neighbour re-reported at 3 Hz; returns the closest approach (m)."""
    assert v.reposition(np.array(goal, float), v.now_s).ok
    t_end, closest, next_report = v.now_s + timeout_s, math.inf, v.now_s
    while v.goto_active and v.now_s < t_end:
        if v.now_s >= next_report:
            store.add(entry(9, *neighbour_ned, v.now_s, heading_rad=heading_rad))
            next_report += 1.0 / 3.0
        v.step(v.now_s + 0.02)
        closest = min(
            closest, float(np.linalg.norm(v.pos_ned_m[:2] - np.asarray(neighbour_ned[:2])))
        )
    assert not v.goto_active, f"did not arrive; at {v.pos_ned_m}"
    return closest


def test_traffic_becomes_local_neighbours_dead_reckoned_to_now() -> None:
    store, policy = TrafficStore(5.0), Recorder()
    g = PolicyGuidance(policy, store, HOME, rate_hz=10.0)
    store.add(entry(7, 20.0, 5.0, -5.0, t_s=1.0, heading_rad=math.pi / 2, speed_m_s=2.0))
    store.add(entry(8, -4.0, 0.0, -5.0, t_s=1.5))
    pos, vel, hdg = g.neighbours(now_s=1.5)
    # Neighbour 7 was reported 0.5 s ago flying east at 2 m/s: 1 m further east now.
    assert pos == pytest.approx(np.array([[20.0, 6.0], [-4.0, 0.0]]), abs=0.01)
    assert vel == pytest.approx(np.array([[0.0, 2.0], [0.0, 0.0]]), abs=1e-9)
    assert hdg == pytest.approx([math.pi / 2, 0.0])
    assert g.neighbours(now_s=7.0)[0].shape == (0, 2)  # aged out


def test_policy_runs_at_its_own_rate_and_sees_the_traffic() -> None:
    store, policy = TrafficStore(5.0), Recorder()
    v = airborne(PolicyGuidance(policy, store, HOME, rate_hz=10.0))
    store.add(entry(9, 10.0, 3.0, -5.0, v.now_s))
    t0 = v.now_s
    v.reposition(np.array([30.0, 0.0, -5.0]), t0)
    while v.now_s < t0 + 2.0:
        v.step(v.now_s + 0.02)
    assert 19 <= len(policy.calls) <= 21  # 10 Hz over 2 s, while physics ran at 50 Hz
    assert policy.calls[-1][1] == pytest.approx(np.array([[10.0, 3.0]]), abs=0.01)


def test_goto_flies_around_a_neighbour_on_the_path_with_a_known_policy() -> None:
    store = TrafficStore(5.0)
    v = airborne(PolicyGuidance(Repulsion(), store, HOME, rate_hz=10.0))
    closest = fly_goto(v, store, (30.0, 0.0, -5.0), (15.0, 0.0, -5.0))
    assert closest >= 3.0
    assert np.linalg.norm(v.pos_ned_m[:2] - [30.0, 0.0]) < PARAMS.arrive_radius_m + 0.3


def test_policy_fault_makes_the_vehicle_hold() -> None:
    class Faulty:
        def command(self, *args):
            raise ValueError("C policy core fault: nonfinite")

    v = airborne(PolicyGuidance(Faulty(), TrafficStore(5.0), HOME, rate_hz=10.0))
    v.reposition(np.array([30.0, 0.0, -5.0]), v.now_s)
    v.step(v.now_s + 0.5)
    assert v.mode is Px4Mode.HOLD and not v.goto_active and "Guidance fault: holding" in v.events


def check_separation(closest_m: float, placeholder_may_fail: bool = False) -> None:
    """Never within 3 m. Only where the placeholder weights are known to fall short (a neighbour
    that faces away) is a miss with those weights an expected failure rather than a failure."""
    episodes = trained_episodes()
    if closest_m < 3.0 and placeholder_may_fail and episodes < TRAINED_EPISODES:
        pytest.xfail(
            f"the shipped weights are a placeholder ({episodes} episodes) and came within "
            f"{closest_m:.2f} m; the plumbing works (it arrived), the avoidance needs trained weights"
        )
    assert closest_m >= 3.0


@pytest.mark.parametrize(
    "heading_rad",
    [math.pi, math.pi / 2, -math.pi / 2, 0.0],
    ids=["facing-us", "facing-east", "facing-west", "facing-away"],
)
def test_goto_with_the_c_policy_avoids_a_neighbour_on_the_path(heading_rad) -> None:
    """The neighbour stands still; its reported heading is all the policy knows of its motion
    (the observation has no speed), so "facing away" looks like a vehicle flying off."""
    policy = c_policy_or_skip()
    store = TrafficStore(5.0)
    v = airborne(PolicyGuidance(policy, store, HOME, rate_hz=10.0))
    closest = fly_goto(v, store, (30.0, 0.0, -5.0), (15.0, 0.0, -5.0), heading_rad=heading_rad)
    check_separation(closest, placeholder_may_fail=heading_rad == 0.0)


@pytest.mark.e2e
def test_onboard_emulator_behind_the_relay_flies_around_traffic() -> None:
    c_policy_or_skip()
    port = free_udp_port()
    home = f"{HOME.lat_deg},{HOME.lon_deg},{HOME.alt_m}"
    args = [
        "--id",
        "2",
        "--connect",
        f"udpout:127.0.0.1:{port}",
        "--home",
        home,
        "--onboard",
        "--separation-m",
        "4",
        "--policy-speed-m-s",
        "5",
        "--takeoff-speed-m-s",
        "5",
        "--pos-gain-1-s",
        "3",
        "--accel-m-s2",
        "10",
    ]
    cfg = RelayConfig(connection=f"udpin:127.0.0.1:{port}")
    stop = threading.Event()
    with SitlProcess(args) as proc, RelayBackend(cfg, HOME) as relay:
        assert relay.wait_connected(), proc.output()
        deadline = time.monotonic() + 10.0  # the relay reads the module's CVY_SEP_M
        while (t := relay.telemetry()) is None or t.onboard_separation_m is None:
            assert time.monotonic() < deadline, f"no CVY_SEP_M: {t}"
            time.sleep(0.05)
        assert t.onboard_separation_m == pytest.approx(4.0)
        relay.takeoff(5.0)
        deadline = time.monotonic() + 15.0
        while (t := relay.telemetry()) is None or t.pos_ned_m[2] > -4.7:
            assert time.monotonic() < deadline, f"no takeoff: {t}"
            time.sleep(0.05)
        neighbour = Traffic(9, (12.0, 0.0, -5.0), (0.0, 0.0, 0.0), math.pi, 0.0)

        def report() -> None:  # the mesh side of the relay, at the paper's 3 Hz
            while not stop.wait(1.0 / 3.0):
                relay.send_traffic([neighbour])

        reporter = threading.Thread(target=report, daemon=True)
        relay.send_traffic([neighbour])
        reporter.start()
        try:
            time.sleep(0.2)
            relay.goto_local((24.0, 0.0, -5.0))
            closest, deadline = math.inf, time.monotonic() + 40.0
            while True:
                t = relay.telemetry()
                closest = min(closest, math.dist(t.pos_ned_m[:2], neighbour.pos_ned_m[:2]))
                if (
                    math.dist(t.pos_ned_m[:2], (24.0, 0.0)) < 1.2
                    and math.hypot(*t.vel_ned_m_s[:2]) < 0.3
                ):
                    break
                assert time.monotonic() < deadline, f"did not arrive: {t}\n{proc.output()[-2000:]}"
                time.sleep(0.02)
        finally:
            stop.set()
            reporter.join(2.0)
        assert proc.alive()
    check_separation(closest)


def test_c_onboard_tick_decides_at_the_trained_period_and_filters_every_tick() -> None:
    """The C tick (covey_guidance_step): 10 Hz ticks, decisions every trained period
    (separation 4 m at 3 m/s: 4/3/3 = 0.44 s), the filter on the neighbour in between."""
    policy = c_policy_or_skip()
    assert policy.decision_period_s == pytest.approx(4.0 / 3.0 / 3.0, rel=1e-6)
    store = TrafficStore(5.0)
    g = PolicyGuidance(policy, store, HOME, rate_hz=10.0)
    v = airborne(g)
    ticks0, decisions0 = g.ticks, g.decisions
    closest = fly_goto(v, store, (30.0, 0.0, -5.0), (15.0, 0.0, -5.0), heading_rad=0.0)
    ticks, decisions = g.ticks - ticks0, g.decisions - decisions0
    # one decision per period: 10 Hz ticks, 0.44 s period -> due on every 5th tick (0.5 s)
    assert ticks / decisions == pytest.approx(5.0, rel=0.15)
    assert g.filtered > 0  # the standing neighbour on the path made the filter act
    assert closest >= 3.0  # with the filter even the "facing-away" case keeps 3 m


def test_onboard_policy_is_told_the_berth_and_the_c_filter_keeps_the_separation() -> None:
    """The emulator's onboard mode tells the C network policy_separation_m (default: a share of
    the separation, as the agents fly); the C filter and the decision period keep separation_m."""
    c_policy_or_skip()
    from firmware.cpolicy import CPolicy
    from firmware.sitl.config import SitlConfig
    from firmware.sitl.emulator import Emulator
    from firmware.sitl.sitl_cli import config_from_args
    from policy.runtime import FILTERED_BERTH_SHARE

    assert config_from_args(["--onboard", "--policy-separation-m", "2"]).policy_separation_m == 2.0
    assert config_from_args(["--onboard"]).sparse_rule is True
    assert config_from_args(["--onboard", "--no-sparse-rule"]).sparse_rule is False
    link = f"udpin:127.0.0.1:{free_udp_port()}"
    with Emulator(SitlConfig(onboard=True, sparse_rule=False, links=(link,))) as emu:
        assert emu.vehicle.guidance._tick._cfg.sparse_rule == 0
    # nearly head-on (dead-on for the sparse rule, so the network flies it)
    scene = ([0.0, 0.0], [1.0, 0.0], 0.0, [30.0, 0.0], [[8.0, 0.2]], [[-1.0, 0.0]], [math.pi])
    for ps, told_m in ((None, 3.0 * FILTERED_BERTH_SHARE), (1.5, 1.5)):
        link = f"udpin:127.0.0.1:{free_udp_port()}"
        with Emulator(SitlConfig(onboard=True, policy_separation_m=ps, links=(link,))) as emu:
            guidance = emu.vehicle.guidance
            tick = guidance._tick
            assert tick._cfg.policy.separation_m == pytest.approx(told_m)
            assert tick._cfg.safety.radius_m == 3.0 and tick._cfg.safety_filter == 1
            assert tick._cfg.decision_period_s == pytest.approx(1.0)
            assert tick._cfg.sparse_rule == 1  # as the agents fly
            r = tick.step(Observation.shaped(*scene), now_s=0.0)
        assert r.status == "ok" and r.decided and not r.straight
        told = CPolicy.load(separation_m=3.0, policy_separation_m=told_m).command(*scene)
        wide = CPolicy.load(separation_m=3.0, policy_separation_m=2 * told_m).command(*scene)
        np.testing.assert_allclose(r.vel_m_s, told, atol=1e-6)
        assert np.abs(r.vel_m_s - wide).max() > 0.05  # the berth changed what was flown
