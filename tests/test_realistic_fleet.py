"""Realistic vehicles in a fleet-sim host (in process, injected time, a real Zenoh router on
loopback): 0.3 s velocity lag, 2.5 m/s^2, gusts and GNSS estimates drifting 0.5 m. Eight
vehicles swap through the centre of their grid; the states carry each vehicle's sigma, the
filter keeps the inflated berth between estimates, and the TRUE positions never come within
the 3 m separation. Without the uncertainty in the states (sigma 0: the filter takes the
estimates as the truth) the same flight is measured for contrast."""

from __future__ import annotations

import numpy as np
import pytest

from agent.backends.sim import SimConfig
from agent.hosts import Fleet
from agent.shell_config import FleetSimConfig
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandKind, Mode
from comms.session import embedded_router, free_tcp_port
from policy.pointmass import VehicleModel

pytestmark = pytest.mark.e2e
ALT_M = 5.0


def _cmd(kind: CommandKind, *params: float) -> Command:
    return Command(kind, new_nonce(), 0, params=tuple(params) + (0.0,) * (3 - len(params)))


def _swap(seed: int, report_sigma: bool = True) -> tuple[float, float, list]:
    """Closest true and estimated approach of the swap, and the final modes."""
    clock = [0.0]
    cfg = FleetSimConfig(
        vehicles=8,
        first_id=21,
        mesh=embedded_router(free_tcp_port(), fleet="real"),
        spacing_m=7.0,
        sim=SimConfig(vehicle=VehicleModel.realistic()),
    )
    with Mesh(cfg.mesh) as mesh:
        fleet = Fleet(cfg, mesh, clock_s=lambda: clock[0], rng=np.random.default_rng(seed))
        if not report_sigma:
            fleet.sim.pos_sigma_m = 0.0
        sim = fleet.sim
        for i in range(8):
            assert fleet.handle_command(i, _cmd(CommandKind.TAKEOFF, ALT_M)).result is (
                AckResult.ACCEPTED
            )

        def fly(seconds: float) -> tuple[float, float]:
            true_min = est_min = np.inf
            for _ in range(round(seconds * 10)):
                clock[0] += 0.1
                fleet.tick(clock[0])
                up = sim.true_pos_m[:, 2] < -1.0
                if up.sum() > 1:
                    for arr, is_true in ((sim.true_pos_m, True), (sim.pos_m, False)):
                        p = arr[up, :2]
                        d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1))
                        d += np.eye(len(p)) * 1e9
                        if is_true:
                            true_min = min(true_min, float(d.min()))
                        else:
                            est_min = min(est_min, float(d.min()))
            return true_min, est_min

        fly(8.0)
        centre = sim.pos_m[:, :2].mean(axis=0)
        for i in range(8):
            goal = 2 * centre - sim.pos_m[i, :2]  # through the centre, head-on with its mirror
            ack = fleet.handle_command(i, _cmd(CommandKind.GOTO_LOCAL, *goal, -ALT_M))
            assert ack.result is AckResult.ACCEPTED, ack.reason
        true_min, est_min = fly(90.0)
        return true_min, est_min, fleet.modes


def test_realistic_fleet_keeps_separation_on_true_positions(capsys) -> None:
    true_min, est_min, modes = _swap(seed=35)
    plain_true, plain_est, _ = _swap(seed=35, report_sigma=False)
    with capsys.disabled():
        print(
            f"\n[realistic swap of 8] closest true {true_min:.2f} m (estimates {est_min:.2f} m);"
            f" without the sigma in the states: true {plain_true:.2f} m (estimates"
            f" {plain_est:.2f} m)"
        )
    assert modes == [Mode.HOLDING] * 8  # everyone arrived and holds
    assert true_min >= 3.0
    assert est_min > 3.6  # the inflated berth kept between the estimates
