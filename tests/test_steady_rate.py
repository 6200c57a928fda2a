"""The steady-state rule (comms/state_rate.py SteadyConfig): a vehicle whose last state still
predicts it publishes at the steady rate, anything its receivers could not extrapolate goes out on
the next tick, and what a receiver extrapolates is never further than tol_m from the truth.
A vehicle holding at rest publishes at the hold rate (1 Hz) and any motion at once. Then a real
agent on a real Zenoh mesh: hovering at 1 Hz, a goto sent at once and its acceleration faster
than the steady rate, no gap in the seqs and no loss at the station."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from conftest import views_by_id, wait_until
from test_agent_idle import NO_GCS, Seqs

from agent.backends.sim import SimBackend, SimConfig
from agent.hosts import Agent
from agent.shell_config import AgentConfig
from comms.commands import new_nonce
from comms.schema import AckResult, Command, Mode
from comms.state_rate import (
    MAX_HOLD_PERIOD_S,
    MIN_STEADY_STATE_HZ,
    StatePacer,
    SteadyConfig,
    announces_hold,
)
from groundstation.fleet import FleetModel

FLEET = "steady"
TICK_S = 0.1


def _fly(pacer: StatePacer, pos, vel, hdg=None, sig=None, t0_s: float = 0.0) -> np.ndarray:
    """Ticks (T,) of one row along the track pos (T, 3), vel (T, 3): which ticks published."""
    n = len(pos)
    hdg = np.zeros(n) if hdg is None else hdg
    sig = np.zeros(n, np.int64) if sig is None else sig
    return np.array(
        [
            pacer.due(t0_s + k * TICK_S, [False], pos[k], vel[k], [hdg[k]], [sig[k]], [False])[0]
            for k in range(n)
        ]
    )


def _straight(n: int, v=(1.0, 0.5, 0.0)):
    vel = np.tile(np.asarray(v, float), (n, 1))
    return vel * TICK_S * np.arange(n)[:, None], vel


def test_hovering_and_straight_flight_publish_at_the_steady_rate() -> None:
    for v in ((0.0, 0.0, 0.0), (1.0, 0.5, -0.2)):
        pos, vel = _straight(60, v)
        sent = _fly(StatePacer(10.0, 1.0, 10.0, steady=SteadyConfig()), pos, vel)
        assert sent[0], "the first state goes out at once"
        gaps = np.diff(np.flatnonzero(sent))
        assert set(gaps.tolist()) == {3}, f"not 3 Hz at {v}: gaps {gaps}"
    # without the rule: every tick
    pos, vel = _straight(20)
    assert _fly(StatePacer(10.0, 1.0, 10.0), pos, vel).all()


def test_a_change_receivers_cannot_extrapolate_goes_out_on_the_next_tick() -> None:
    pos, vel = _straight(40)
    for what in ("velocity", "heading", "mode"):
        p, v = pos.copy(), vel.copy()
        hdg, sig = np.zeros(40), np.zeros(40, np.int64)
        if what == "velocity":  # a 0.2 m/s step at tick 20 (the position follows from it)
            v[20:] += (0.0, 0.2, 0.0)
            p[21:] += np.cumsum(np.tile((0.0, 0.2 * TICK_S, 0.0), (19, 1)), axis=0)
        elif what == "heading":
            hdg[20:] = 0.1
        else:
            sig[20:] = 7
        sent = _fly(StatePacer(10.0, 1.0, 10.0, steady=SteadyConfig()), p, v, hdg, sig)
        assert sent[20], f"a {what} change waited"
        # steady again after it
        assert set(np.diff(np.flatnonzero(sent[21:])).tolist()) <= {3}, what


def test_what_receivers_extrapolate_stays_within_tol_m_on_random_tracks() -> None:
    cfg = SteadyConfig(tol_m=0.1)
    rng = np.random.default_rng(5)
    worst, published, ticks = 0.0, 0, 0
    for _ in range(20):
        pacer = StatePacer(10.0, 1.0, 10.0, steady=cfg)
        p, v = np.zeros(3), np.zeros(3)
        last = None
        for k in range(300):
            # a velocity that mostly holds and sometimes drifts or jumps (hover, cruise, turns)
            r = rng.random()
            if r < 0.05:
                v = rng.normal(0, 1.0, 3)
            elif r < 0.5:
                v = v + rng.normal(0, 0.02, 3)
            p = p + v * TICK_S
            t = k * TICK_S
            if pacer.due(t, [False], p, v, [0.0], [0], [False])[0]:
                last = (t, p.copy(), v.copy())
                published += 1
            pred = last[1] + last[2] * (t - last[0])
            worst = max(worst, float(np.linalg.norm(p - pred)))
            ticks += 1
            assert t - last[0] <= 1 / MIN_STEADY_STATE_HZ + 1e-9
    assert worst <= cfg.tol_m + 1e-12, worst
    assert published < 0.8 * ticks, "the rule never saved a state"


HOLD = int(Mode.HOLDING)  # `_fly`'s sig is the mode


def test_a_holder_at_rest_publishes_at_the_hold_rate_and_any_motion_at_once() -> None:
    pos, vel = _straight(80, (0.0, 0.0, 0.0))
    sig = np.full(80, HOLD, np.int64)
    sent = _fly(StatePacer(10.0, 1.0, 10.0, steady=SteadyConfig()), pos, vel, sig=sig)
    assert sent[0] and set(np.diff(np.flatnonzero(sent)).tolist()) == {20}, "not 0.5 Hz"
    # a push of 0.15 m/s at tick 45 (past the 0.1 m/s of rest): out at once, then 3 Hz
    v, p = vel.copy(), pos.copy()
    v[45:] = (0.15, 0.0, 0.0)
    p[46:] += np.cumsum(np.tile((0.15 * TICK_S, 0.0, 0.0), (34, 1)), axis=0)
    sent = _fly(StatePacer(10.0, 1.0, 10.0, steady=SteadyConfig()), p, v, sig=sig)
    assert sent[45], "the first state off rest waited"
    assert set(np.diff(np.flatnonzero(sent[45:])).tolist()) == {3}
    # a goto (a new mode) at tick 45: at once
    sig2 = sig.copy()
    sig2[45:] = int(Mode.GOTO)
    sent = _fly(StatePacer(10.0, 1.0, 10.0, steady=SteadyConfig()), pos, vel, sig=sig2)
    assert sent[45] and set(np.diff(np.flatnonzero(sent[45:])).tolist()) == {3}
    # at rest in another mode (a goto's vehicle waiting), or holding while moving: steady 3 Hz
    for s_, v_ in ((int(Mode.GOTO), (0.0, 0.0, 0.0)), (HOLD, (0.5, 0.0, 0.0))):
        pos, vel = _straight(40, v_)
        sent = _fly(
            StatePacer(10.0, 1.0, 10.0, steady=SteadyConfig()), pos, vel, sig=np.full(40, s_)
        )
        assert set(np.diff(np.flatnonzero(sent)).tolist()) == {3}, (s_, v_)
    # the hold rate is capped to the steady rate, and 2 Hz is taken
    pos, vel = _straight(40)
    pos[:], vel[:] = 0.0, 0.0
    for hz, gap in ((5.0, 3), (2.0, 5)):
        pacer = StatePacer(10.0, 1.0, 10.0, steady=SteadyConfig(hold_state_hz=hz))
        assert set(np.diff(np.flatnonzero(_fly(pacer, pos, vel, sig=sig[:40]))).tolist()) == {gap}


def test_a_receiver_tells_a_holder_at_rest_from_its_state() -> None:
    assert announces_hold(Mode.HOLDING, (0.0, 0.05, -0.05))
    assert not announces_hold(Mode.HOLDING, (0.0, 0.1, 0.05))  # faster than rest
    assert not announces_hold(Mode.GOTO, (0.0, 0.0, 0.0))
    assert not announces_hold(Mode.HOLDING, (math.nan, 0.0, 0.0))
    assert MAX_HOLD_PERIOD_S == 2.0


def test_an_idle_row_keeps_the_idle_rate_and_the_steady_rate_is_capped_to_the_full_one() -> None:
    pacer = StatePacer(10.0, 1.0, 10.0, n=2, steady=SteadyConfig())
    sent = np.zeros(2, int)
    for k in range(30):
        sent += pacer.due(
            k * TICK_S, [True, False], np.zeros((2, 3)), np.zeros((2, 3)), [0, 0], [0, 0], [0, 0]
        )
    # row 1: its first state, one a tick early to take its turn, then every third tick
    assert sent.tolist() == [3, 11]
    slow = StatePacer(2.0, 1.0, 10.0, steady=SteadyConfig(state_hz=5.0))
    pos, vel = _straight(40, (0.0, 0.0, 0.0))
    assert set(np.diff(np.flatnonzero(_fly(slow, pos, vel))).tolist()) == {5}


@pytest.mark.parametrize(
    ("kw", "why"),
    [
        ({"state_hz": 1.0}, "at least every 0.33 s"),
        ({"state_hz": math.nan}, "steady state_hz"),
        ({"tol_m": 0.0}, "tol_m"),
        ({"tol_m_s": 2.0}, "tol_m_s"),
        ({"tol_rad": -1.0}, "tol_rad"),
        ({"hold_state_hz": 0.4}, "hold_state_hz must be within \\[0.5, 100\\]"),
        ({"hold_state_hz": math.inf}, "hold_state_hz"),
    ],
)
def test_bad_steady_settings_are_refused_with_the_reason(kw, why) -> None:
    with pytest.raises(ValueError, match=why):
        SteadyConfig(**kw)


def test_a_hovering_agent_publishes_at_the_hold_rate_and_a_goto_at_once(mesh_trio) -> None:
    hub, a, _b = mesh_trio
    heard, station = Seqs(), FleetModel()
    hub.subscribe_states(heard.on_state, vehicle_id=1)
    hub.subscribe_states(station.on_state, vehicle_id=1)
    t = [0.0]
    cfg = AgentConfig(vehicle_id=1, failsafe=NO_GCS, steady=SteadyConfig())
    with Agent(cfg, SimBackend(SimConfig(), now_s=0.0), a, clock_s=lambda: t[0]) as agent:

        def ticks(n: int) -> int:
            sent0 = a.stats.states_sent
            for _ in range(n):
                t[0] += TICK_S
                agent.tick(t[0])
            return a.stats.states_sent - sent0

        ack = agent.handle_command(Command.takeoff(10.0, nonce=new_nonce(), stamp_ns=0))
        assert ack.result is AckResult.ACCEPTED
        climb = ticks(150)  # 15 s: climbs to 10 m and holds there
        assert agent.core.mode_of(0) is Mode.HOLDING
        hover = ticks(60)  # 6 s hovering at rest
        assert 2 <= hover <= 4, f"{hover} states in 6 s of hover (the 0.5 Hz hold rate: 3)"
        view = views_by_id(station.snapshot(time.time_ns()))[1]
        assert not view.stale, "the station waits for a holder's next state"
        ack = agent.handle_command(
            Command.goto_local(30.0, 0.0, -10.0, nonce=new_nonce(), stamp_ns=0)
        )
        assert ack.result is AckResult.ACCEPTED
        assert ticks(1) == 1, "the new mode waited for the steady period"
        # accelerating: a state each time the velocity moved 0.1 m/s from the last one
        speeding = ticks(19)
        assert speeding > 6, f"{speeding} states in 1.9 s of acceleration (steady: 6)"
        total = climb + hover + 1 + speeding
        assert wait_until(lambda: len(heard.of(1)) >= total, 10)
        seqs = [seq for seq, _ in heard.of(1)]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # one seq per state: no gaps
        view = views_by_id(station.snapshot(time.time_ns()))[1]
        assert view.loss_pct == 0.0


@pytest.mark.parametrize(("steady", "period_ticks"), [(True, 3), (False, 10)])
def test_rows_that_started_together_spread_over_the_ticks_of_their_period(
    steady: bool, period_ticks: int
) -> None:
    """90 hovering (steady) or 90 landed (idle) rows, all published on the same tick: after one
    period each tick carries a k-th of them, each row every k ticks, and no gap is longer than
    the period allows (turns only make a state earlier)."""
    n = 90
    pacer = StatePacer(10.0, 1.0, 10.0, n=n, steady=SteadyConfig() if steady else None)
    zeros = np.zeros((n, 3))
    idle = np.full(n, not steady)
    ticks = 60
    sent = np.array(
        [
            pacer.due(k * TICK_S, idle, zeros, zeros, np.zeros(n), np.zeros(n), np.ones(n))
            for k in range(ticks)
        ]
    )
    assert sent[0].all(), "every row's first state goes out at once"
    per_tick = sent[period_ticks:].sum(axis=1)
    assert per_tick.tolist() == [n // period_ticks] * (ticks - period_ticks)
    period_s = 1 / 3.0 if steady else 1.0
    for row in range(n):
        at = np.flatnonzero(sent[:, row])
        gaps = np.diff(at)
        assert gaps.max() * TICK_S <= period_s + 1e-9, (row, gaps)
        assert set(gaps[1:].tolist()) == {period_ticks}, (row, gaps)
