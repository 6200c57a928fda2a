"""How often a vehicle publishes its state, and how long a receiver waits before calling it stale.

A vehicle that is idle (landed or killed, disarmed, on the ground, no autopilot action under way)
has nothing new to say, and nobody steers around it (agent/neighbours.py skips landed, disarmed
vehicles). It publishes its state at `idle_state_hz` (1 Hz by default) instead of `state_hz`
(10 Hz), and hears no neighbour states (agent/shell.py). The rule:

    period_s = 1 / idle_state_hz   if idle, else 1 / state_hz
    due      = now_s - last_s >= period_s - tick_period_s / 2   (jitter must not skip a state)
               or idle != idle at the last published state       (a change of idleness: at once)
               or it is the row's turn (below)

A period of k >= 2 ticks gives each row a turn: row r on the ticks t where (t + r) % k == 0. A row
publishes on its turn (up to k - 1 ticks before the rule above would have it), so rows that
started together, a fleet that took off or landed at once, spread over the k ticks instead of
publishing all on one (measured: a 100-vehicle host sent 100 states every third tick, then 33 or
34 on each). Turns only ever make a state earlier.

so the state after a take-off command (or after arming by other means) goes out on the tick after
it, never an idle period later, and so does the first landed state after a touchdown. The one
rule serves both shells: `covey agent` (one row) and `covey fleet-sim` (N rows), as `StatePacer`.

The contract on the wire: an idle vehicle publishes at least every `MAX_IDLE_PERIOD_S`; its seq
still grows by one per published state, so a lower rate is not loss (groundstation/fleet.py). A
receiver tells an idle vehicle from its state alone (`announces_idle`: landed or killed, disarmed)
and waits `idle_stale_after_s` for it before calling it stale.

A vehicle in the air whose state a receiver can predict (`SteadyConfig`, off unless configured:
`covey agent --steady-state-hz`) publishes at `steady_state_hz` instead of `state_hz`: the
dead-reckoning threshold of distributed simulation (IEEE 1278 DIS). Receivers already extrapolate
every neighbour's last state at its velocity (agent/neighbours.py); a row is steady while its
position is within `tol_m` of that extrapolation of its last published state, its velocity within
`tol_m_s` and its heading within `tol_rad` of what it published, and its mode and arming as they
were. Anything else (a turn, a speed change, a new mode) publishes on the next tick:

    steady   = |p - (p_last + v_last (now_s - last_s))| <= tol_m and |v - v_last| <= tol_m_s
               and |heading - heading_last| <= tol_rad and (mode, armed) unchanged
    period_s = 1 / idle_state_hz if idle, 1 / steady_state_hz if steady, else 1 / state_hz

so what a receiver extrapolates is never further than tol_m from the truth at a publication, and
a steady vehicle is heard at least every 1 / steady_state_hz (>= 3 Hz: the slowest link covey
flies on and the state period in the scoping reach, docs/scaling.md). A hovering or straight-
flying fleet thus sends a third of the states.

A steady vehicle holding at rest (`announces_hold`: mode HOLDING, speed at most HOLD_REST_M_S,
in the state it published and now) publishes at `SteadyConfig.hold_state_hz` (0.5 Hz) instead:
nothing it says changes until it moves, and the first state after it moves (a goto, a push by
the filter, a gust or a drift of its estimate past tol_m) goes out on the next tick, as any
unsteady state does. Receivers tell a holder from its state alone, like an idle vehicle, and
wait longer before calling it stale (agent/neighbours.py `hold_stale_s`, the station's
`hold_stale_after_s`). The scoping reach still holds: a holder does not move between its
states, so a vehicle entering its cells closes on it at one vehicle's speed over the longer
hand-over (comms/scope.py `ScopeConfig.hold_reach_m`, within `reach_m`). A hovering fleet thus
sends a twentieth of the states of 10 Hz, a sixth of the steady rate's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from comms.one_row import FLAG
from comms.schema import Mode

IDLE_STATE_HZ = 1.0
"""Default state rate of an idle vehicle."""
MAX_IDLE_PERIOD_S = 1.0
"""An idle vehicle publishes at least this often (idle_state_hz >= 1 / this): what receivers
count on when they judge an idle vehicle's silence."""
IDLE_MODES = frozenset({Mode.LANDED, Mode.KILLED})
"""Modes of a vehicle that can be idle (with its motors disarmed and on the ground)."""

MAX_HOLD_PERIOD_S = 2.0
"""A vehicle holding at rest publishes at least this often (hold_state_hz >= 1 / this): what
receivers count on when they judge a holder's silence."""
HOLD_REST_M_S = 0.1
"""A HOLDING vehicle whose speed (3D, the state's velocity) is at most this is at rest
(`announces_hold`)."""

MIN_STEADY_STATE_HZ = 3.0
"""A steady vehicle publishes at least this often: the slowest link covey flies on, which the
scoping reach (comms/scope.py `state_period_s`) and the neighbours' stale limit count on."""


@dataclass(frozen=True)
class SteadyConfig:
    """When a vehicle in the air may publish at the lower steady rate (module docstring)."""

    state_hz: float = MIN_STEADY_STATE_HZ
    """State rate while steady; at least MIN_STEADY_STATE_HZ (capped to the full rate)."""
    tol_m: float = 0.1
    """Largest gap between the position and the extrapolated last published one."""
    tol_m_s: float = 0.1
    """Largest change of velocity (norm of the difference) since the last published state."""
    tol_rad: float = 0.05
    """Largest change of heading since the last published state."""
    hold_state_hz: float = 0.5
    """State rate while steady and holding at rest (`announces_hold`, in what was published
    and now); at least 1 / MAX_HOLD_PERIOD_S, capped to state_hz (and the full rate)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.state_hz) and MIN_STEADY_STATE_HZ <= self.state_hz <= 100):
            raise ValueError(
                f"steady state_hz must be within [{MIN_STEADY_STATE_HZ:g}, 100] (receivers and "
                f"the scoping reach count on a state at least every "
                f"{1 / MIN_STEADY_STATE_HZ:.2f} s), got {self.state_hz}"
            )
        low = 1.0 / MAX_HOLD_PERIOD_S
        if not (math.isfinite(self.hold_state_hz) and low <= self.hold_state_hz <= 100):
            raise ValueError(
                f"steady hold_state_hz must be within [{low:g}, 100] (receivers count on a "
                f"holding vehicle every {MAX_HOLD_PERIOD_S:g} s), got {self.hold_state_hz}"
            )
        for name, hi in (("tol_m", 1.0), ("tol_m_s", 1.0), ("tol_rad", 0.5)):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 < v <= hi):
                raise ValueError(f"steady {name} must be within (0, {hi:g}], got {v}")


_IDLE_MODE = np.zeros(256, bool)
_IDLE_MODE[[int(m) for m in IDLE_MODES]] = True


def announces_idle(mode: Mode, armed: bool) -> bool:
    """What a receiver reads from a state: the vehicle may publish at its idle rate only."""
    return mode in IDLE_MODES and not armed


_HOLDING = int(Mode.HOLDING)


def announces_hold(mode: Mode | int, vel_ned_m_s) -> bool:
    """What a receiver reads from a state: the vehicle holds at rest and may publish at its
    hold rate only (MAX_HOLD_PERIOD_S)."""
    if int(mode) != _HOLDING:
        return False
    vn, ve, vd = vel_ned_m_s
    return vn * vn + ve * ve + vd * vd <= HOLD_REST_M_S * HOLD_REST_M_S


def hold_rows(mode, vel_ned_m_s) -> np.ndarray:
    """(N,) bool: `announces_hold` of N rows, (N,) modes (ints) and (N, 3) velocities."""
    vel = np.asarray(vel_ned_m_s, float).reshape(-1, 3)
    return (np.asarray(mode, np.int64).reshape(-1) == _HOLDING) & (
        np.einsum("ij,ij->i", vel, vel) <= HOLD_REST_M_S * HOLD_REST_M_S
    )


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


def idle_one(mode: int, armed: bool, in_air: bool, busy: bool = False) -> bool:
    """`idle_rows` of one vehicle, on Python values (an agent's every tick)."""
    return bool(_IDLE_MODE[mode]) and not (armed or in_air or busy)


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


def _one(x):
    """The one value of a one-row argument: a (1,) array's item, or a scalar."""
    return x.item(0) if type(x) is np.ndarray else np.asarray(x).reshape(-1).item(0)


class StatePacer:
    """Which of N vehicles publish their state this tick (the rule in the module docstring).
    An idle rate above `state_hz` is capped to it: an idle vehicle never says more."""

    def __init__(
        self,
        state_hz: float,
        idle_state_hz: float,
        tick_hz: float,
        n: int = 1,
        steady: SteadyConfig | None = None,
    ) -> None:
        check_rates(state_hz, idle_state_hz)
        if not (math.isfinite(tick_hz) and tick_hz > 0):
            raise ValueError(f"tick_hz must be positive, got {tick_hz}")
        self.period_s = 1.0 / state_hz
        self.idle_period_s = 1.0 / min(idle_state_hz, state_hz)
        self.tick_hz = tick_hz
        self.slack_s = 0.5 / tick_hz
        self.calls = 0
        """How many times `due` was asked (once per tick): whose turn it is."""
        self._rows = np.arange(n)
        self.last_s = np.full(n, -np.inf)
        """When each row last published."""
        self.last_idle = np.zeros(n, bool)
        """Whether each row was idle when it last published."""
        self.steady = steady
        self.steady_period_s = 1.0 / min(steady.state_hz, state_hz) if steady else self.period_s
        self.hold_period_s = (
            1.0 / min(steady.hold_state_hz, steady.state_hz, state_hz)
            if steady
            else self.steady_period_s
        )
        self.last_pos = np.zeros((n, 3))
        self.last_vel = np.zeros((n, 3))
        self.last_hdg = np.zeros(n)
        self.last_sig = np.full(n, -1, np.int64)
        """What each row last published (position, velocity, heading, mode and arming)."""

    def due(
        self,
        now_s: float,
        idle: np.ndarray,
        pos_m: np.ndarray | None = None,
        vel_m_s: np.ndarray | None = None,
        heading_rad: np.ndarray | None = None,
        mode: np.ndarray | None = None,
        armed: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N,) bool: the rows to publish at `now_s`, given which are `idle` now; they count as
        published. With a SteadyConfig, also each row's (N, 3) position and velocity, (N,)
        heading, mode (ints) and arming; without them no row is steady."""
        if len(self._rows) == 1:
            return self._due_one(now_s, idle, pos_m, vel_m_s, heading_rad, mode, armed)
        idle = np.asarray(idle, bool)
        period_s = np.where(idle, self.idle_period_s, self.period_s)
        track = self.steady is not None and pos_m is not None
        if track:
            pos_m = np.asarray(pos_m, float).reshape(-1, 3)
            vel_m_s = np.asarray(vel_m_s, float).reshape(-1, 3)
            heading_rad = np.asarray(heading_rad, float).reshape(-1)
            # what must go out at once, as one int per row: mode and arming
            sig = np.asarray(mode, np.int64).reshape(-1) * 2 + np.asarray(armed, bool).reshape(-1)
            steady = ~idle & self._steady(now_s, pos_m, vel_m_s, heading_rad, sig)
            # holding at rest now and in what it published (steady: the same mode)
            hold = steady & hold_rows(sig // 2, vel_m_s) & hold_rows(sig // 2, self.last_vel)
            period_s = np.where(
                hold, self.hold_period_s, np.where(steady, self.steady_period_s, period_s)
            )
        gap_s = now_s - self.last_s
        due = (gap_s >= period_s - self.slack_s) | (idle != self.last_idle)
        # Turns: a row whose period spans k >= 2 ticks goes out on every k-th tick, row r on
        # the ticks where (tick + r) % k == 0, up to k - 1 ticks early once to take its turn.
        # Rows that started together (a fleet that took off or landed at once) would otherwise
        # all publish on the same tick: a host's 100 states in one burst every third tick, and
        # its neighbours' receipt waiting behind the burst. Never later than the rule above.
        ticks = np.maximum(np.floor(period_s * self.tick_hz + 1e-6), 1.0).astype(np.int64)
        turn = (ticks >= 2) & ((self.calls + self._rows) % ticks == 0)
        due |= turn & (gap_s >= period_s - self.slack_s - (ticks - 1) / self.tick_hz)
        self.calls += 1
        self.last_s[due] = now_s
        self.last_idle[due] = idle[due]
        if track and pos_m is not None and vel_m_s is not None and heading_rad is not None:
            self.last_pos[due], self.last_vel[due] = pos_m[due], vel_m_s[due]
            self.last_hdg[due], self.last_sig[due] = heading_rad[due], sig[due]
        return due

    def _due_one(self, now_s, idle, pos_m, vel_m_s, heading_rad, mode, armed) -> np.ndarray:
        """`due` and `_steady` for one row (an agent's every tick) on Python floats: the same
        rule, equal to the array path (tests/test_state_rate.py)."""
        idle_now = bool(_one(idle))
        last_s = float(self.last_s[0])
        period_s = self.idle_period_s if idle_now else self.period_s
        track = self.steady is not None and pos_m is not None
        if track:
            cfg = self.steady
            assert cfg is not None
            p = np.asarray(pos_m, float).reshape(-1).tolist()
            v = np.asarray(vel_m_s, float).reshape(-1).tolist()
            hdg, m, a = float(_one(heading_rad)), int(_one(mode)), bool(_one(armed))
            sig = m * 2 + a
            age_s = now_s - last_s
            if not idle_now and math.isfinite(age_s) and sig == int(self.last_sig[0]):
                lp, lv = self.last_pos[0].tolist(), self.last_vel[0].tolist()
                dn = p[0] - (lp[0] + lv[0] * age_s)
                de = p[1] - (lp[1] + lv[1] * age_s)
                dd = p[2] - (lp[2] + lv[2] * age_s)
                wn, we, wd = v[0] - lv[0], v[1] - lv[1], v[2] - lv[2]
                turn = abs((hdg - float(self.last_hdg[0]) + math.pi) % (2 * math.pi) - math.pi)
                if (
                    dn * dn + de * de + dd * dd <= cfg.tol_m**2
                    and wn * wn + we * we + wd * wd <= cfg.tol_m_s**2
                    and turn <= cfg.tol_rad
                ):
                    rest = HOLD_REST_M_S * HOLD_REST_M_S
                    hold = (
                        m == _HOLDING
                        and v[0] * v[0] + v[1] * v[1] + v[2] * v[2] <= rest
                        and lv[0] * lv[0] + lv[1] * lv[1] + lv[2] * lv[2] <= rest
                    )
                    period_s = self.hold_period_s if hold else self.steady_period_s
        gap_s = now_s - last_s
        due = gap_s >= period_s - self.slack_s or idle_now != bool(self.last_idle[0])
        ticks = max(math.floor(period_s * self.tick_hz + 1e-6), 1)
        if ticks >= 2 and self.calls % ticks == 0:  # its turn (row 0)
            due = due or gap_s >= period_s - self.slack_s - (ticks - 1) / self.tick_hz
        self.calls += 1
        if due:
            self.last_s[0] = now_s
            self.last_idle[0] = idle_now
            if track:
                self.last_pos[0], self.last_vel[0] = p, v
                self.last_hdg[0], self.last_sig[0] = hdg, sig
        return FLAG[due]

    def _steady(self, now_s, pos_m, vel_m_s, heading_rad, sig) -> np.ndarray:
        """(N,) bool: rows whose last published state still predicts them (module docstring)."""
        cfg = self.steady
        assert cfg is not None  # asked only with a SteadyConfig (`due`'s `track`)
        age_s = now_s - self.last_s
        known = np.isfinite(age_s) & (sig == self.last_sig)
        age_s = np.where(known, age_s, 0.0)
        drift = pos_m - (self.last_pos + self.last_vel * age_s[:, None])
        turn = np.abs(np.remainder(heading_rad - self.last_hdg + math.pi, 2 * math.pi) - math.pi)
        return (
            known
            & (np.einsum("ij,ij->i", drift, drift) <= cfg.tol_m**2)
            & (np.sum((vel_m_s - self.last_vel) ** 2, axis=1) <= cfg.tol_m_s**2)
            & (turn <= cfg.tol_rad)
        )

    def again(self) -> None:
        """Make every row due on the next call (a test re-sending at the same instant)."""
        self.last_s[:] = -np.inf
