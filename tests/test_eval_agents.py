"""`covey eval --controllers agents`: every vehicle flies the agents' own guidance tick
(agent/eval_agents.py), through the same suites, links and vehicle models as the others."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from agent.eval_agents import CONTROLLERS, AgentFleet, agents
from agent.guidance import GuidanceConfig
from policy import evalsim, scenarios
from policy.eval import EvalConfig, cases
from policy.pointmass import VehicleModel
from policy.safety import SafetyConfig

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no system C compiler (cc)")


def test_covey_eval_flies_the_agents_guidance(tmp_path) -> None:
    """The real command line, the quick suites on both links: no collision, every vehicle
    arrives, and the agents' rows are in the table beside policy+filter's."""
    import covey_cli

    out = tmp_path / "eval"
    argv = ["eval", "--quick", "--controllers", "agents,policy+filter", "--no-figures"]
    assert covey_cli.main([*argv, "--no-progress", "--out", str(out)]) == 0
    import json

    rows = json.loads((out / "results.json").read_text())["summary"]
    mine = [r for r in rows if r["controller"] == "agents"]
    assert {r["link"] for r in mine} == {"perfect", "degraded"}
    assert {r["suite"] for r in mine} == {"circle", "conflict", "large"}
    for r in mine:
        assert r["collisions"] == 0 and r["success"] == 1.0 and r["min_sep"] >= 3.0, r


@needs_cc
def test_the_agents_use_the_c_core_as_they_do_in_flight() -> None:
    ctrl = agents(EvalConfig(), SafetyConfig())
    _, _, starts, goals = cases(EvalConfig(suites=("circle",), quick=True))[0]
    r = evalsim.run(
        starts, goals, ctrl, evalsim.PERFECT, evalsim.EvalSimConfig(), np.random.default_rng(0)
    )
    assert r["success"] and r["collisions"] == 0
    calls = ctrl.c_core_calls
    assert calls["decide"] > 0 and calls["filter"] > 0, calls
    ctrl.reset()
    assert ctrl.c_core_calls == {}


def test_a_manned_aircraft_is_kept_at_its_berth_only_when_told() -> None:
    """The agents' views carry the manned flag to their filter: told, nobody comes within 30 m
    of the aircraft (realistic vehicles); the flag dropped (traffic only), the fleet lets it
    pass close."""
    sim = evalsim.EvalSimConfig(vehicles=VehicleModel.realistic())
    ctrl = AgentFleet(GuidanceConfig(), SafetyConfig())

    def as_traffic(*args, nbr_manned=None, **kw):
        return ctrl(*args, **kw)

    vars(as_traffic).update(uses_sigma=True, uses_cooperative=True)
    rng = np.random.default_rng(5)
    told = dropped = 0
    for name, starts, goals, nc, speeds, manned in scenarios.manned_cases(rng, 40.0, quick=True):
        opts = {"non_cooperative": nc, "speed_m_s": speeds, "manned": manned}
        ctrl.reset()
        r = evalsim.run(starts, goals, ctrl, evalsim.PERFECT, sim, np.random.default_rng(1), **opts)
        assert r["success"] and r["manned_min_sep"] >= 30.0, (name, r)
        told += r["manned_entries"]
        ctrl.reset()
        u = evalsim.run(
            starts, goals, as_traffic, evalsim.PERFECT, sim, np.random.default_rng(1), **opts
        )
        dropped += u["manned_entries"]
    assert told == 0 and dropped > 0


def test_the_agents_route_around_zones_themselves() -> None:
    """In the zones suite the agents are given the zones (as the fleet plan reaches them) and
    route and filter themselves: every row's guidance has the router; nobody enters a zone."""
    from policy import zone_eval

    ctrl = AgentFleet(GuidanceConfig(), SafetyConfig())
    scene = next(c for c in cases(EvalConfig(suites=("zones",), quick=True)) if "convex" in c[1])
    _, name, starts, goals, opts = scene
    r = zone_eval.run(
        "agents",
        starts,
        goals,
        opts["zones_m"],
        ctrl,
        evalsim.PERFECT,
        evalsim.EvalSimConfig(),
        np.random.default_rng(2),
    )
    assert ctrl._rows and all(g.router is not None for g in ctrl._rows.values())
    assert r["zone_entries"] == 0 and r["success"], (name, r)


def test_the_command_line_knows_every_controller() -> None:
    assert set(CONTROLLERS) == {"c+filter", "agents"}
