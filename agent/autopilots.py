"""A shell's vehicles as arrays: N vehicle backends read, stepped and steered as N rows.

The shell (agent/shell.py) works on rows; this module is the one place that turns backends into
rows and rows back into calls. One or a few real autopilots (MAVSDK, a relay) are read one
`telemetry()` call each. The rows of one simulated fleet (agent/backends/sim.py: `SimBackend`s
of one `SimFleet`, in row order) are read straight from its arrays: the fast path, which
`read_each` (the reference path) must equal (tests/test_shell.py).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from agent.backends.base import BackendError, Capability, Telemetry, VehicleBackend
from agent.backends.sim import SimBackend, SimFleet
from agent.flight_core import Observed
from comms.one_row import FLAG, frozen

log = logging.getLogger(__name__)


class Autopilots:
    """N vehicle backends, one row each."""

    def __init__(
        self, backends: Sequence[VehicleBackend], assumed_pos_sigma_m: float = 0.0
    ) -> None:
        """`assumed_pos_sigma_m`: the position 1-sigma of a vehicle whose autopilot reports no
        horizontal accuracy (ShellConfig.assumed_pos_sigma_m); a simulated vehicle reports its
        model's (0: exact)."""
        if not (math.isfinite(assumed_pos_sigma_m) and assumed_pos_sigma_m >= 0.0):
            raise ValueError(f"assumed_pos_sigma_m must be >= 0, got {assumed_pos_sigma_m}")
        if not backends:
            raise ValueError("a shell needs at least one vehicle backend")
        self.backends = list(backends)
        self.n = len(self.backends)
        self.capabilities: frozenset[Capability] = frozenset.intersection(
            *(frozenset(b.capabilities) for b in self.backends)
        )
        """What every vehicle can do (a shell flies all of its vehicles one way)."""
        self.sim: SimFleet | None = _one_sim_fleet(self.backends)
        """The simulated fleet whose rows these are, in order, or None (the fast path's)."""
        self.pos_sigma_m = np.zeros(self.n)
        """(n,) each vehicle's position 1-sigma, from the last `read`."""
        self._sigma_one = (math.nan, self.pos_sigma_m)  # a fleet of one: its sigma, as (1,)
        self._assumed_m = np.array(
            [0.0 if isinstance(b, SimBackend) else assumed_pos_sigma_m for b in self.backends]
        )

    def capable(self, capability: Capability) -> list[int]:
        """The rows whose backend has `capability` (a receiver, a geofence...)."""
        return [i for i, b in enumerate(self.backends) if capability in b.capabilities]

    def step(self, now_s: float) -> None:
        """Let simulated vehicles move up to `now_s` (real ones move by themselves)."""
        if self.sim is not None:
            self.sim.step(now_s)
            return
        for b in self.backends:
            b.step(now_s)

    def read(self) -> Observed | None:
        """This tick's telemetry of every row, or None while a vehicle has none yet (an
        autopilot not yet heard)."""
        sim = self.sim
        if sim is None:
            return self.read_each()
        with sim.lock:
            return self._read_one(sim) if self.n == 1 else self._read_rows(sim)

    def _read_rows(self, sim: SimFleet) -> Observed:
        """`read` of a simulated fleet, straight from its arrays. Lock held."""
        self.pos_sigma_m = np.full(self.n, float(sim.pos_sigma_m))
        return Observed(
            sim.pos_m,
            sim.ground_vel_m_s,
            sim.armed,
            sim.pos_m[:, 2] < -0.05,  # SimFleet.in_air, every row
            sim.battery_pct,
            ~sim.closed,
            self.pos_sigma_m,
        )

    def _read_one(self, sim: SimFleet) -> Observed:
        """`read` of a fleet of one (an agent's every tick): its flags taken as Python bools
        and given as shared read-only arrays, its sigma's array kept while the sigma is the
        same, its velocity the fleet's one-row `ground_vel_m_s`; no array is computed (each
        small numpy call costs a cold tick several microseconds, docs/companion.md). Equal to
        the rows path and to `read_each` (tests/test_shell.py). Lock held."""
        sigma = float(sim.pos_sigma_m)
        if sigma != self._sigma_one[0]:  # kept from tick to tick: read-only
            self._sigma_one = (sigma, frozen(np.full(1, sigma)))
        self.pos_sigma_m = self._sigma_one[1]
        return Observed(
            sim.pos_m,
            sim.ground_vel_m_s,
            sim.armed,
            FLAG[sim.in_air(0)],
            sim.battery_pct,
            FLAG[not sim.closed.item(0)],
            self.pos_sigma_m,
        )

    def read_each(self) -> Observed | None:
        """`read` by one `telemetry()` call per backend (the reference path)."""
        tels: list[Telemetry] = []
        for b in self.backends:
            tel = b.telemetry()
            if tel is None:
                return None
            tels.append(tel)
        reported = np.array([t.pos_sigma_m for t in tels], float)
        # 0: the autopilot reports no accuracy (backends.base.pos_sigma_of); not taken as exact
        self.pos_sigma_m = np.where(reported > 0.0, reported, self._assumed_m)
        return Observed(
            np.array([t.pos_ned_m for t in tels], float).reshape(self.n, 3),
            np.array([t.vel_ned_m_s for t in tels], float).reshape(self.n, 3),
            np.array([t.armed for t in tels], bool),
            np.array([t.in_air for t in tels], bool),
            np.array([t.battery_pct for t in tels], float),
            np.array([t.link_ok for t in tels], bool),
            self.pos_sigma_m,
            np.array(
                [
                    math.nan if t.onboard_separation_m is None else t.onboard_separation_m
                    for t in tels
                ],
                float,
            ),
        )

    def set_velocities(self, rows: np.ndarray, vel_ned_m_s: np.ndarray, heading_rad: np.ndarray):
        """Velocity setpoints for `rows` (guided: armed, linked, finite). A refused setpoint is
        logged; the next tick sends another."""
        if self.sim is not None:
            self.sim.set_velocities(rows, vel_ned_m_s, heading_rad)
            return
        for r, v, h in zip(rows.tolist(), vel_ned_m_s, heading_rad.tolist(), strict=True):
            try:
                self.backends[r].set_velocity_ned(v, h)
            except BackendError as exc:
                log.warning("setpoint refused: %s", exc)


def _one_sim_fleet(backends: list[VehicleBackend]) -> SimFleet | None:
    """The SimFleet whose rows 0..n-1 `backends` are, in order (plain SimBackends only: a
    subclass may change what a row does), or None."""
    first = backends[0]
    if type(first) is not SimBackend:
        return None
    fleet = first.fleet
    if fleet.n != len(backends):
        return None
    for i, b in enumerate(backends):
        if type(b) is not SimBackend or b.fleet is not fleet or b.index != i:
            return None
    return fleet
