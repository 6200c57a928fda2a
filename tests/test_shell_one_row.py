"""The shell's one-row bookkeeping (an agent's every tick, on Python bools) equals its rows
path: which vehicles are busy and idle after this tick's actions (`VehicleShell._submit`
against `_submit_rows`, `idle_one` against `idle_rows`), and the link events."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from agent.backends.sim import SimBackend, SimConfig
from agent.failsafe import FailsafeConfig
from agent.flight_core import Action, ActionKind, Observed
from agent.hosts import Agent
from agent.shell_config import AgentConfig
from comms.mesh import Mesh
from comms.schema import EventKind, Mode
from comms.session import embedded_router, free_tcp_port
from comms.state_rate import idle_one, idle_rows


@pytest.mark.parametrize("mode", list(Mode))
def test_idle_one_equals_idle_rows(mode: Mode) -> None:
    for armed, in_air, busy in itertools.product((False, True), repeat=3):
        want = idle_rows(np.array([int(mode)]), np.array([armed]), np.array([in_air]), busy)
        assert idle_one(int(mode), armed, in_air, busy) is bool(want[0])


class _Queue:
    """An action queue that records what it is given and says whether it is busy."""

    def __init__(self, busy: bool) -> None:
        self.busy, self.got = busy, []

    def submit(self, action: Action) -> None:
        self.got.append(action)


@pytest.fixture(scope="module")
def agent():
    cfg = AgentConfig(vehicle_id=4, failsafe=FailsafeConfig(require_gcs=False))
    with (
        Mesh(embedded_router(free_tcp_port(), fleet="shellrow")) as mesh,
        Agent(cfg, SimBackend(SimConfig(), now_s=0.0), mesh, clock_s=lambda: 0.0) as ag,
    ):
        yield ag


def _obs(armed: bool, in_air: bool) -> Observed:
    z = np.zeros((1, 3))
    return Observed(z, z, np.array([armed]), np.array([in_air]), np.array([90.0]), np.ones(1, bool))


@pytest.mark.parametrize("seed", range(4))
def test_submit_of_one_row_equals_the_rows_path(agent: Agent, seed: int) -> None:
    rng = np.random.default_rng(seed)
    saved = agent._queues, agent._threaded, int(agent.core.mode[0])
    seen = set()
    try:
        for _ in range(200):
            agent.core.mode[0] = int(rng.choice(list(Mode)))
            agent._threaded = bool(rng.random() < 0.5)
            queue_busy = bool(rng.random() < 0.3)
            actions = [Action(0, ActionKind.HOLD)] * int(rng.integers(0, 3))
            obs = _obs(bool(rng.random() < 0.3), bool(rng.random() < 0.3))
            one_q, rows_q = _Queue(queue_busy), _Queue(queue_busy)
            agent._queues = [one_q]
            busy, idle = agent._submit(actions, obs)
            agent._queues = [rows_q]
            busy_ref, idle_ref = agent._submit_rows(actions, obs)
            np.testing.assert_array_equal(busy, busy_ref)
            np.testing.assert_array_equal(idle, idle_ref)
            assert busy.dtype == busy_ref.dtype and idle.shape == idle_ref.shape == (1,)
            assert one_q.got == rows_q.got == actions
            seen.add((bool(busy[0]), bool(idle[0])))
    finally:
        agent._queues, agent._threaded = saved[0], saved[1]
        agent.core.mode[0] = saved[2]
    assert seen == {(False, False), (False, True), (True, False)}


def test_a_lost_and_restored_link_is_said_once_each(agent: Agent) -> None:
    said: list[str] = []
    event, agent._event = agent._event, lambda text, kind, *a, **k: said.append((text, kind))
    try:
        for ok in (True, True, False, False, False, True, True):
            agent._link_events(np.array([ok]))
    finally:
        agent._event = event
    assert said == [
        ("autopilot link LOST", EventKind.FAILSAFE),
        ("autopilot link restored", EventKind.FAILSAFE),
    ]
