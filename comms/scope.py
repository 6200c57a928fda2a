"""Spatial scoping: which grid cells of states a vehicle must hear, and when that changes.

A vehicle hears the states of the cells within its reach, not the whole fleet (docs/scaling.md):

    reach_m = sense_range_m + separation_m + closing_speed_m_s * handover_s
    closing_speed_m_s = 2 * max_speed_m_s       (two vehicles flying at each other)
    handover_s = resubscribe_s + state_period_s + link_latency_s + cell_relay_period_s

A neighbour outside the reach when the subscriptions change cannot come within sense range plus
separation before its first state through the new subscription arrives.

Hysteresis: a vehicle keeps an anchor cell and the (2k + 1)^2 cells around it,
k = ceil((reach_m + hysteresis_m) / CELL_M), until it strays more than hysteresis_m outside the
anchor cell; then the cell it is in becomes the anchor. While it stays within that margin, every
point within reach_m of it lies in a subscribed cell (Chebyshev distance <= Euclidean), and a
vehicle that wanders along a cell border does not churn subscriptions.

`Scope` works on N vehicles at once (a fleet-sim process subscribes to the union of its
vehicles' cells; an agent is N = 1). Pure: no Zenoh, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from comms.keys import CELL_M, Cell
from comms.state_rate import MAX_HOLD_PERIOD_S


@dataclass(frozen=True)
class ScopeConfig:
    """What a vehicle must hear, in world units; the defaults hold for covey's guidance defaults
    (3 m separation, 1 m/s cruise) on a link as slow as 3 Hz."""

    enabled: bool = True
    """Subscribe to the cells within reach only; False: every state of the fleet (the old way)."""
    sense_range_m: float = 15.0
    """The farthest a neighbour can be and still change what guidance does. At least the safety
    filter's reach (separation * 1.2 + 2 * cruise * 4 s horizon = 11.6 m) and the stale-caution
    radius (15 m); the shipped policy has no sense range of its own, so this is its sense range."""
    separation_m: float = 3.0
    """The separation guidance keeps (a neighbour's state is its centre; its disc reaches this far)."""
    max_speed_m_s: float = 2.0
    """The fastest any vehicle of the fleet flies horizontally (twice the default cruise)."""
    resubscribe_s: float = 0.3
    """Worst time from declaring a cell's subscriber to its first routed sample (across routers)."""
    state_period_s: float = 0.34
    """Worst time between two states of one vehicle (the slowest link: 3 Hz)."""
    link_latency_s: float = 0.1
    """Worst one-way delay of a state on the link."""
    cell_relay_period_s: float = 0.1
    """Worst wait of a state in a router's cell relay (comms/relay.py; `covey router
    --cell-relay-period-s`, whose default this is)."""
    hysteresis_m: float = 5.0
    """How far past its anchor cell a vehicle may stray before its subscriptions move."""

    def __post_init__(self) -> None:
        for name in (
            "sense_range_m",
            "separation_m",
            "max_speed_m_s",
            "resubscribe_s",
            "state_period_s",
            "link_latency_s",
            "cell_relay_period_s",
            "hysteresis_m",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 100_000):
                raise ValueError(f"{name}={value} must be a finite number within [0, 100000]")

    @property
    def closing_speed_m_s(self) -> float:
        """Two vehicles flying straight at each other."""
        return 2.0 * self.max_speed_m_s

    @property
    def handover_s(self) -> float:
        """Worst delay from a subscription change to a new cell's first state."""
        return (
            self.resubscribe_s
            + self.state_period_s
            + self.link_latency_s
            + self.cell_relay_period_s
        )

    @property
    def hold_reach_m(self) -> float:
        """What a holder at rest needs heard: it publishes only every MAX_HOLD_PERIOD_S
        (comms/state_rate.py) but does not move between its states (the first state of a move
        goes out at once), so one vehicle closes on it at max speed over the longer hand-over:
        sense range + separation + max speed * (resubscribe + hold period + latency + relay): 23 m
        with the defaults, which `reach_m` covers (tests/test_comms_scope.py)."""
        hand_over_s = (
            self.resubscribe_s + MAX_HOLD_PERIOD_S + self.link_latency_s + self.cell_relay_period_s
        )
        return self.sense_range_m + self.separation_m + self.max_speed_m_s * hand_over_s

    @property
    def reach_m(self) -> float:
        """reach = sense range + separation + closing speed * hand-over delay, or a holder's
        longer reach (`hold_reach_m`) where that is further: 23 m with the defaults."""
        moving = self.sense_range_m + self.separation_m + self.closing_speed_m_s * self.handover_s
        return max(moving, self.hold_reach_m)

    @property
    def rings(self) -> int:
        """Cells subscribed on each side of the anchor cell: ceil((reach + hysteresis) / cell)."""
        return max(1, math.ceil((self.reach_m + self.hysteresis_m) / CELL_M))

    def cells_around(self, anchor: Cell) -> set[Cell]:
        """The (2 rings + 1)^2 cells a vehicle anchored in `anchor` hears."""
        k, (cn, ce) = self.rings, anchor
        return {(cn + i, ce + j) for i in range(-k, k + 1) for j in range(-k, k + 1)}


class Scope:
    """Anchor cells of N vehicles and the union of the cells they hear."""

    def __init__(self, cfg: ScopeConfig, n: int = 1) -> None:
        self.cfg = cfg
        self.anchor = np.zeros((n, 2), np.int64)
        self.placed = np.zeros(n, bool)
        """Rows that have had a position (an unplaced vehicle hears nothing yet)."""
        self.cells: frozenset[Cell] = frozenset()
        self.moves = 0
        """How many times the cell set changed (read only)."""

    def update(self, pos_ned_m: np.ndarray) -> frozenset[Cell] | None:
        """Give the vehicles' positions, (N, 2+) or one (2+,) row; returns the new cell set when
        it changed, else None (the common case: a few comparisons)."""
        h = self.cfg.hysteresis_m
        p = np.asarray(pos_ned_m, np.float64).reshape(len(self.anchor), -1)[:, :2]
        if len(p) == 1 and self.placed[0]:
            # an agent's every tick: still within its anchor's margin, on Python floats (the
            # test below on one row; a move, a NaN or a first fix take the array path)
            (n_m, e_m), (an, ae) = p[0].tolist(), self.anchor[0].tolist()
            if (
                an * CELL_M - h <= n_m < (an + 1) * CELL_M + h
                and ae * CELL_M - h <= e_m < (ae + 1) * CELL_M + h
            ):
                return None
        ok = np.isfinite(p).all(axis=1)
        lo = self.anchor * CELL_M - h
        hi = (self.anchor + 1) * CELL_M + h
        strayed = ((p < lo) | (p >= hi)).any(axis=1)
        move = ok & (strayed | ~self.placed)
        if not move.any():
            return None
        self.anchor[move] = np.floor(p[move] / CELL_M).astype(np.int64)
        self.placed |= move
        cells: set[Cell] = set()
        for cn, ce in {tuple(a) for a in self.anchor[self.placed].tolist()}:
            cells |= self.cfg.cells_around((cn, ce))
        if cells == self.cells:
            return None
        self.cells = frozenset(cells)
        self.moves += 1
        return self.cells
