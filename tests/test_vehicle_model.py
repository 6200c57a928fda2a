"""The one point-mass model's realistic vehicles (policy.pointmass.VehicleModel / Vehicles):
velocity lag, acceleration limit, gusts and a drifting position estimate, each measured on a
seeded fleet, and the vectorised fleet equal to a plain per-vehicle reference loop."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from policy.pointmass import VehicleModel, Vehicles, integrate


def test_presets_and_bad_values():
    r = VehicleModel.realistic()
    assert (r.lag_s, r.max_accel_m_s2, r.gust_m_s, r.gust_corr_s, r.drift_m, r.drift_corr_s) == (
        0.3,
        2.5,
        0.2,
        5.0,
        0.5,
        10.0,
    )
    assert VehicleModel.named("ideal") == VehicleModel.ideal() == VehicleModel()
    with pytest.raises(ValueError, match="vehicle model must be one of ideal, realistic"):
        VehicleModel.named("real")
    for bad in ({"lag_s": -1.0}, {"drift_m": math.nan}, {"gust_corr_s": 0.0}):
        with pytest.raises(ValueError):
            VehicleModel(**bad)


def test_presets_with_fields_changed_and_their_refusals():
    import argparse

    from policy.pointmass import vehicle_model_arg

    m = VehicleModel.named("realistic:drift_m=1.0, gust_m_s=0.4")
    assert m == replace(VehicleModel.realistic(), drift_m=1.0, gust_m_s=0.4)
    assert VehicleModel.named("ideal:lag_s=0.5") == VehicleModel(lag_s=0.5)
    assert VehicleModel.named("realistic:") == VehicleModel.realistic()
    for bad, why in (
        ("realistic:drift=1", "not field=value"),
        ("realistic:drift_m", "not field=value"),
        ("realistic:drift_m=x", "drift_m must be a number"),
        ("realistic:drift_m=-1", "drift_m must be finite and >= 0"),
        ("realistic:drift_corr_s=0", "drift_corr_s must be > 0"),
        ("wobbly:drift_m=1", "must be one of ideal, realistic"),
    ):
        with pytest.raises(ValueError, match=why):
            VehicleModel.named(bad)
        with pytest.raises(argparse.ArgumentTypeError, match=why):
            vehicle_model_arg(bad)
    assert vehicle_model_arg("realistic:drift_m=1.0") == "realistic:drift_m=1.0"


def test_ideal_vehicles_fly_the_command_exactly_and_draw_nothing():
    rng = np.random.default_rng(3)
    fleet = Vehicles(np.zeros((4, 2)), VehicleModel.ideal(), rng)
    want = np.array([[1.0, 0.0], [0.0, -1.0], [0.5, 0.5], [0.0, 0.0]])
    fleet.step(want, 0.1)
    assert np.array_equal(fleet.vel_m_s, want)
    assert np.allclose(fleet.pos_m, want * 0.1)
    assert np.array_equal(fleet.est_pos_m, fleet.pos_m)
    # the caller's random stream is untouched (the link's losses stay as they were)
    assert rng.random() == np.random.default_rng(3).random()


def test_velocity_lag_reaches_63_percent_after_tau_and_respects_the_acceleration_limit():
    m = VehicleModel(lag_s=0.3)
    fleet = Vehicles(np.zeros((1, 2)), m, np.random.default_rng(0))
    dt = 0.01
    for _ in range(30):  # 0.3 s
        fleet.step(np.array([[1.0, 0.0]]), dt)
    assert fleet.vel_m_s[0, 0] == pytest.approx(1.0 - math.exp(-1.0), abs=1e-9)
    limited = Vehicles(np.zeros((1, 2)), VehicleModel(lag_s=0.3, max_accel_m_s2=2.5), None)
    prev = 0.0
    for _ in range(100):
        limited.step(np.array([[10.0, 0.0]]), 0.1)
        assert limited.vel_m_s[0, 0] - prev <= 2.5 * 0.1 + 1e-12
        prev = limited.vel_m_s[0, 0]


def test_gusts_and_drift_have_the_stated_sigma_and_correlation_time():
    m = VehicleModel.realistic()
    n, dt = 2000, 0.1
    fleet = Vehicles(np.zeros((n, 2)), m, np.random.default_rng(7))
    g0, d0 = fleet.gust_m_s.copy(), fleet.drift_m.copy()
    for k in range(1, 101):  # 10 s of hovering
        fleet.step(np.zeros((n, 2)), dt)
        if k == 50:
            g5 = fleet.gust_m_s.copy()
    d10 = fleet.drift_m
    assert np.std(g5) == pytest.approx(0.2, rel=0.05)
    assert np.std(d10) == pytest.approx(0.5, rel=0.05)
    # corr(x(t), x(t + T)) = exp(-1) at the correlation time T
    assert np.corrcoef(g0.ravel(), g5.ravel())[0, 1] == pytest.approx(math.exp(-1), abs=0.04)
    assert np.corrcoef(d0.ravel(), d10.ravel())[0, 1] == pytest.approx(math.exp(-1), abs=0.04)
    # hovering vehicles are blown about: the truth moves, by about the gust's integral
    assert 0.3 < np.std(fleet.pos_m) < 2.0
    assert np.allclose(fleet.est_pos_m - fleet.pos_m, fleet.drift_m)
    assert fleet.pos_sigma_m == 0.5


def _reference(starts, wants, model: VehicleModel, seed: int, dt: float):
    """The same flight one vehicle and one axis at a time in plain floats, drawing the noise
    with the same calls as the fleet."""
    rng = np.random.default_rng(seed)
    n = len(starts)
    gust = rng.standard_normal((n, 2)) * model.gust_m_s
    drift = rng.standard_normal((n, 2)) * model.drift_m
    pos = [list(map(float, p)) for p in starts]
    vel = [[0.0, 0.0] for _ in range(n)]
    ag, ad = math.exp(-dt / model.gust_corr_s), math.exp(-dt / model.drift_corr_s)
    out = []
    for want in wants:
        for i in range(n):
            dv = [(want[i][a] - vel[i][a]) * (1.0 - math.exp(-dt / model.lag_s)) for a in (0, 1)]
            norm = math.hypot(*dv)
            lim = model.max_accel_m_s2 * dt
            s = lim / norm if norm > lim else 1.0
            for a in (0, 1):
                vel[i][a] += dv[a] * s
                pos[i][a] += vel[i][a] * dt + gust[i][a] * dt
        wg = rng.standard_normal((n, 2))
        wd = rng.standard_normal((n, 2))
        for i in range(n):
            for a in (0, 1):
                gust[i][a] = ag * gust[i][a] + model.gust_m_s * math.sqrt(1 - ag * ag) * wg[i][a]
                drift[i][a] = ad * drift[i][a] + model.drift_m * math.sqrt(1 - ad * ad) * wd[i][a]
        out.append([[pos[i][a] + drift[i][a] for a in (0, 1)] for i in range(n)])
    return np.array(out), np.array(pos)


def test_vectorised_fleet_equals_the_reference_loop():
    m = VehicleModel.realistic()
    rng = np.random.default_rng(5)
    starts = rng.uniform(-10, 10, (5, 2))
    wants = rng.uniform(-1.5, 1.5, (40, 5, 2))
    est_ref, pos_ref = _reference(starts, wants, m, 11, 0.1)
    fleet = Vehicles(starts, m, np.random.default_rng(11))
    est = []
    for w in wants:
        fleet.step(w, 0.1)
        est.append(fleet.est_pos_m)
    assert np.allclose(np.array(est), est_ref, atol=1e-9)
    assert np.allclose(fleet.pos_m, pos_ref, atol=1e-9)


def test_integrate_without_the_new_options_is_unchanged():
    pos, vel = np.zeros((2, 3)), np.zeros((2, 3))
    pos[:, 2] = -5.0
    integrate(pos, vel, np.array([[1.0, 0, 0], [0, 1.0, 0]]), 0.1, 4.0)
    assert np.allclose(vel, [[0.4, 0, 0], [0, 0.4, 0]])
    # a gust moves airborne 3-D rows only
    ground = np.zeros((1, 3))
    integrate(ground, np.zeros((1, 3)), np.zeros((1, 3)), 1.0, wind_m_s=np.array([[1.0, 0.0]]))
    assert np.array_equal(ground, np.zeros((1, 3)))


def test_the_simulator_reports_its_estimate_and_sigma_and_holds_on_it():
    from agent.backends.sim import SimConfig, SimFleet

    fleet = SimFleet(
        SimConfig(vehicle=VehicleModel.realistic()),
        np.zeros((3, 3)),
        rng=np.random.default_rng(4),
    )
    for i in range(3):
        fleet.takeoff(i, 5.0)
    for k in range(1, 301):  # 30 s: take off, then hold where each believes it is
        fleet.step(0.1 * k)
    tel = fleet.telemetry(0)
    assert tel.pos_sigma_m == 0.5 and tel.pos_ned_m[:2] == tuple(fleet.pos_m[0, :2])
    off = fleet.pos_m[:, :2] - fleet.true_pos_m[:, :2]
    assert np.allclose(off, fleet.body.drift_m) and np.abs(off).max() > 0.05
    assert np.allclose(fleet.pos_m[:, 2], fleet.true_pos_m[:, 2])  # the drift is horizontal
    ideal = SimFleet(SimConfig(), np.zeros((1, 3)))
    assert ideal.pos_m is ideal.true_pos_m and ideal.telemetry(0).pos_sigma_m == 0.0


def test_the_emulator_reports_its_estimate_and_sigma():
    from comms.geo import GeoOrigin
    from firmware.sitl import streams
    from firmware.sitl.vehicle import Vehicle

    v = Vehicle(model=VehicleModel.realistic(), rng=np.random.default_rng(6))
    assert v.arm(0.0).result == 0 and v.takeoff(5.0, 0.0).result == 0
    v.step(20.0)
    assert v.pos_sigma_m == 0.5
    assert np.allclose(v.est_pos_ned_m[:2] - v.pos_ned_m[:2], v.drift_m)
    assert np.abs(v.drift_m).max() > 0.01
    msg = streams.local_position_ned(v, 0)
    assert (msg.x, msg.y) == pytest.approx(tuple(v.est_pos_ned_m[:2]), abs=1e-4)
    assert streams.gps_raw_int(v, GeoOrigin(), 0).h_acc == 500
    plain = Vehicle()
    assert plain.pos_sigma_m == 0.0 and streams.gps_raw_int(plain, GeoOrigin(), 0).h_acc == 0


def test_vehicle_model_flags(capsys):
    from agent import agent_cli
    from agent.agent_cli import fleet_sim_parser
    from groundstation.demo import parser as demo_parser

    assert fleet_sim_parser().parse_args(["--vehicle-model", "realistic"]).vehicle_model == (
        "realistic"
    )
    assert demo_parser().parse_args([]).vehicle_model == "ideal"
    assert agent_cli.sim_config("realistic").vehicle == VehicleModel.realistic()
    assert agent_cli.sim_config("ideal").vehicle is None
    assert agent_cli.sim_config("realistic:drift_m=1").vehicle.drift_m == 1.0
    for argv, why in (
        (["--vehicle-model", "real"], "must be one of ideal, realistic"),
        (["--vehicle-model", "realistic:drift_m=x"], "drift_m must be a number"),
        (
            ["--id", "1", "--vehicle", "mavsdk:udpin://0.0.0.0:1", "--vehicle-model", "realistic"],
            "--vehicle-model is how a simulated vehicle flies; a mavsdk vehicle flies itself",
        ),
    ):
        with pytest.raises(SystemExit) as exc:
            agent_cli.cli(argv)
        assert exc.value.code == 2 and why in capsys.readouterr().err


def test_a_reported_sigma_apart_from_the_drift_reaches_every_simulator_and_the_zone_rule():
    """`reported_sigma_m`: the 1-sigma a vehicle reports where it is not its drift's (a
    conservative eph). Every simulator reports it, and the zone eval's goal rule pads for it
    as the flight core does; the flight itself stays exact."""
    from agent.backends.sim import SimConfig, SimFleet
    from firmware.sitl.vehicle import Vehicle

    assert VehicleModel.realistic().pos_sigma_m == 0.5  # unset: the drift's
    m = VehicleModel.named("ideal:reported_sigma_m=0.5")
    assert (m.drift_m, m.reported_sigma_m, m.pos_sigma_m) == (0.0, 0.5, 0.5)
    assert VehicleModel.named("realistic:reported_sigma_m=0").pos_sigma_m == 0.0
    for bad in ("ideal:reported_sigma_m=-0.1", "ideal:reported_sigma_m=inf"):
        with pytest.raises(ValueError, match="reported_sigma_m must be finite and >= 0"):
            VehicleModel.named(bad)
    fleet = Vehicles(np.zeros((3, 2)), m, np.random.default_rng(1))
    assert fleet.pos_sigma_m == 0.5 and np.array_equal(fleet.est_pos_m, fleet.pos_m)
    sim = SimFleet(SimConfig(vehicle=m), np.zeros((1, 3)))
    assert sim.pos_m is sim.true_pos_m and sim.telemetry(0).pos_sigma_m == 0.5
    assert Vehicle(model=m).pos_sigma_m == 0.5


def test_the_zone_eval_refuses_goals_at_the_reported_sigma():
    """zones-edge-goals: goals 2 m off a square are refused at a 0.5 m sigma (the filter keeps
    3.8 m) and flown at sigma 0, whether the sigma comes from the drift or is only reported
    (it padded for the drift alone: ideal vehicles reporting 0.5 m never arrived)."""
    from policy import eval as policy_eval
    from policy import scenarios, zone_eval
    from policy.evalsim import PERFECT, EvalSimConfig

    scenes = {s[0]: s[1:] for s in scenarios.zone_scenes(np.random.default_rng(0))}
    starts, goals, zones = scenes["edge-goals"]
    name = "policy+filter"
    guided = policy_eval.controllers(policy_eval.EvalConfig(controllers=(name,)))[name]

    def fly(vehicles: str) -> dict:
        sim = EvalSimConfig(vehicles=VehicleModel.named(vehicles))
        rng = np.random.default_rng(1)
        r = zone_eval.run(name, starts, goals, zones, guided, PERFECT, sim, rng)
        assert r["zone_entries"] == 0 and r["success"], r
        return r

    assert fly("ideal")["refused"] == 0
    assert fly("ideal:reported_sigma_m=0.5")["refused"] == 2
    assert fly("realistic")["refused"] == 2
