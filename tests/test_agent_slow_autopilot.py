"""An autopilot whose actions take seconds: commands are acked at once, the state stream keeps
its rate, and the station shows the outcome against the command when the action ends."""

from __future__ import annotations

import threading
import time

import pytest
from conftest import wait_until

from agent.backends.base import BackendError
from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig
from agent.hosts import Agent
from agent.shell_config import AgentConfig
from comms.commands import new_nonce
from comms.mesh import Mesh
from comms.schema import AckResult, Command, Mode, VehicleState
from comms.session import MeshConfig, embedded_router, free_tcp_port
from groundstation.station import GcsConfig, GroundStation

ACTION_S = 5.0
VID = 1


class SlowSim(SimBackend):
    """A simulated vehicle whose take-off call blocks for ACTION_S (a MAVSDK take-off is up to
    three autopilot calls of up to 6 s), then succeeds, or fails with `fail`."""

    def __init__(self, fail: str | None = None) -> None:
        super().__init__(SimConfig(), now_s=time.monotonic())
        self.fail = fail

    def takeoff(self, alt_m: float) -> None:
        time.sleep(ACTION_S)
        if self.fail:
            raise BackendError(self.fail)
        super().takeoff(alt_m)


class States:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.stamps: list[tuple[float, VehicleState]] = []

    def on_state(self, state: VehicleState, _recv_ns: int) -> None:
        if state.vehicle_id == VID:
            with self.lock:
                self.stamps.append((time.monotonic(), state))

    def between(self, t0: float, t1: float) -> list[VehicleState]:
        with self.lock:
            return [s for t, s in self.stamps if t0 <= t <= t1]

    def last_mode(self) -> Mode | None:
        with self.lock:
            return self.stamps[-1][1].mode if self.stamps else None


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.parametrize("fail", [None, "arming denied: preflight checks failed"])
def test_slow_actions_do_not_block_acks_or_states(fail: str | None) -> None:
    port = free_tcp_port()
    peer = MeshConfig(mode="peer", connect=(f"tcp/127.0.0.1:{port}",))
    stop = threading.Event()
    with Mesh(embedded_router(port)) as hub, Mesh(peer) as agent_mesh:
        states = States()
        hub.subscribe_states(states.on_state)
        cfg = AgentConfig(vehicle_id=VID, mesh=peer, failsafe=FailsafeConfig(require_gcs=False))
        with (
            Agent(cfg, SlowSim(fail), agent_mesh) as agent,
            GroundStation(GcsConfig(mesh=peer, port=0)) as gcs,
        ):
            runner = threading.Thread(target=agent.run, args=(stop,), daemon=True)
            runner.start()
            try:
                assert wait_until(lambda: states.last_mode() is Mode.LANDED, 30), "no state"
                cmd = Command.takeoff(4.0, nonce=new_nonce(), stamp_ns=0, targets=(VID,))
                t0 = time.monotonic()
                res = hub.send_command(cmd, expect=(VID,), timeout_s=10)
                ack_s = time.monotonic() - t0
                outcome = res.outcomes[VID]
                print(f"ack after {ack_s * 1e3:.0f} ms for a {ACTION_S:.0f} s take-off call")
                # Acked on acceptance: far sooner than the autopilot call (the old agent took 5 s).
                assert outcome.ack is not None and outcome.ack.result is AckResult.ACCEPTED
                assert outcome.ack.mode is Mode.TAKING_OFF
                assert ack_s < ACTION_S / 2, ack_s
                # While the call blocks, the vehicle keeps publishing at its 10 Hz.
                time.sleep(ACTION_S - 1.0)
                during = states.between(t0 + 0.5, t0 + ACTION_S - 1.0)
                rate_hz = len(during) / (ACTION_S - 1.5)
                print(f"{rate_hz:.1f} states/s while the take-off call blocked")
                assert rate_hz >= 8.0, rate_hz

                def shown():
                    entry = next(
                        (e for e in gcs.commands.entries() if e.command.nonce == cmd.nonce), None
                    )
                    return None if entry is None else entry.done.get(VID)

                assert wait_until(lambda: shown() is not None, 30), (
                    "the station never saw the outcome"
                )
                done = shown()
                if fail is None:
                    assert done.ok and "takeoff" in done.detail
                    assert wait_until(lambda: states.last_mode() is Mode.HOLDING, 30)
                else:
                    assert not done.ok and fail in done.detail and "back to landed" in done.detail
                    assert wait_until(lambda: states.last_mode() is Mode.LANDED, 10)
                # The command log the operator reads marks the vehicle's chip done (it reached
                # its altitude) / failed (the autopilot's reason).
                want = f'data-vehicle="{VID}" data-answer="{"done" if fail is None else "failed"}"'
                assert wait_until(lambda: want in gcs.command_log_html.content, 10), (
                    gcs.command_log_html.content
                )
            finally:
                stop.set()
                runner.join(timeout=10)
