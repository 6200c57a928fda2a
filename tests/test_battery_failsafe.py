"""The battery failsafe re-arms (issue 39, finding 6).

Before: it fired once per agent process. After a return and a landing at 25 %, a take-off at
22-24 % was accepted and the vehicles hovered at 18-20 % with no further failsafe. Now a vehicle
below the return threshold refuses take-off (and whatever else the failsafe would undo) with the
reason in its ack, and an airborne vehicle below it returns again, without repeating itself
while it already returns or lands.
"""

from __future__ import annotations

import re

import numpy as np

from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig, Failsafes
from agent.hosts import Agent
from agent.modes import Trigger
from agent.shell_config import AgentConfig
from comms.mesh import Mesh
from comms.schema import AckResult, Command, CommandKind, EventKind, Mode
from comms.session import MeshConfig

HERE = np.array([0.0, 0.0, -10.0])
TICK_S = 0.1
ISOLATED = MeshConfig(mode="peer", connect=(), listen=("tcp/127.0.0.1:0",))
NO_GCS = FailsafeConfig(require_gcs=False)


def test_the_return_fires_again_whenever_airborne_below_the_threshold() -> None:
    fs = Failsafes(NO_GCS, now_s=0.0)
    assert fs.evaluate(1.0, Mode.GOTO, False, 24.0, HERE).trigger is Trigger.FAILSAFE_RETURN
    # returning, then landing, then landed: nothing more (no repeated commands)
    for t, mode in ((2.0, Mode.RETURNING), (30.0, Mode.RETURNING), (40.0, Mode.LANDING)):
        assert fs.evaluate(t, mode, False, 22.0, HERE) is None
    assert fs.evaluate(50.0, Mode.LANDED, False, 22.0, HERE) is None
    # airborne again below the threshold (before: no failsafe at all, once per process)
    again = fs.evaluate(60.0, Mode.HOLDING, False, 20.0, HERE)
    assert again is not None and again.trigger is Trigger.FAILSAFE_RETURN
    # and the critical level still lands a returning vehicle, at once
    assert fs.evaluate(61.0, Mode.RETURNING, False, 9.0, HERE).trigger is Trigger.FAILSAFE_LAND
    assert fs.evaluate(62.0, Mode.LANDING, False, 8.0, HERE) is None


def test_a_return_that_did_not_stick_is_retried_after_a_pause_not_every_tick() -> None:
    fs = Failsafes(FailsafeConfig(require_gcs=False, battery_retry_s=5.0), now_s=0.0)
    assert fs.evaluate(1.0, Mode.HOLDING, False, 24.0, HERE).trigger is Trigger.FAILSAFE_RETURN
    # the mode was rolled back (its action failed): still holding
    assert [fs.evaluate(1.0 + 0.1 * k, Mode.HOLDING, False, 24.0, HERE) for k in range(1, 40)] == [
        None
    ] * 39
    assert fs.evaluate(6.0, Mode.HOLDING, False, 24.0, HERE).trigger is Trigger.FAILSAFE_RETURN


def test_commands_the_failsafe_would_undo_are_refused_with_the_reason() -> None:
    cfg = FailsafeConfig()
    why = cfg.battery_refusal(CommandKind.TAKEOFF, 22.4)
    assert why is not None and "battery 22 % below the 25 % return threshold" in why
    for kind in (CommandKind.GOTO_LOCAL, CommandKind.GOTO_GLOBAL, CommandKind.HOLD):
        assert cfg.battery_refusal(kind, 24.0)
    for kind in (CommandKind.RETURN, CommandKind.LAND, CommandKind.KILL):
        assert cfg.battery_refusal(kind, 24.0) is None
    assert "landing threshold" in cfg.battery_refusal(CommandKind.RETURN, 9.0)
    assert cfg.battery_refusal(CommandKind.LAND, 9.0) is None
    assert cfg.battery_refusal(CommandKind.TAKEOFF, 25.1) is None
    assert cfg.battery_refusal(CommandKind.TAKEOFF, float("nan")) is None  # unknown: no claim


def _cmd(kind: CommandKind, *params: float, nonce: int) -> Command:
    return Command(kind, nonce, 0, params=(*params, 0.0, 0.0, 0.0)[:3])


def test_an_agent_returns_lands_and_then_refuses_take_off_below_the_threshold() -> None:
    """A real agent around the simulator: the battery drops in flight, it returns home and
    lands once (one failsafe event), then refuses a take-off with the reason in the ack."""
    clock = [1000.0]
    events: list[tuple[str, EventKind]] = []
    with Mesh(ISOLATED) as mesh:
        backend = SimBackend(SimConfig(), now_s=clock[0])
        battery = backend.fleet.battery_pct
        cfg = AgentConfig(vehicle_id=3, mesh=ISOLATED, failsafe=NO_GCS)
        with Agent(cfg, backend, mesh, clock_s=lambda: clock[0]) as agent:
            publish = agent._event
            agent._event = lambda text, kind=EventKind.STATUS, *a, **k: (
                events.append((text, kind)),
                publish(text, kind, *a, **k),
            )

            def fly(ticks: int) -> None:
                for _ in range(ticks):
                    clock[0] += TICK_S
                    agent.tick(clock[0])
                    assert agent.actions.wait_idle(5.0)

            fly(2)
            assert agent.handle_command(_cmd(CommandKind.TAKEOFF, 5.0, nonce=1)).result is (
                AckResult.ACCEPTED
            )
            fly(60)
            ack = agent.handle_command(_cmd(CommandKind.GOTO_LOCAL, 20.0, 0.0, -5.0, nonce=2))
            assert ack.result is AckResult.ACCEPTED
            fly(30)
            battery[0] = 24.0
            fly(1)
            assert agent.mode is Mode.RETURNING
            refused = agent.handle_command(_cmd(CommandKind.GOTO_LOCAL, 20.0, 0, -5.0, nonce=3))
            assert refused.result is AckResult.REJECTED and "return threshold" in refused.reason
            top_m = 0.0
            for _ in range(600):
                fly(1)
                battery[0] = min(battery[0], 24.0)  # the simulator drains it further
                top_m = max(top_m, -backend.telemetry().pos_ned_m[2])
                if agent.mode is Mode.LANDED:
                    break
            assert agent.mode is Mode.LANDED
            failsafes = [t for t, k in events if k is EventKind.FAILSAFE]
            assert failsafes == ["battery low (24 %): returning home"], failsafes
            ack = agent.handle_command(_cmd(CommandKind.TAKEOFF, 5.0, nonce=4))
            assert ack.result is AckResult.REJECTED, "take-off below the threshold"
            # the climb to its layer drains it further: below 25 %, above the 10 % landing
            assert re.match(r"battery (1\d|2[0-4]) % below the 25 % return threshold", ack.reason)
            # a failsafe return flies the layers too: vehicle 3's is 10 + 2 x 4 = 18 m
            assert abs(top_m - 18.0) <= 0.6, top_m
            fly(5)
            assert agent.mode is Mode.LANDED and not backend.telemetry().armed
