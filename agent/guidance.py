"""Guidance: turn (own state, target, neighbours) into velocity setpoints, for N vehicles.

Horizontal: the learned policy (policy.runtime) while flying a goto or a return. The policy was
trained to decide once per training step (1 s in policy units, `GuidancePolicy.decision_period_s`),
so it decides at that period and its velocity is held in between, as in training and in `covey
eval`; the stale-data slowdown and the safety filter run on the held velocity every tick, against
the latest neighbours. In hold, a position-hold controller whose output also goes through the
safety filter, so a holding vehicle still steps aside for a neighbour that comes too close.
Vertical: a proportional altitude controller (the policy is planar, as in the paper).
Keep-out zones (`set_zones`): goto rows fly routed waypoints and the filter keeps zone edges; a
zone with a floor or ceiling counts only for rows whose altitudes reach it, and a row over or
under one is kept on its side until horizontally clear (policy/zone_bands.py).

`BatchGuidance` is the one decide-and-hold loop, for any number of vehicles; each row sees its
own neighbours (`NeighbourViews`). `Guidance` is one vehicle's view of it (the N = 1 case) with
a `NeighbourSnapshot` in and a `GuidanceOutput` out. For one row the policy and the filter run
their single-vehicle fast paths; for many, their batched paths (equal within 1e-6 m/s,
tests/test_flight_core.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING

import numpy as np

from agent.neighbours import NeighbourSnapshot
from comms.one_row import FLAG
from comms.scope import ScopeConfig
from policy import safety
from policy.goal_rule import ARRIVE_RADIUS_M
from policy.lanes import LaneConfig, hold_short
from policy.observation import Observations
from policy.runtime import (
    TOLD_SIGMA_FREE_M,
    GuidancePolicy,
    filtered_told_share,
    told_separation_m,
)
from policy.sparse import SparseConfig

if TYPE_CHECKING:  # shapely and scipy load only with zones (`set_zones`)
    from agent.guidance_c import CCore
    from policy.zone_bands import ZoneBands

DECISION_DUE_SHARE = 0.95
"""A decision is due once this share of the decision period has passed (tick jitter must not
push a decision a whole tick late)."""


_INDEX = (int, np.integer)
"""One row's index (`NeighbourViews.sky`), as isinstance takes it."""


@dataclass(frozen=True)
class GuidanceConfig:
    """Tuning of the guidance loop, in world units."""

    separation_m: float = 3.0
    """Minimum distance between two vehicles; the policy's 3 m scales to this."""
    cruise_speed_m_s: float = 1.0
    """Speed the policy flies at (its unit speed). To get out of the way of faster traffic that
    does not cooperate, the separation filter may fly up to twice this (docs/sky.md "The escape
    speed")."""
    arrive_radius_m: float = ARRIVE_RADIUS_M
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
    max_neighbours: int | None = None
    """Nearest neighbours each decision sees; None: every neighbour within the sense range."""
    policy_separation_m: float | None = None
    """Separation the policy is told to keep, its distance scale; the filter still keeps the
    whole separation. None: with the filter on, the share of the separation the weights' config
    states (the shipped weights: all of it; weights without one: 1.25 m per 3 m, a narrower
    berth), the whole separation with it off (policy.runtime.told_separation_m)."""
    sparse_rule: bool = True
    """With the filter on: where a vehicle meets at most two others and not dead-on, fly straight
    at the goal and let the filter resolve it (policy.sparse; docs/policy.md "Sparse traffic").
    Off, or with the filter off: the policy always."""
    non_cooperative_separation_m: float | None = None
    """Separation the filter keeps from traffic that does not cooperate (it also takes the
    whole correction for it; policy.safety.SafetyConfig.non_cooperative_radius_m). None:
    separation_m."""
    manned_separation_m: float | None = safety.MANNED_SEPARATION_M
    """Separation the filter keeps from a manned aircraft (traffic whose ADS-B emitter category
    is manned, comms/adsb.py; policy.safety.SafetyConfig.manned_radius_m). None: as other
    traffic (non_cooperative_separation_m)."""
    lanes: LaneConfig = field(default_factory=LaneConfig)
    """Who waits at a gap only one vehicle fits through (policy.lanes)."""
    c_core: bool = False
    """One vehicle's policy decision and separation filter run in the compiled C core
    (firmware/, built on first use with the system C compiler; equal to numpy's within float32,
    and numpy where the core does not cover a call: zones, a fault, no compiler). `covey agent`
    turns it on; numpy is the reference (agent/guidance_c.py)."""

    def __post_init__(self) -> None:
        for name in ("separation_m", "cruise_speed_m_s", "arrive_radius_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        p = self.decision_period_s
        if p is not None and not (math.isfinite(p) and 0 <= p <= 10):
            raise ValueError(f"decision_period_s must be within 0..10 s (or None), got {p}")
        if self.max_neighbours is not None and self.max_neighbours < 0:
            raise ValueError(f"max_neighbours must be >= 0 or None, got {self.max_neighbours}")
        ps = self.policy_separation_m
        if ps is not None and not (math.isfinite(ps) and ps > 0):
            raise ValueError(f"policy_separation_m must be a positive number (or None), got {ps}")
        nc = self.non_cooperative_separation_m
        if nc is not None and not (math.isfinite(nc) and nc > 0):
            raise ValueError(
                f"non_cooperative_separation_m must be a positive number (or None), got {nc}"
            )
        ms = self.manned_separation_m
        if ms is not None and not (math.isfinite(ms) and ms > 0):
            raise ValueError(f"manned_separation_m must be a positive number (or None), got {ms}")

    @property
    def told_separation_m(self) -> float:
        """The separation the policy is told (policy.runtime.told_separation_m, with the told
        share of the weights at policy_path)."""
        return told_separation_m(
            self.separation_m,
            self.safety_filter,
            self.policy_separation_m,
            share=filtered_told_share(self.policy_path),
        )

    @property
    def told_sigma_free_m(self) -> float | None:
        """Beyond this position 1-sigma the policy is told a berth that grows with the
        filter's inflation (policy.runtime.told_scale); None with a policy_separation_m asked
        for: that one is told as it is."""
        return TOLD_SIGMA_FREE_M if self.policy_separation_m is None else None

    def scope(self, base: ScopeConfig) -> ScopeConfig:
        """`base` widened to what this guidance needs to hear (comms/scope.py): its separation;
        the safety filter's reach, r (1 + margin) + 2 v tau, and the stale-caution radius
        within the sense range; its own cruise speed within the fleet's top speed. The policy's
        berth (policy_separation_m) does not narrow it: the filter keeps separation_m."""
        f = safety.SafetyConfig()
        filter_reach_m = (
            self.separation_m * (1.0 + f.margin) + 2.0 * self.cruise_speed_m_s * f.time_horizon_s
        )
        return replace(
            base,
            separation_m=max(base.separation_m, self.separation_m),
            sense_range_m=max(base.sense_range_m, filter_reach_m, self.stale_caution_radius_m),
            max_speed_m_s=max(base.max_speed_m_s, self.cruise_speed_m_s),
        )

    def load_policy(self, safety_cfg: safety.SafetyConfig | None = None) -> GuidancePolicy:
        """The policy this configuration flies (unfiltered: guidance filters, to see when), told
        `told_separation_m`; its filter settings keep separation_m (`safety_config`, or
        `safety_cfg` where an evaluation sets them: agent/eval_agents.py)."""
        return GuidancePolicy.load(
            self.policy_path,
            separation_m=self.separation_m,
            policy_separation_m=self.told_separation_m,
            cruise_speed_m_s=self.cruise_speed_m_s,
            safety_filter=False,
            max_neighbours=self.max_neighbours,
            sparse_rule=SparseConfig() if self.safety_filter and self.sparse_rule else None,
            safety_cfg=safety_cfg or self.safety_config(),
            told_sigma_free_m=self.told_sigma_free_m,
        )

    def safety_config(self) -> safety.SafetyConfig:
        """The separation filter's settings this configuration flies: separation_m kept
        (radius_m), cruise speed, the traffic berths, the default margin and sigma_k. The
        policy it loads filters with exactly these (`GuidancePolicy.safety_cfg`); where the
        autopilot runs the filter itself (relay mode: the PX4 module, CVY_SEP_M and friends set
        to the fleet's values), the flight core's goal rule reads its zone clearance from them."""
        return safety.SafetyConfig(
            radius_m=self.separation_m,
            max_speed_m_s=self.cruise_speed_m_s,
            non_cooperative_radius_m=self.non_cooperative_separation_m,
            manned_radius_m=self.manned_separation_m,
        )


@dataclass(frozen=True)
class NeighbourViews:
    """What each of k rows knows of its neighbours, padded to K: valid marks real entries."""

    pos_m: np.ndarray
    """(k, K, 3) NED"""
    vel_m_s: np.ndarray
    """(k, K, 3) NED"""
    heading_rad: np.ndarray
    """(k, K)"""
    valid: np.ndarray
    """(k, K) bool"""
    stale: np.ndarray
    """(k, K) bool: the entry's data is old (guidance slows down near it)."""
    ids: np.ndarray | None = None
    """(k, K) the entries' vehicle ids (0: unknown); with `own_ids`, the filter pushes
    coincident vehicles apart by id (policy.safety.untie). None: it cannot."""
    own_ids: np.ndarray | None = None
    """(k,) each row's own vehicle id."""
    pos_sigma_m: np.ndarray | None = None
    """(k, K) the entries' position 1-sigma (m); None: all 0 (exact)."""
    cooperative: np.ndarray | None = None
    """(k, K) bool, False for traffic that does not avoid; None: all cooperative."""
    own_pos_sigma_m: np.ndarray | None = None
    """(k,) each row's own position 1-sigma; None: all 0."""
    manned: np.ndarray | None = None
    """(k, K) bool, True for a manned aircraft (traffic; the filter keeps its own berth from
    it); None: none."""

    @classmethod
    def of_snapshot(
        cls, nbrs: NeighbourSnapshot, own_id: int | None = None, own_pos_sigma_m: float = 0.0
    ) -> NeighbourViews:
        """One row: an agent's neighbour table (`own_id`: the agent's vehicle; own_pos_sigma_m:
        its position estimate's 1-sigma, from its telemetry)."""
        k = len(nbrs)
        stale = np.array([vid in nbrs.stale_ids for vid in nbrs.ids], bool).reshape(1, k)
        sigma = nbrs.column("pos_sigma_m", 0.0)
        coop = nbrs.column("cooperative", True)
        manned = nbrs.column("manned", False)
        return cls(
            np.asarray(nbrs.pos_ned_m, float).reshape(1, k, 3),
            np.asarray(nbrs.vel_ned_m_s, float).reshape(1, k, 3),
            np.asarray(nbrs.heading_rad, float).reshape(1, k),
            np.ones((1, k), bool),
            stale,
            None if own_id is None else np.array(nbrs.ids, np.int64).reshape(1, k),
            None if own_id is None else np.array([own_id], np.int64),
            sigma.reshape(1, k) if sigma.any() else None,
            None if coop.all() else coop.reshape(1, k),
            np.array([own_pos_sigma_m], float) if own_pos_sigma_m else None,
            manned.reshape(1, k) if manned.any() else None,
        )

    @classmethod
    def nearest(
        cls,
        rows_pos_m: np.ndarray,
        self_index: np.ndarray,
        world_pos_m: np.ndarray,
        world_vel_m_s: np.ndarray,
        world_heading_rad: np.ndarray,
        world_active: np.ndarray,
        world_stale: np.ndarray,
        max_neighbours: int | None,
        world_ids: np.ndarray | None = None,
        rows_ids: np.ndarray | None = None,
        world_pos_sigma_m: np.ndarray | None = None,
        rows_pos_sigma_m: np.ndarray | None = None,
        world_cooperative: np.ndarray | None = None,
        world_manned: np.ndarray | None = None,
    ) -> NeighbourViews:
        """Each row sees the nearest `max_neighbours` active world entries (horizontal
        distance) other than itself (`self_index`, -1 = not in the world); with the world's and
        the rows' vehicle ids, the views carry them (coincident vehicles are untied); likewise
        the position 1-sigmas (world (m,), rows (k,)) and the world's cooperative flags."""
        k, m = len(rows_pos_m), len(world_pos_m)
        # squared horizontal distances, per axis: a quarter of the cost of a (k, m, 2) difference
        key = np.square(rows_pos_m[:, None, 0] - world_pos_m[None, :, 0])
        key += np.square(rows_pos_m[:, None, 1] - world_pos_m[None, :, 1])
        key[:, ~world_active] = np.inf
        inside = self_index >= 0
        key[np.flatnonzero(inside), self_index[inside]] = np.inf
        width = m if max_neighbours is None else min(max_neighbours, m)
        if 0 < width < m:
            cols = np.argpartition(key, width - 1, axis=1)[:, :width]
        else:  # all of them, or none (max_neighbours 0, as the policy runtime reads it)
            cols = np.broadcast_to(np.arange(width), (k, width))
        valid = np.isfinite(np.take_along_axis(key, cols, axis=1))
        with_ids = world_ids is not None and rows_ids is not None
        return cls(
            world_pos_m[cols],
            world_vel_m_s[cols],
            world_heading_rad[cols],
            valid,
            world_stale[cols] & valid,
            np.asarray(world_ids, np.int64)[cols] if with_ids else None,
            np.asarray(rows_ids, np.int64) if with_ids else None,
            None if world_pos_sigma_m is None else np.asarray(world_pos_sigma_m, float)[cols],
            None if world_cooperative is None else np.asarray(world_cooperative, bool)[cols],
            None if rows_pos_sigma_m is None else np.asarray(rows_pos_sigma_m, float),
            None if world_manned is None else np.asarray(world_manned, bool)[cols],
        )

    def take(self, rows: np.ndarray) -> NeighbourViews:
        """The views of `rows` (an index array) alone: every per-row field sliced by them."""
        cut: dict = {}
        for f in fields(self):
            value = getattr(self, f.name)
            cut[f.name] = None if value is None else value[rows]
        return NeighbourViews(**cut)

    def select(self, r: int | np.integer) -> slice | np.ndarray:
        """What picks row r's valid neighbours out of a row of a per-neighbour field: a slice
        where they are one run (an agent's views: all but its own entry; the field's view, no
        copy), else the row's mask."""
        valid = self.valid[r]
        flags = valid.tolist()
        n = flags.count(True)
        first = flags.index(True) if n else 0
        if False in flags[first : first + n]:  # the n valid ones are not all in a row
            return valid
        return slice(first, first + n)

    def row(self, r: int, sel=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Row r's valid neighbours: positions (K', 3), velocities, headings, stale flags
        (views of the fields where `select` gives a slice: read them, do not write); `sel`:
        the row's `select`, where the caller has it."""
        v = self.select(r) if sel is None else sel
        return self.pos_m[r, v], self.vel_m_s[r, v], self.heading_rad[r, v], self.stale[r, v]

    def sky(self, rows=None, manned: bool = False, sel=None) -> dict:
        """The filter's real-vehicle inputs (policy.safety.pair_radius_m) for one row (an int:
        its valid neighbours, as `row`; `sel`: its `select`, where the caller has it) or view
        rows (an index array, None = all: padded), as keyword arguments; empty when the views
        carry none (exact, all cooperative). `manned`: with the manned flags (nbr_manned) for
        policy.safety's filters (the runtime's calls take none)."""
        out: dict = {}
        if isinstance(rows, _INDEX):
            v = self.select(rows) if sel is None else sel
            if manned and self.manned is not None:
                out["nbr_manned"] = self.manned[rows, v]
            if self.own_pos_sigma_m is not None:
                out["pos_sigma_m"] = float(self.own_pos_sigma_m[rows])
            if self.pos_sigma_m is not None:
                out["nbr_pos_sigma_m"] = self.pos_sigma_m[rows, v]
            if self.cooperative is not None:
                out["nbr_cooperative"] = self.cooperative[rows, v]
            return out
        sel = slice(None) if rows is None else rows
        if manned and self.manned is not None:
            out["nbr_manned"] = self.manned[sel]
        if self.own_pos_sigma_m is not None:
            out["pos_sigma_m"] = self.own_pos_sigma_m[sel]
        if self.pos_sigma_m is not None:
            out["nbr_pos_sigma_m"] = self.pos_sigma_m[sel]
        if self.cooperative is not None:
            out["nbr_cooperative"] = self.cooperative[sel]
        return out


@dataclass(frozen=True)
class GuidanceStep:
    """Setpoints for k rows."""

    vel_ned_m_s: np.ndarray
    """(k, 3)"""
    heading_rad: np.ndarray
    filtered: np.ndarray
    """(k,) the safety filter changed the command."""
    slowed_for_stale: np.ndarray
    decided: np.ndarray
    """(k,) the policy decided this tick (False: its last decision was held)."""
    waypoint_m: np.ndarray | None = None
    """(k, 2) the waypoint each row flies to on a routed goto (NaN: none); None without zones."""


class BatchGuidance:
    """The decide-and-hold loop of n vehicles: each row's held decision, goal and time."""

    def __init__(self, cfg: GuidanceConfig, n: int, policy: GuidancePolicy | None = None) -> None:
        self.cfg = cfg
        self.policy = policy or cfg.load_policy()
        self.safety_cfg = self.policy.safety_cfg
        p = cfg.decision_period_s
        self.decision_period_s = self.policy.decision_period_s if p is None else p
        self.held_m_s = np.full((n, 2), np.nan)
        """The last decision's horizontal velocity per row (NaN: nothing held)."""
        self.held_goal_m = np.full((n, 3), np.nan)
        self.decided_s = np.full(n, -np.inf)
        self.zones = None
        """Keep-out edges the filter keeps clear of (policy.zone_lines.ZoneSet), None: none."""
        self.router = None
        """Routes around them (policy.routes.Router): a goto row flies to its next waypoint."""
        self.bands: ZoneBands | None = None
        """The zones' floors and ceilings (policy.zone_bands.ZoneBands), None: every zone closed
        at every altitude (no zone has a band)."""
        self.waypoint_m = np.full((n, 2), np.nan)
        """Each row's current waypoint (north, east) while it flies a routed goto, else NaN."""
        self.c_core: CCore | None = None
        """The C twin of the single-vehicle paths (agent/guidance_c.py), None: numpy."""
        if cfg.c_core and n == 1:
            from agent.guidance_c import CCore

            self.c_core = CCore.maybe(cfg, self.safety_cfg)

    def set_zones(self, keep_out_m, fence_m=None, bands_m=None) -> None:
        """Keep out of these polygons [(K, 2) north/east metres] and inside the fence from
        now on: goto rows fly the route planner's next waypoint (policy.routes), and the filter
        keeps the zone edges as hard lines (policy.zone_lines), holding rows included. Empty
        and no fence: no zones. bands_m: (floor_alt_m, ceiling_alt_m) per polygon (None: no
        floor / no ceiling): a banded zone counts only for rows whose altitudes reach its band,
        and rows over or under it are kept on their side (policy/zone_bands.py). None or no band
        at all: every zone closed at every altitude. `zones` and `router` are every zone's."""
        from policy.routes import zones_for
        from policy.zone_bands import ZoneBands  # shapely and scipy: only with zones

        self.zones, self.router = zones_for(self.safety_cfg, keep_out_m, fence_m)
        full = (self.zones, self.router)
        self.bands = ZoneBands.of(self.safety_cfg, keep_out_m, fence_m, bands_m, full)
        self.waypoint_m[:] = np.nan

    def route(self, pos_m, goal_m, pos_sigma_m: float = 0.0):
        """The whole route (policy.routes.Route) from pos_m to goal_m (north/east) of a
        vehicle whose position 1-sigma is pos_sigma_m, for the station and Foxglove to draw;
        None without zones. Around every zone at every altitude (as the station draws it), not
        only the zones the vehicle's altitudes reach (`set_zones` bands_m)."""
        if self.router is None:
            return None
        pad = self.safety_cfg.sigma_k * pos_sigma_m
        return self.router.plan(np.asarray(pos_m, float)[:2], np.asarray(goal_m, float)[:2], pad)

    def _routed(
        self, router, rows, pos_m, target_m, goto, own_sigma_m=None, views=None
    ) -> np.ndarray:
        """target_m with each goto row's horizontal target replaced by its next waypoint of
        `router` (None: no zones), on routes that keep the filter's padding for each row's
        position 1-sigma (own_sigma_m (k,), None: 0) more from the zones (policy.routes
        `Router.widened`); a row that must wait for a one-lane gap gets its hold point
        (policy.lanes, from `views`, NeighbourViews of the rows; None: nobody waits)."""
        self.waypoint_m[rows] = np.nan
        if router is None or not goto.any():
            return target_m
        out = target_m.copy()
        pad = None if own_sigma_m is None else self.safety_cfg.sigma_k * own_sigma_m[goto]
        way = router.next_waypoints(pos_m[goto, :2], target_m[goto, :2], pad)
        if views is not None and views.valid[goto].any():
            g = np.flatnonzero(goto)
            mates = views.valid[g]
            if views.cooperative is not None:
                mates = mates & views.cooperative[g]
            way = hold_short(
                router,
                pos_m[goto, :2],
                target_m[goto, :2],
                way,
                pad,
                views.pos_m[g],
                views.vel_m_s[g],
                mates,
                None if views.own_ids is None else views.own_ids[g],
                None if views.ids is None else views.ids[g],
                self.cfg.lanes,
            )
        out[goto, :2] = way
        self.waypoint_m[rows[goto]] = out[goto, :2]
        return out

    def _band_groups(self, pos_m, target_m, views: NeighbourViews):
        """(target, groups) with banded zones (policy.zone_bands): the target under the vertical
        guard, and [(row indices, ZoneSet, Router)] per subset of zones the rows reach."""
        assert self.bands is not None
        sigma = views.own_pos_sigma_m
        pad = np.zeros(len(pos_m)) if sigma is None else self.safety_cfg.sigma_k * sigma
        return self.bands.groups(pos_m, target_m, pad)

    def _routed_groups(self, groups, rows, pos_m, target_m, goto, own_sigma_m, views):
        """`_routed` of each group with its own router; a goto row that no zone (and no
        fence) counts for flies at its goal, its waypoint (as a row in sight of it)."""
        out = target_m.copy()
        for g, _, router in groups:
            sigma = None if own_sigma_m is None else own_sigma_m[g]
            out[g] = self._routed(
                router, rows[g], pos_m[g], target_m[g], goto[g], sigma, views.take(g)
            )
            if router is None:
                free = g[goto[g]]
                self.waypoint_m[rows[free]] = target_m[free, :2]
        return out

    def _filter_groups(self, groups, pos_m, vel_m_s, pref_m_s, views: NeighbourViews):
        """`_filter` of each group with its own zones."""
        if len(groups) == 1:
            return self._filter(pos_m, vel_m_s, pref_m_s, views, groups[0][1])
        out, filtered = np.empty_like(pref_m_s), np.zeros(len(pos_m), bool)
        for g, zones, _ in groups:
            out[g], filtered[g] = self._filter(
                pos_m[g], vel_m_s[g], pref_m_s[g], views.take(g), zones
            )
        return out, filtered

    def due(self, now_s: float | None, rows: np.ndarray, goal_m: np.ndarray) -> np.ndarray:
        """Whether each row's policy should decide now: nothing held (first tick, after a hold),
        a new goal, or its period has passed (DECISION_DUE_SHARE of it, for tick jitter).
        Without a clock (`now_s` None): always."""
        if now_s is None:
            return np.ones(len(rows), bool)
        return (
            np.isnan(self.held_m_s[rows, 0])
            | ~np.all(self.held_goal_m[rows] == goal_m, axis=1)
            | (now_s - self.decided_s[rows] >= DECISION_DUE_SHARE * self.decision_period_s)
        )

    def forget(self, rows: np.ndarray) -> None:
        """Drop the held decisions of `rows` (their next goto decides at once)."""
        self.held_m_s[rows] = np.nan
        self.held_goal_m[rows] = np.nan

    def step(
        self,
        now_s: float | None,
        rows: np.ndarray,
        pos_m: np.ndarray,
        vel_m_s: np.ndarray,
        heading_rad: np.ndarray,
        target_m: np.ndarray,
        holding: np.ndarray,
        views: NeighbourViews,
        decide: np.ndarray | None = None,
        speed_cap_m_s: np.ndarray | None = None,
    ) -> GuidanceStep:
        """One tick for `rows`: goto rows fly the (held) policy towards `target_m`, holding rows
        keep `target_m`; everyone goes through the filter. `decide` (k,) forces (True) or skips
        (False) a decision; None: `due`. A goto row with nothing held decides regardless.
        `speed_cap_m_s` (k,): a horizontal speed limit per row (a mission item's speed), applied
        to the preference before the filter; 0 or None: none."""
        if len(rows) == 1 and self.bands is None:  # one vehicle (an agent): in floats
            return self._step_one(
                now_s,
                rows,
                pos_m,
                vel_m_s,
                heading_rad,
                target_m,
                holding,
                views,
                decide,
                speed_cap_m_s,
            )
        return self._step_rows(
            now_s,
            rows,
            pos_m,
            vel_m_s,
            heading_rad,
            target_m,
            holding,
            views,
            decide,
            speed_cap_m_s,
        )

    def _step_rows(
        self,
        now_s,
        rows,
        pos_m,
        vel_m_s,
        heading_rad,
        target_m,
        holding,
        views,
        decide,
        speed_cap_m_s,
    ) -> GuidanceStep:
        """`step` in arrays, for any number of rows: the reference `_step_one` is tested
        against."""
        cfg = self.cfg
        k = len(rows)
        goto = ~holding
        self.forget(rows[holding])
        sigma = views.own_pos_sigma_m
        if self.bands is None:
            target_m = self._routed(self.router, rows, pos_m, target_m, goto, sigma, views)
        else:  # each group of rows flies against the zones its altitudes reach
            target_m, groups = self._band_groups(pos_m, target_m, views)
            target_m = self._routed_groups(groups, rows, pos_m, target_m, goto, sigma, views)
        want = self.due(now_s, rows, target_m) if decide is None else np.asarray(decide, bool)
        deciding = goto & (want | np.isnan(self.held_m_s[rows, 0]))
        d = np.flatnonzero(deciding)
        if d.size:
            r = rows[d]
            self.held_m_s[r] = self._decide(
                pos_m[d], vel_m_s[d], heading_rad[d], target_m[d], views, d
            )
            self.held_goal_m[r] = target_m[d]
            self.decided_s[r] = -np.inf if now_s is None else now_s
        factor = np.where(goto, self._stale_factor(pos_m, views), 1.0)
        pref = np.zeros((k, 2))
        pref[goto] = self.held_m_s[rows[goto]] * factor[goto, None]
        if speed_cap_m_s is not None:  # slower than the policy's cruise, before the filter
            cap = np.where(speed_cap_m_s > 0, speed_cap_m_s, np.inf)
            norm = np.maximum(np.hypot(pref[:, 0], pref[:, 1]), 1e-9)
            pref *= np.minimum(1.0, cap / norm)[:, None]
        hold = cfg.hold_gain_1_s * (target_m[holding, :2] - pos_m[holding, :2])
        speed = np.hypot(hold[:, 0], hold[:, 1])
        hold *= (cfg.cruise_speed_m_s / np.maximum(speed, cfg.cruise_speed_m_s))[:, None]
        pref[holding] = hold
        if self.bands is None:
            v_h, filtered = self._filter(pos_m, vel_m_s, pref, views, self.zones)
        else:
            v_h, filtered = self._filter_groups(groups, pos_m, vel_m_s, pref, views)
        vz = np.clip(
            cfg.vertical_gain_1_s * (target_m[:, 2] - pos_m[:, 2]),
            -cfg.max_vertical_speed_m_s,
            cfg.max_vertical_speed_m_s,
        )
        # Heading is the direction of motion (the paper's definition); kept when (nearly) still.
        # Hovering does not turn the vehicle: a holding row turns only when it really moves.
        min_speed = np.where(holding, 0.5, 0.05)
        moving = np.hypot(v_h[:, 0], v_h[:, 1]) >= min_speed
        heading = np.where(moving, np.arctan2(v_h[:, 1], v_h[:, 0]), heading_rad)
        vel = np.column_stack([v_h, vz])
        way = None if self.router is None else self.waypoint_m[rows].copy()
        return GuidanceStep(vel, heading, filtered, factor < 1.0, deciding, way)

    def _step_one(
        self,
        now_s,
        rows,
        pos_m,
        vel_m_s,
        heading_rad,
        target_m,
        holding,
        views,
        decide,
        speed_cap_m_s,
    ) -> GuidanceStep:
        """`_step_rows` for one row without zone bands, in Python floats: an agent's tick pays
        for each small numpy call, and most of its cost was theirs (docs/companion.md, round
        fifteen). The policy, the route and the filter are the shared calls; tests compare
        the two paths (tests/test_guidance_one_row.py)."""
        cfg = self.cfg
        r = rows.item(0)
        hold = bool(holding.item(0))
        if hold:
            self.forget(rows)
        if self.router is None:  # no zones: no waypoint (as `_routed` says without a router)
            self.waypoint_m[r] = np.nan
        else:
            target_m = self._routed(
                self.router, rows, pos_m, target_m, ~holding, views.own_pos_sigma_m, views
            )
        target = target_m.tolist()[0]
        held_n, held_e = self.held_m_s[r].tolist()
        nothing = math.isnan(held_n)
        if decide is not None:
            want = bool(decide[0])
        elif now_s is None:
            want = True
        else:
            want = (
                nothing
                or self.held_goal_m[r].tolist() != target
                or now_s - self.decided_s.item(r) >= DECISION_DUE_SHARE * self.decision_period_s
            )
        deciding = not hold and (want or nothing)
        if deciding:
            held = self._decide_one(
                pos_m[0, :2], vel_m_s[0, :2], heading_rad[0], target_m[0, :2], views, 0
            )
            self.held_m_s[r] = held
            self.held_goal_m[r] = target_m[0]
            self.decided_s[r] = -np.inf if now_s is None else now_s
            held_n, held_e = held.tolist()
        (pn, pe, pd), (own_vn, own_ve, _) = pos_m.tolist()[0], vel_m_s.tolist()[0]
        factor = 1.0
        if hold:
            hn, he = cfg.hold_gain_1_s * (target[0] - pn), cfg.hold_gain_1_s * (target[1] - pe)
            scale = cfg.cruise_speed_m_s / max(math.hypot(hn, he), cfg.cruise_speed_m_s)
            pref_n, pref_e = hn * scale, he * scale
        else:
            factor = self._stale_factor_one(pn, pe, views)
            pref_n, pref_e = held_n * factor, held_e * factor
            cap = 0.0 if speed_cap_m_s is None else float(speed_cap_m_s[0])
            if cap > 0.0:
                clip = min(1.0, cap / max(math.hypot(pref_n, pref_e), 1e-9))
                pref_n, pref_e = pref_n * clip, pref_e * clip
        vn, ve, filtered = self._filter_one(
            (pn, pe), (own_vn, own_ve), (pref_n, pref_e), views, self.zones
        )
        vz = cfg.vertical_gain_1_s * (target[2] - pd)
        vz = min(max(vz, -cfg.max_vertical_speed_m_s), cfg.max_vertical_speed_m_s)
        moving = math.hypot(vn, ve) >= (0.5 if hold else 0.05)
        heading = math.atan2(ve, vn) if moving else heading_rad.item(0)
        way = None if self.router is None else self.waypoint_m[rows].copy()
        return GuidanceStep(
            np.array([[vn, ve, vz]]),
            np.array([heading]),
            FLAG[filtered],
            FLAG[factor < 1.0],
            FLAG[deciding],
            way,
        )

    def _decide(
        self, pos_m, vel_m_s, heading_rad, goal_m, views: NeighbourViews, idx
    ) -> np.ndarray:
        """Unfiltered policy velocities (len(idx), 2) for view rows `idx`."""
        if len(idx) == 1:  # one vehicle (an agent): the single-vehicle fast path
            row = int(idx[0])
            args = (pos_m[0, :2], vel_m_s[0, :2], heading_rad[0], goal_m[0, :2])
            return self._decide_one(*args, views, row)[None]
        obs = Observations(
            pos_m[:, :2],
            vel_m_s[:, :2],
            heading_rad,
            goal_m[:, :2],
            views.pos_m[idx, :, :2],
            views.vel_m_s[idx, :, :2],
            views.heading_rad[idx],
            views.valid[idx],
            **views.sky(idx),
        )
        return self.policy.command_batch(obs)

    def _decide_one(
        self, pos_m, vel_m_s, heading_rad, goal_m, views: NeighbourViews, row: int
    ) -> np.ndarray:
        """The unfiltered policy velocity (2,) of one vehicle (north/east (2,) inputs) among
        the valid neighbours of view row `row`: the policy's single-vehicle call."""
        sel = views.select(row)
        p, v, h, _ = views.row(row, sel)
        args = (pos_m, vel_m_s, heading_rad, goal_m)
        nbrs, sky = (p[:, :2], v[:, :2], h), views.sky(row, sel=sel)
        out = None if self.c_core is None else self.c_core.decide(*args, *nbrs, **sky)
        if out is None:  # numpy: the reference, and what the C core leaves to it
            out = self.policy.command(*args, *nbrs, **sky)
        return np.asarray(out, float)

    def _stale_factor(self, pos_m: np.ndarray, views: NeighbourViews) -> np.ndarray:
        cfg = self.cfg
        if not views.stale.any():
            return np.ones(len(pos_m))
        d = np.hypot(*(views.pos_m[..., :2] - pos_m[:, None, :2]).transpose(2, 0, 1))
        near = (views.stale & views.valid & (d < cfg.stale_caution_radius_m)).any(axis=1)
        return np.where(near, cfg.stale_slowdown, 1.0)

    def _stale_factor_one(self, pos_n_m: float, pos_e_m: float, views: NeighbourViews) -> float:
        """`_stale_factor` of views row 0 (the vehicle at pos_n_m, pos_e_m) in floats."""
        stale = views.stale.tolist()[0]
        if True not in stale:
            return 1.0
        cfg = self.cfg
        for old, valid, (n, e, _) in zip(
            stale, views.valid.tolist()[0], views.pos_m.tolist()[0], strict=True
        ):
            if old and valid and math.hypot(n - pos_n_m, e - pos_e_m) < cfg.stale_caution_radius_m:
                return cfg.stale_slowdown
        return 1.0

    def _filter(self, pos_m, vel_m_s, pref_m_s, views: NeighbourViews, zones):
        """(velocities (k, 2), changed (k,)): the separation filter on pref_m_s, keeping the
        edges of `zones` (policy.zone_lines.ZoneSet, None: none)."""
        k = len(pos_m)
        if k == 1:  # the single-vehicle fast path
            (pn, pe, *_), (vn, ve, *_) = pos_m.tolist()[0], vel_m_s.tolist()[0]
            n, e, changed = self._filter_one(
                (pn, pe), (vn, ve), tuple(pref_m_s.tolist()[0]), views, zones
            )
            return np.array([[n, e]]), np.array([changed])
        if not self.cfg.safety_filter or (not views.valid.any() and zones is None):
            return pref_m_s, np.zeros(k, bool)
        ids = views.ids is not None and views.own_ids is not None
        out = safety.filter_padded(
            pos_m[:, :2],
            vel_m_s[:, :2],
            pref_m_s,
            views.pos_m[..., :2],
            views.vel_m_s[..., :2],
            views.valid,
            self.safety_cfg,
            views.own_ids if ids else None,
            views.ids if ids else None,
            **views.sky(manned=True),
            zones=zones,
        )
        if zones is None:
            none = ~views.valid.any(axis=1)  # no neighbour: the command is not touched
            out[none] = pref_m_s[none]
        return out, np.linalg.norm(out - pref_m_s, axis=1) > 1e-6

    def _filter_one(
        self,
        pos_m: tuple[float, float],
        vel_m_s: tuple[float, float],
        pref_m_s: tuple[float, float],
        views: NeighbourViews,
        zones,
    ) -> tuple[float, float, bool]:
        """`_filter` of one vehicle among the neighbours of views row 0, in Python floats:
        (north, east, changed) of its own (north, east) position, velocity and preference."""
        v = views.select(0)
        nbr_pos_m, nbr_vel_m_s = views.pos_m[0, v, :2], views.vel_m_s[0, v, :2]
        if not self.cfg.safety_filter or (not len(nbr_pos_m) and zones is None):
            return pref_m_s[0], pref_m_s[1], False
        own_id = nbr_ids = None  # without both, coincident vehicles are not untied
        if views.ids is not None and views.own_ids is not None:
            own_id, nbr_ids = views.own_ids.item(0), views.ids[0, v]
        sky = views.sky(0, manned=True, sel=v)
        nbrs = (nbr_pos_m, nbr_vel_m_s)
        got = None
        if self.c_core is not None and zones is None:  # the core has no zone lines here
            got = self.c_core.filter(pos_m, vel_m_s, pref_m_s, *nbrs, own_id, nbr_ids, **sky)
        if got is None:  # numpy: the reference, and what the C core leaves to it
            own = (np.array(pos_m), np.array(vel_m_s), np.array(pref_m_s))
            got = safety.filter_one(
                *own, *nbrs, self.safety_cfg, own_id, nbr_ids, **sky, zones=zones
            )
            got = np.asarray(got, float).tolist()
        (vn, ve), (pn, pe) = got, pref_m_s
        dn, de = vn - pn, ve - pe  # the norm of `_filter`, in floats
        return vn, ve, math.sqrt(dn * dn + de * de) > 1e-6


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
    """One vehicle's guidance: `BatchGuidance` with one row."""

    def __init__(self, cfg: GuidanceConfig, policy: GuidancePolicy | None = None) -> None:
        self.cfg = cfg
        self.batch = BatchGuidance(cfg, 1, policy)
        self.policy = self.batch.policy
        self.safety_cfg = self.batch.safety_cfg
        self.decision_period_s = self.batch.decision_period_s

    _ROW = np.zeros(1, int)

    def decision_due(self, now_s: float, goal_m: np.ndarray) -> bool:
        return bool(self.batch.due(now_s, self._ROW, np.asarray(goal_m, float)[None])[0])

    @property
    def has_decision(self) -> bool:
        """A decision is held (goto can skip deciding)."""
        return not np.isnan(self.batch.held_m_s[0, 0])

    def reset(self) -> None:
        """Forget the held decision (the next goto decides at once)."""
        self.batch.forget(self._ROW)

    def _step(self, now_s, pos_m, vel_m_s, heading_rad, target_m, holding, nbrs, decide):
        out = self.batch.step(
            now_s,
            self._ROW,
            np.asarray(pos_m, float)[None],
            np.asarray(vel_m_s, float)[None],
            np.array([heading_rad], float),
            np.asarray(target_m, float)[None],
            np.array([holding]),
            NeighbourViews.of_snapshot(nbrs),
            None if decide is None else np.array([decide]),
        )
        return GuidanceOutput(
            out.vel_ned_m_s[0],
            float(out.heading_rad[0]),
            bool(out.filtered[0]),
            bool(out.slowed_for_stale[0]),
            bool(out.decided[0]),
        )

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
        """Policy guidance towards `goal_m` (NED). `decide` forces (True) or skips (False) a
        decision; None decides when due, or every call when `now_s` is None."""
        return self._step(now_s, pos_m, vel_m_s, heading_rad, goal_m, False, nbrs, decide)

    def hold(
        self,
        pos_m: np.ndarray,
        vel_m_s: np.ndarray,
        heading_rad: float,
        hold_m: np.ndarray,
        nbrs: NeighbourSnapshot,
    ) -> GuidanceOutput:
        """Keep `hold_m`, stepping aside for neighbours that come too close."""
        return self._step(None, pos_m, vel_m_s, heading_rad, hold_m, True, nbrs, None)

    def arrived(self, pos_m: np.ndarray, goal_m: np.ndarray) -> bool:
        return bool(
            np.hypot(*(goal_m[:2] - pos_m[:2])) <= self.cfg.arrive_radius_m
            and abs(goal_m[2] - pos_m[2]) <= self.cfg.arrive_alt_tol_m
        )
