"""Guidance: turn (own state, goal, neighbour table) into a velocity setpoint.

Horizontal: the learned policy (policy.runtime, plus its safety filter) in position modes. The
policy was trained to decide once per training step (1 s in policy units,
`GuidancePolicy.decision_period_s`), so it decides at that period and its velocity is held in
between, as in training and in `covey eval`; the stale-data slowdown and the safety filter run
on the held velocity every tick, against the latest neighbours. In
hold, a position-hold controller whose output also goes through the safety filter, so a holding
vehicle still steps aside for a neighbour that comes too close.
Vertical: a proportional altitude controller (the policy is planar, as in the paper).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.neighbours import NeighbourSnapshot
from policy import safety
from policy.runtime import GuidancePolicy

DECISION_DUE_SHARE = 0.95
"""A decision is due once this share of the decision period has passed (tick jitter must not
push a decision a whole tick late). Used by Guidance and by fleet-sim's batched copy of it."""


@dataclass(frozen=True)
class GuidanceConfig:
    """Tuning of the guidance loop, in world units."""

    separation_m: float = 3.0
    """Minimum distance between two vehicles; the policy's 3 m scales to this."""
    cruise_speed_m_s: float = 1.0
    """Speed the policy flies at (its unit speed)."""
    arrive_radius_m: float = 1.0
    """Horizontal distance at which a goto counts as arrived (then the vehicle holds there)."""
    arrive_alt_tol_m: float = 0.5
    vertical_gain_1_s: float = 1.0
    max_vertical_speed_m_s: float = 1.5
    hold_gain_1_s: float = 0.8
    stale_slowdown: float = 0.5
    """Speed factor while a nearby neighbour's data is stale."""
    stale_caution_radius_m: float = 15.0
    """Stale neighbours farther than this do not slow us down."""
    safety_filter: bool = True
    """Run the separation filter after the policy (beyond the paper)."""
    policy_path: str | None = None
    """Weights file; None = the shipped weights."""
    decision_period_s: float | None = None
    """Seconds between policy decisions (the velocity is held in between). None: the policy's
    own period, as trained; 0: decide every tick (jerkier tracks, see docs/policy.md)."""

    def __post_init__(self) -> None:
        for name in ("separation_m", "cruise_speed_m_s", "arrive_radius_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        p = self.decision_period_s
        if p is not None and not (math.isfinite(p) and 0 <= p <= 10):
            raise ValueError(f"decision_period_s must be within 0..10 s (or None), got {p}")


@dataclass(frozen=True)
class GuidanceOutput:
    vel_ned_m_s: np.ndarray
    heading_rad: float
    filtered: bool
    """The safety filter changed the command."""
    slowed_for_stale: bool
    decided: bool = True
    """The policy decided this tick (False: its last decision was held)."""


class Guidance:
    def __init__(self, cfg: GuidanceConfig, policy: GuidancePolicy | None = None) -> None:
        self.cfg = cfg
        self.policy = policy or GuidancePolicy.load(
            cfg.policy_path,
            separation_m=cfg.separation_m,
            cruise_speed_m_s=cfg.cruise_speed_m_s,
            safety_filter=False,  # applied here so that we can tell when it acted
        )
        self.safety_cfg = self.policy.safety_cfg
        p = cfg.decision_period_s
        self.decision_period_s = self.policy.decision_period_s if p is None else p
        self._held_m_s: np.ndarray | None = None  # the last decision's horizontal velocity
        self._held_goal_m: np.ndarray | None = None
        self._decided_s = -math.inf

    def decision_due(self, now_s: float, goal_m: np.ndarray) -> bool:
        """Whether the policy should decide now: its period has passed (DECISION_DUE_SHARE of it,
        for tick jitter), the goal changed, or nothing is held (first tick, after a hold)."""
        return (
            self._held_m_s is None
            or self._held_goal_m is None
            or not np.array_equal(self._held_goal_m, goal_m)
            or now_s - self._decided_s >= DECISION_DUE_SHARE * self.decision_period_s
        )

    @property
    def has_decision(self) -> bool:
        """A decision is held (goto can skip deciding)."""
        return self._held_m_s is not None

    def reset(self) -> None:
        """Forget the held decision (the next goto decides at once)."""
        self._held_m_s = self._held_goal_m = None

    def _vertical(self, pos_d_m: float, goal_d_m: float) -> float:
        vz = self.cfg.vertical_gain_1_s * (goal_d_m - pos_d_m)
        return float(np.clip(vz, -self.cfg.max_vertical_speed_m_s, self.cfg.max_vertical_speed_m_s))

    def _stale_factor(self, pos_m: np.ndarray, nbrs: NeighbourSnapshot) -> float:
        if not nbrs.stale_ids:
            return 1.0
        for vid, p in zip(nbrs.ids, nbrs.pos_ned_m, strict=True):
            if (
                vid in nbrs.stale_ids
                and np.hypot(*(p[:2] - pos_m[:2])) < self.cfg.stale_caution_radius_m
            ):
                return self.cfg.stale_slowdown
        return 1.0

    def _filter(self, pos_m, vel_m_s, pref_m_s, nbrs: NeighbourSnapshot) -> tuple[np.ndarray, bool]:
        if not self.cfg.safety_filter or len(nbrs) == 0:
            return pref_m_s, False
        out = safety.filter_velocity(
            pos_m[:2],
            vel_m_s[:2],
            pref_m_s,
            nbrs.pos_ned_m[:, :2],
            nbrs.vel_ned_m_s[:, :2],
            self.safety_cfg,
        )
        return out, bool(np.linalg.norm(out - pref_m_s) > 1e-6)

    def goto(
        self,
        pos_m: np.ndarray,
        vel_m_s: np.ndarray,
        heading_rad: float,
        goal_m: np.ndarray,
        nbrs: NeighbourSnapshot,
        now_s: float | None = None,
        decide: bool | None = None,
    ) -> GuidanceOutput:
        """Policy guidance towards `goal_m` (NED).

        `decide` forces (True) or skips (False) a policy decision; None decides when
        `decision_due(now_s, goal_m)`, or every call when `now_s` is None. Nothing held: decide."""
        if decide is None:
            decide = now_s is None or self.decision_due(now_s, goal_m)
        if decide or self._held_m_s is None:
            self._held_m_s = np.asarray(
                self.policy.command(
                    pos_m[:2],
                    vel_m_s[:2],
                    heading_rad,
                    goal_m[:2],
                    nbrs.pos_ned_m[:, :2],
                    nbrs.vel_ned_m_s[:, :2],
                    nbrs.heading_rad,
                ),
                dtype=float,
            )
            self._held_goal_m = np.array(goal_m, dtype=float)
            self._decided_s = -math.inf if now_s is None else now_s
            decide = True
        factor = self._stale_factor(pos_m, nbrs)
        v_h, filtered = self._filter(pos_m, vel_m_s, self._held_m_s * factor, nbrs)
        vel = np.array([v_h[0], v_h[1], self._vertical(pos_m[2], goal_m[2])])
        return GuidanceOutput(vel, _heading_of(v_h, heading_rad), filtered, factor < 1.0, decide)

    def hold(
        self,
        pos_m: np.ndarray,
        vel_m_s: np.ndarray,
        heading_rad: float,
        hold_m: np.ndarray,
        nbrs: NeighbourSnapshot,
    ) -> GuidanceOutput:
        """Keep `hold_m`, stepping aside for neighbours that come too close."""
        self.reset()  # a later goto starts from a fresh decision
        pref = self.cfg.hold_gain_1_s * (hold_m[:2] - pos_m[:2])
        speed = float(np.linalg.norm(pref))
        if speed > self.cfg.cruise_speed_m_s:
            pref *= self.cfg.cruise_speed_m_s / speed
        v_h, filtered = self._filter(pos_m, vel_m_s, pref, nbrs)
        vel = np.array([v_h[0], v_h[1], self._vertical(pos_m[2], hold_m[2])])
        # Hovering does not turn the vehicle: keep the heading unless it really moves.
        return GuidanceOutput(
            vel, _heading_of(v_h, heading_rad, min_speed_m_s=0.5), filtered, False
        )

    def arrived(self, pos_m: np.ndarray, goal_m: np.ndarray) -> bool:
        return bool(
            np.hypot(*(goal_m[:2] - pos_m[:2])) <= self.cfg.arrive_radius_m
            and abs(goal_m[2] - pos_m[2]) <= self.cfg.arrive_alt_tol_m
        )


def _heading_of(v_h: np.ndarray, fallback_rad: float, min_speed_m_s: float = 0.05) -> float:
    """Heading is the direction of motion (the paper's definition); keep the last one when still."""
    if float(np.hypot(v_h[0], v_h[1])) < min_speed_m_s:
        return fallback_rad
    return math.atan2(float(v_h[1]), float(v_h[0]))


def heading_towards(pos_m: np.ndarray, goal_m: np.ndarray, fallback_rad: float) -> float:
    d = goal_m[:2] - pos_m[:2]
    if float(np.hypot(*d)) < 1e-6:
        return fallback_rad
    return math.atan2(float(d[1]), float(d[0]))
