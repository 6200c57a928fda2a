"""Manned aircraft through the runtime API and `covey eval --suites manned`: GuidancePolicy
and CPolicy take `nbr_manned` (issue 35's API, extended), the evaluation tells the
controllers which intruders are manned and counts the covey vehicles that entered the berth
(true positions)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from policy import evalsim, scenarios
from policy.eval import EvalConfig, cases, controllers
from policy.observation import EXACT, Sky

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")
DT_S = 0.1


def test_sky_takes_manned_flags_and_names_a_bad_one() -> None:
    sky = Sky.checked(nbr_manned=[False, True])
    assert sky is not EXACT and sky.nbr_manned.tolist() == [False, True]
    assert sky.kwargs()["nbr_manned"].tolist() == [False, True]
    assert "nbr_manned" not in Sky.checked(0.5).kwargs()  # the common case passes none
    assert sky.rows(np.array([1])).nbr_manned.tolist() == [True]
    assert Sky(nbr_manned=np.array(True)).fit(3).nbr_manned.tolist() == [True] * 3
    with pytest.raises(ValueError, match="nbr_manned must have shape"):
        Sky.checked(nbr_manned=[True, False], k=3)
    with pytest.raises(ValueError, match="nbr_manned must be booleans"):
        Sky.checked(nbr_manned=[0.5])
    with pytest.raises(ValueError, match="nbr_manned must have shape"):
        Sky(nbr_manned=np.array([True])).fit(2)


def _fly(command, manned: bool, duration_s: float = 80.0) -> float:
    """A vehicle holding its goal at the origin; an aircraft at 2 m/s passing 20 m east of it
    from 90 m north, told as traffic (and manned or not). Closest true distance."""
    pos, vel = np.zeros(2), np.zeros(2)
    ipos, ivel = np.array([90.0, 20.0]), np.array([-2.0, 0.0])
    closest = np.inf
    for _ in range(round(duration_s / DT_S)):
        vel = np.asarray(
            command(
                pos,
                vel,
                0.0,
                np.zeros(2),
                ipos[None],
                ivel[None],
                np.array([np.pi]),
                nbr_cooperative=np.array([False]),
                nbr_manned=np.array([manned]),
            ),
            float,
        )
        pos, ipos = pos + vel * DT_S, ipos + ivel * DT_S
        closest = min(closest, float(np.hypot(*(pos - ipos))))
    return closest


def test_the_runtime_keeps_a_manned_aircrafts_berth() -> None:
    from policy.runtime import GuidancePolicy

    pol = GuidancePolicy.load()
    assert _fly(pol.command, False) == pytest.approx(20.0, abs=0.5)  # plain traffic: 3.6 m is kept
    assert _fly(pol.command, True) >= 30.0
    with pytest.raises(ValueError, match="nbr_manned"):
        pol.command(
            np.zeros(2),
            np.zeros(2),
            0.0,
            np.ones(2),
            np.ones((1, 2)),
            np.zeros((1, 2)),
            np.zeros(1),
            nbr_manned=[True, False],
        )


@needs_cc
def test_the_c_core_keeps_the_berth_and_equals_the_runtime() -> None:
    from firmware.cpolicy import CPolicy
    from policy.runtime import GuidancePolicy

    cpol, pol = CPolicy.load(), GuidancePolicy.load()
    assert _fly(cpol.command, True) >= 30.0
    rng = np.random.default_rng(35)
    worst = 0.0
    for _ in range(60):
        k = int(rng.integers(1, 5))
        args = (
            rng.uniform(-5, 5, 2),
            rng.uniform(-0.7, 0.7, 2),
            float(rng.uniform(-np.pi, np.pi)),
            rng.uniform(-30, 30, 2),
            rng.uniform(-50, 50, (k, 2)),
            rng.uniform(-3, 3, (k, 2)),
            rng.uniform(-np.pi, np.pi, k),
        )
        args = tuple(np.asarray(a, np.float32).astype(float) for a in args)
        sky = {"nbr_cooperative": rng.random(k) < 0.5, "nbr_manned": rng.random(k) < 0.4}
        a = pol.command(*args, **sky)
        b = cpol.command(*args, **sky)
        worst = max(worst, float(np.abs(a - b).max()))
    assert worst <= 1e-4, worst


def test_the_suite_has_every_scene_at_every_speed() -> None:
    got = cases(EvalConfig(suites=("manned",)))
    names = [c[1] for c in got]
    per_speed = ["crossing", "block-10", "head-on", "overtake", "circle-8", "conflict-6"]
    assert names == [f"manned-{s:g}m_s-{n}" for s in scenarios.MANNED_SPEEDS_M_S for n in per_speed]
    for _suite, _name, starts, _goals, options in got:
        nc, speeds, manned = options["non_cooperative"], options["speed_m_s"], options["manned"]
        assert manned.tolist() == nc.tolist() and manned.sum() == 1 and manned[-1]
        assert speeds[-1] in scenarios.MANNED_SPEEDS_M_S and np.all(speeds[:-1] == 1.0)
        # heard MANNED_HEARD_S before it passes the centre: far beyond the berth at the start
        gap = np.hypot(*(starts[:-1] - starts[-1]).T).min()
        assert gap >= speeds[-1] * scenarios.MANNED_HEARD_S - 30.0


def test_the_controllers_are_told_which_neighbour_is_manned() -> None:
    seen = []

    def spy(ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, nbr_valid, **kw):
        seen.append((kw.get("nbr_cooperative"), kw.get("nbr_manned")))
        return evalsim.straight_line(ids, t_s, pos, vel, heading, goal)

    spy.uses_cooperative = True
    rng = np.random.default_rng(0)
    _, starts, goals, nc, speeds, manned = scenarios.manned_cases(rng, 20.0, quick=True)[0]
    r = evalsim.run(
        starts, goals, spy, evalsim.PERFECT, evalsim.EvalSimConfig(), rng, nc, speeds, manned
    )
    coop, told = seen[0]
    assert coop[0].tolist() == [True, False] and told[0].tolist() == [False, True]
    # flying straight, the vehicle is at the centre when the aircraft passes it
    assert r["manned_entries"] == 1 and r["manned_min_sep"] < 3.0 and r["collisions"] == 1
    with pytest.raises(ValueError, match="manned aircraft must be one of the non_cooperative"):
        evalsim.run(
            starts, goals, spy, evalsim.PERFECT, evalsim.EvalSimConfig(), rng, None, None, manned
        )


def test_a_manned_aircraft_is_already_at_its_speed_when_the_scene_starts() -> None:
    """A 60 m/s aircraft on realistic vehicles (2.5 m/s^2) would take 24 s to reach its speed
    from rest, and pass the fleet late: it starts flying."""
    from policy.pointmass import VehicleModel

    rng = np.random.default_rng(1)
    _, starts, goals, nc, speeds, manned = scenarios.manned_cases(rng, 60.0, quick=True)[0]
    cfg = evalsim.EvalSimConfig(record=True, vehicles=VehicleModel.realistic())
    r = evalsim.run(
        starts, goals, evalsim.straight_line, evalsim.PERFECT, cfg, rng, nc, speeds, manned
    )
    first = np.hypot(*(r["tracks"][1, -1] - r["tracks"][0, -1]))
    assert first == pytest.approx(60.0 * cfg.dt_s, rel=0.05)


@pytest.mark.parametrize("vehicles", ["ideal", "realistic"])
def test_marked_the_fleet_keeps_the_berth_unmarked_it_does_not(vehicles: str) -> None:
    """The quick suite (a crossing vehicle and a block of 10, at 20, 40 and 60 m/s), perfect
    link, the numpy filter: 0 vehicles within 30 m of the aircraft when it is told as manned;
    told only as traffic (its 3.6 m berth), the fleet lets it pass close."""
    from policy.pointmass import VehicleModel

    cfg = EvalConfig(suites=("manned",), quick=True, controllers=("orca",), vehicles=vehicles)
    sim_cfg = evalsim.EvalSimConfig(vehicles=VehicleModel.named(vehicles))
    ctrl = controllers(cfg)["orca"]

    def as_traffic(*args, nbr_manned=None, **kw):
        return ctrl(*args, **kw)

    vars(as_traffic).update(uses_sigma=True, uses_cooperative=True)
    entries, closest, collisions = 0, np.inf, 0
    unmarked = 0
    for i, (_s, name, starts, goals, opt) in enumerate(cases(cfg)):
        rng = np.random.default_rng([3, i])
        r = evalsim.run(starts, goals, ctrl, evalsim.PERFECT, sim_cfg, rng, **opt)
        entries += r["manned_entries"]
        collisions += r["collisions"]
        closest = min(closest, r["manned_min_sep"])
        assert r["success"], (name, r)
        u = evalsim.run(starts, goals, as_traffic, evalsim.PERFECT, sim_cfg, rng, **opt)
        unmarked += u["manned_entries"]
    assert entries == 0 and collisions == 0 and closest >= 30.0, (entries, closest)
    assert unmarked > 0


@needs_cc
def test_c_filter_keeps_the_aircraft_among_more_than_64_reports() -> None:
    """The C core takes 64 reports a call; `c+filter` keeps traffic first, so a manned aircraft
    farther than 69 covey vehicles is still avoided."""
    from firmware.ceval import c_filter
    from policy.safety import SafetyConfig

    rng = np.random.default_rng(64)
    k = 70
    ang = rng.uniform(0, 2 * np.pi, k - 1)
    covey = np.column_stack([np.cos(ang), np.sin(ang)]) * rng.uniform(40, 60, k - 1)[:, None]
    nbr_pos = np.vstack([covey, [[0.0, 200.0]]])[None]  # the aircraft 200 m east, closing
    nbr_vel = np.vstack([np.zeros((k - 1, 2)), [[0.0, -40.0]]])[None]
    coop = np.ones((1, k), bool)
    coop[0, -1] = False
    manned = ~coop

    def fly(nbrs: int) -> np.ndarray:
        ctrl = c_filter(EvalConfig(), SafetyConfig())
        return ctrl(
            np.array([0]),
            0.0,
            np.zeros((1, 2)),
            np.zeros((1, 2)),
            np.zeros(1),
            np.array([[30.0, 0.0]]),
            nbr_pos[:, :nbrs],
            nbr_vel[:, :nbrs],
            np.zeros((1, nbrs)),
            np.ones((1, nbrs), bool),
            nbr_cooperative=coop[:, :nbrs],
            nbr_manned=manned[:, :nbrs],
        )[0]

    alone = fly(k - 1)  # the covey vehicles only: straight north
    seen = fly(k)
    assert alone[1] == pytest.approx(0.0, abs=1e-6)
    assert np.abs(seen - alone).max() > 0.3, (alone, seen)  # it reacts to the aircraft
