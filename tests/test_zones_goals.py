"""A goal next to a keep-out zone: the filter keeps 1.8 m + sigma_k x the position 1-sigma from
every zone, so a goal nearer than that is flown to the nearest point outside it when that point
is within the arrival radius, and refused at once, naming the zone and the distances, when it is
not (policy.routes `Router.check_goal`, agent/flight_core.py `_clear_goal`). And the sigma of an
autopilot that reports no accuracy (`--assumed-pos-sigma-m`, agent/autopilots.py)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from agent.autopilots import Autopilots
from agent.backends.base import Telemetry
from agent.failsafe import FailsafeConfig
from agent.flight_core import CoreConfig, FlightCore, Observed
from agent.modes import Mode
from comms.plan import FleetPlan, Zone
from comms.schema import AckResult, Command, CommandKind
from policy.routes import Router
from policy.safety import SIGMA_K

SQUARE = ((-8.0, -8.0), (-8.0, 8.0), (8.0, 8.0), (8.0, -8.0))
REACH_M = 1.8
"""The filter's zone radius at the default 3 m separation (policy.routes RouteConfig.reach_m)."""


def _dist(pt) -> float:
    return float(shapely.Polygon(SQUARE).distance(shapely.Point(*pt)))


@pytest.mark.parametrize(
    ("off_m", "sigma_m", "moved"),
    [(2.0, 0.0, False), (2.6, 0.5, True), (2.0, 0.5, True), (5.0, 0.5, False)],
)
def test_a_goal_inside_the_clearance_moves_to_its_edge(off_m, sigma_m, moved) -> None:
    router = Router([np.array(SQUARE)])
    goal = np.array([8.0 + off_m, 1.0])
    c = router.check_goal(goal, SIGMA_K * sigma_m)
    clearance = REACH_M + SIGMA_K * sigma_m
    assert c.clearance_m == pytest.approx(clearance)
    assert c.distance_m == pytest.approx(off_m) and c.zone == 0
    if not moved:
        assert np.array_equal(c.goal_m, goal) and c.shift_m == 0.0 and c.problem(0.0) == ""
        return
    assert clearance <= _dist(c.goal_m) <= clearance + 0.1  # just outside the clearance
    assert c.shift_m == pytest.approx(clearance - off_m, abs=0.1)
    assert (c.problem(1.0) == "") == (c.shift_m <= 1.0)


def test_the_core_flies_a_near_goal_to_the_clearance_or_refuses_it_naming_the_zone() -> None:
    core = FlightCore(CoreConfig(failsafe=FailsafeConfig(require_gcs=False)), 1, now_s=0.0)
    core.set_plan(FleetPlan("f", 1, 0, keep_out=(Zone(SQUARE, "pad"),)))
    here = np.array([30.0, 0.0, -10.0])
    sigma = 0.5
    obs = Observed(
        here[None], np.zeros((1, 3)), np.ones(1, bool), np.ones(1, bool), np.full(1, 90.0),
        np.ones(1, bool), np.full(1, sigma),
    )  # fmt: skip
    core.observe(0.0, obs, gcs_alive=True)
    core.mode[0] = int(Mode.HOLDING)  # flying
    clearance = REACH_M + SIGMA_K * sigma

    def goto(n_m: float):
        return core.command(0, Command(CommandKind.GOTO_LOCAL, 1, 0, (n_m, 0.0, -10.0)), here)

    near = goto(8.0 + clearance - 0.7)  # the edge of the clearance within the 1 m arrival radius
    assert near.result is AckResult.ACCEPTED, near.reason
    assert near.reason.startswith("goal moved 0.") and "'pad'" in near.reason
    assert clearance <= _dist(core.goal_m[0, :2]) <= clearance + 0.1
    far = goto(8.0 + clearance - 1.3)
    assert far.result is AckResult.REJECTED
    assert "keep-out zone 'pad'" in far.reason and f"{clearance:.1f} m" in far.reason
    assert "1 m arrival radius" in far.reason
    clear = goto(8.0 + clearance + 1.0)
    assert clear.result is AckResult.ACCEPTED and clear.reason == ""
    assert core.goal_m[0, 0] == 8.0 + clearance + 1.0


class _Autopilot:
    """An autopilot backend that reports `h_acc_m` (0: no accuracy), as the MAVSDK and relay
    backends do through pos_sigma_of."""

    capabilities = frozenset()

    def __init__(self, h_acc_m: float) -> None:
        self.h_acc_m = h_acc_m

    def telemetry(self) -> Telemetry:
        return Telemetry(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, True, True, 80.0,
                         pos_sigma_m=self.h_acc_m)  # fmt: skip


def test_an_autopilot_without_accuracy_is_assumed_standard_gnss_from_the_flag() -> None:
    from agent import agent_cli

    p = agent_cli.parser()
    default = agent_cli.config_from_args(p.parse_args(["--id", "3"]), p)
    none = agent_cli.config_from_args(p.parse_args(["--id", "3", "--assumed-pos-sigma-m", "0"]), p)
    assert default.assumed_pos_sigma_m == 0.5 and none.assumed_pos_sigma_m == 0.0
    for cfg in (default, none):
        rows = Autopilots([_Autopilot(0.0), _Autopilot(1.2)], cfg.assumed_pos_sigma_m)  # type: ignore[list-item]
        obs = rows.read()
        assert obs is not None and obs.pos_sigma_m is not None
        np.testing.assert_array_equal(obs.pos_sigma_m, [cfg.assumed_pos_sigma_m, 1.2])
    with pytest.raises(ValueError, match="assumed_pos_sigma_m must be finite and >= 0"):
        agent_cli.config_from_args(p.parse_args(["--id", "3", "--assumed-pos-sigma-m", "-1"]), p)
