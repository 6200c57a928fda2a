"""How often a vehicle publishes its state, and how long a receiver waits before calling it stale.

A vehicle that is idle (landed or killed, disarmed, on the ground, no autopilot action under way)
has nothing new to say, and nobody steers around it (agent/neighbours.py skips landed, disarmed
vehicles). It publishes its state at `idle_state_hz` (1 Hz by default) instead of `state_hz`
(10 Hz), and hears no neighbour states (agent/app.py). The rule:

    period_s = 1 / idle_state_hz   if idle, else 1 / state_hz
    due      = now_s - last_s >= period_s - tick_period_s / 2   (jitter must not skip a state)
               or idle != idle at the last published state       (a change of idleness: at once)

so the state after a take-off command (or after arming by other means) goes out on the tick after
it, never an idle period later, and so does the first landed state after a touchdown. The one
rule serves both shells: `covey agent` (one row) and `covey fleet-sim` (N rows), as `StatePacer`.

The contract on the wire: an idle vehicle publishes at least every `MAX_IDLE_PERIOD_S`; its seq
still grows by one per published state, so a lower rate is not loss (groundstation/fleet.py). A
receiver tells an idle vehicle from its state alone (`announces_idle`: landed or killed, disarmed)
and waits `idle_stale_after_s` for it before calling it stale.
"""

from __future__ import annotations

import math

import numpy as np

from comms.schema import Mode

IDLE_STATE_HZ = 1.0
"""Default state rate of an idle vehicle."""
MAX_IDLE_PERIOD_S = 1.0
"""An idle vehicle publishes at least this often (idle_state_hz >= 1 / this): what receivers
count on when they judge an idle vehicle's silence."""
IDLE_MODES = frozenset({Mode.LANDED, Mode.KILLED})
"""Modes of a vehicle that can be idle (with its motors disarmed and on the ground)."""

_IDLE_MODE = np.zeros(256, bool)
_IDLE_MODE[[int(m) for m in IDLE_MODES]] = True


def announces_idle(mode: Mode, armed: bool) -> bool:
    """What a receiver reads from a state: the vehicle may publish at its idle rate only."""
    return mode in IDLE_MODES and not armed


def idle_rows(mode, armed, in_air, busy=False) -> np.ndarray:
    """(N,) bool: the vehicles that are idle (mode in IDLE_MODES, disarmed, on the ground, no
    autopilot action waiting or running). Arguments are (N,) arrays or scalars."""
    mode = np.asarray(mode, np.intp)
    return (
        _IDLE_MODE[mode]
        & ~np.asarray(armed, bool)
        & ~np.asarray(in_air, bool)
        & ~np.asarray(busy, bool)
    ).reshape(-1)


def check_rates(state_hz: float, idle_state_hz: float) -> None:
    """Raise ValueError with the reason if the two rates cannot be used."""
    if not (math.isfinite(state_hz) and 0 < state_hz <= 100):
        raise ValueError(f"state_hz must be within (0, 100], got {state_hz}")
    low = 1.0 / MAX_IDLE_PERIOD_S
    if not (math.isfinite(idle_state_hz) and low <= idle_state_hz <= 100):
        raise ValueError(
            f"idle_state_hz must be within [{low:g}, 100] (receivers count on an idle vehicle "
            f"every {MAX_IDLE_PERIOD_S:g} s), got {idle_state_hz}"
        )


class StatePacer:
    """Which of N vehicles publish their state this tick (the rule in the module docstring).
    An idle rate above `state_hz` is capped to it: an idle vehicle never says more."""

    def __init__(self, state_hz: float, idle_state_hz: float, tick_hz: float, n: int = 1) -> None:
        check_rates(state_hz, idle_state_hz)
        if not (math.isfinite(tick_hz) and tick_hz > 0):
            raise ValueError(f"tick_hz must be positive, got {tick_hz}")
        self.period_s = 1.0 / state_hz
        self.idle_period_s = 1.0 / min(idle_state_hz, state_hz)
        self.slack_s = 0.5 / tick_hz
        self.last_s = np.full(n, -np.inf)
        """When each row last published."""
        self.last_idle = np.zeros(n, bool)
        """Whether each row was idle when it last published."""

    def due(self, now_s: float, idle: np.ndarray) -> np.ndarray:
        """(N,) bool: the rows to publish at `now_s`, given which are `idle` now; they count as
        published."""
        idle = np.asarray(idle, bool)
        period_s = np.where(idle, self.idle_period_s, self.period_s)
        due = (now_s - self.last_s >= period_s - self.slack_s) | (idle != self.last_idle)
        self.last_s[due] = now_s
        self.last_idle[due] = idle[due]
        return due

    def again(self) -> None:
        """Make every row due on the next call (a test re-sending at the same instant)."""
        self.last_s[:] = -np.inf
