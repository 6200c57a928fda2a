"""ctypes wrapper of the C policy core: the onboard policy, callable from Python.

    pol = CPolicy.load(separation_m=3.0, cruise_speed_m_s=1.0)   # shipped weights
    v_m_s = pol.command(pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad)

`command` mirrors `policy.runtime.GuidancePolicy.command`, with the same defaults (as the
agents fly): the network told its weights' share of the separation (the shipped weights: all
of it), then (with `safety_filter=True`,
the default) the sparse-traffic rule (covey_sparse_choose) and the C separation filter
(covey_safety.c) on the neighbours' positions and velocities; `preferred` is the same before
the filter. `onboard()` gives one vehicle's guidance tick as the PX4 module flies it
(covey_guidance.c): decide at the trained period, filter every tick.
Freshness is optional: pass `now_s` with `stamp_s` / `nbr_stamp_s` (seconds on one
clock) and neighbours older than `max_neighbour_age_s` are dropped, an own state older
than `max_own_age_s` raises. The shared library is built on demand into firmware/build/
with the system C compiler (a hash of sources, weights and flags names it, so a stale
build is never loaded).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from firmware import csafety, hostbuild
from policy.observation import Observation, Sky
from policy.runtime import TOLD_SIGMA_FREE_M

if TYPE_CHECKING:  # the zone filter loads only with zones (`set_zones`)
    from firmware.czones import CZones

MAX_NEIGHBOURS = 40
"""COVEY_MAX_NEIGHBOURS: most neighbours fed to the LSTM."""
MAX_INPUTS = 64
"""COVEY_MAX_INPUTS: most neighbour reports per call."""
STATUS_NAMES = {0: "ok", 1: "null", 2: "nonfinite", 3: "range", 4: "stale"}


_Config = csafety.ConfigC


_Command = csafety.CommandC


class CPolicyError(ValueError):
    """The core refused its inputs; `status` is the covey_status_t name."""

    def __init__(self, status: int):
        self.status = STATUS_NAMES.get(status, str(status))
        super().__init__(f"C policy core fault: {self.status}")


@dataclass(frozen=True)
class CPolicyResult:
    """Everything one evaluation returns."""

    status: str
    """"ok" or the fault name."""
    vel_m_s: np.ndarray
    """(north, east) velocity command in m/s; zero on a fault."""
    action: np.ndarray
    """Clipped network action (forward, right), policy units."""
    n_used: int
    n_stale: int
    n_far: int
    n_excess: int


def load_library(npz_path=None) -> ctypes.CDLL:
    """Builds (if needed) and loads the core compiled against `npz_path`'s weights."""
    npz = Path(npz_path) if npz_path is not None else hostbuild.SHIPPED_NPZ
    lib = ctypes.CDLL(str(hostbuild.build_library(hostbuild.header_for(npz))))
    lib.covey_command.restype = ctypes.c_int
    lib.covey_command.argtypes = [
        ctypes.POINTER(_Config),
        ctypes.c_void_p,  # covey_vehicle_t (csafety.VEHICLE_DTYPE)
        ctypes.c_void_p,  # covey_goal_t: float[2]
        ctypes.c_void_p,
        ctypes.c_int32,
        ctypes.c_uint64,
        ctypes.c_void_p,
        ctypes.POINTER(_Command),
    ]
    lib.covey_action.restype = ctypes.c_int
    lib.covey_action.argtypes = [
        ctypes.POINTER(ctypes.c_float),
        ctypes.c_int32,
        ctypes.POINTER(ctypes.c_float),
        ctypes.c_void_p,
        ctypes.POINTER(ctypes.c_float),
    ]
    lib.covey_scratch_bytes.restype = ctypes.c_uint32
    lib.covey_scratch_bytes.argtypes = []
    csafety.bind(lib)
    return lib


class CPolicy:
    """The C policy core with world-unit scaling and the C separation filter."""

    def __init__(
        self,
        npz_path=None,
        separation_m: float = 3.0,
        cruise_speed_m_s: float = 1.0,
        max_neighbours: int | None = None,
        max_neighbour_age_s: float = 1.0,
        max_own_age_s: float = 0.5,
        safety_filter: bool = True,
        safety_cfg=None,
        policy_separation_m: float | None = None,
        sparse_rule: bool = True,
        keep_out_m=None,
        fence_m=None,
        told_sigma_free_m: float | None = TOLD_SIGMA_FREE_M,
    ):
        """The defaults fly as the agents and the PX4 module do (GuidancePolicy's defaults).
        `told_sigma_free_m`: as GuidancePolicy's (covey_told_scale; None: never).
        `policy_separation_m`: the separation the network is told (its distance scale, 3
        policy units = this); None: told_separation_m, as flight tells it (the weights'
        told share of the separation with the filter on, the whole separation without it). The filter always keeps
        separation_m. `sparse_rule` (with the filter only): covey_sparse_choose, policy.sparse's
        C twin, picks the straight line at the goal in sparse traffic."""
        if max_neighbours is None:
            max_neighbours = MAX_NEIGHBOURS
        if not 0 <= max_neighbours <= MAX_NEIGHBOURS:
            raise ValueError(
                f"max_neighbours must be in [0, {MAX_NEIGHBOURS}] for the C core, "
                f"got {max_neighbours}"
            )
        self._lib = load_library(npz_path)
        self._scratch = ctypes.create_string_buffer(self._lib.covey_scratch_bytes())
        # `evaluate`'s arguments, made once (as CSafetyFilter's): refilled call after call
        self._vehicles = csafety.VehicleRows()
        self._goal = np.zeros(2, np.float32)
        self._out = _Command()
        self._args = (
            self._vehicles.own.ctypes.data,
            self._goal.ctypes.data,
            self._vehicles.nbrs.ctypes.data,
            ctypes.byref(self._out),
        )
        # numpy only, like policy.safety below: the rule's one definition (C twin parity tested)
        from policy.runtime import filtered_told_share, told_separation_m

        told_m = told_separation_m(
            separation_m,
            bool(safety_filter),
            policy_separation_m,
            share=filtered_told_share(npz_path),
        )
        self._cfg = _Config(
            told_m,
            cruise_speed_m_s,
            csafety.micros(max_neighbour_age_s),
            csafety.micros(max_own_age_s),
            max_neighbours,
        )
        self.separation_m = float(separation_m)
        if told_sigma_free_m is not None and not (
            np.isfinite(told_sigma_free_m) and told_sigma_free_m >= 0
        ):
            raise ValueError(
                f"told_sigma_free_m must be finite and >= 0 or None, got {told_sigma_free_m}"
            )
        self.told_sigma_free_m = told_sigma_free_m
        self.cruise_speed_m_s = float(cruise_speed_m_s)
        self.max_neighbours = max_neighbours
        self.safety_filter = bool(safety_filter)
        self.sparse_rule = bool(sparse_rule) and self.safety_filter
        from policy.safety import SafetyConfig  # numpy only: the config's one definition

        base = safety_cfg or SafetyConfig()
        self.safety_cfg = replace(base, radius_m=separation_m, max_speed_m_s=cruise_speed_m_s)
        self._filter = csafety.CSafetyFilter(self._lib, self.safety_cfg)
        self.zones: CZones | None = None
        """The C keep-out zones (firmware.czones.CZones), None: none."""
        self.router = None
        """The route planner around them (policy.routes.Router, Python: the companion's)."""
        if keep_out_m is not None or fence_m is not None:
            self.set_zones(keep_out_m or (), fence_m)

    def set_zones(self, keep_out_m, fence_m=None) -> None:
        """GuidancePolicy.set_zones with the C core's zone filter (covey_zones.c): the route
        planner (Python) picks the waypoint, the C filter keeps the zone edges as hard lines."""
        from firmware.czones import CZones
        from policy.routes import zones_for

        zones, self.router = zones_for(self.safety_cfg, keep_out_m, fence_m)
        self.zones = None
        if zones is not None:
            keep = list(zones.polygons[: zones.n_keep_out])
            self.zones = CZones(self._lib, keep, zones.radius_m, zones.time_horizon_s, fence_m)

    @classmethod
    def load(
        cls,
        path=None,
        separation_m: float = 3.0,
        cruise_speed_m_s: float = 1.0,
        max_neighbours: int | None = None,
        **kwargs,
    ) -> CPolicy:
        """Same call as GuidancePolicy.load (path None = shipped weights)."""
        return cls(path, separation_m, cruise_speed_m_s, max_neighbours, **kwargs)

    @property
    def decision_period_s(self) -> float:
        """The trained decision period (covey_trained_period_s) at separation_m, as
        GuidancePolicy's (a narrower policy_separation_m does not shorten it)."""
        cfg = _Config(
            self.separation_m,
            self.cruise_speed_m_s,
            self._cfg.max_neighbour_age_us,
            self._cfg.max_own_age_us,
            self._cfg.max_neighbours,
        )
        return float(self._lib.covey_trained_period_s(ctypes.byref(cfg)))

    def filter(
        self,
        pos_m,
        vel_m_s,
        pref_vel_m_s,
        nbr_pos_m,
        nbr_vel_m_s,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> np.ndarray:
        """The C safety filter alone (world units); raises ValueError on a fault.
        Uncertainties, cooperative and manned flags as `command` takes them; with zones, their
        edges are hard lines (covey_safety_filter_zones)."""
        sky = {"pos_sigma_m": pos_sigma_m, "nbr_pos_sigma_m": nbr_pos_sigma_m}
        r = self._filtered(
            pos_m,
            vel_m_s,
            pref_vel_m_s,
            nbr_pos_m,
            nbr_vel_m_s,
            nbr_cooperative=nbr_cooperative,
            nbr_manned=nbr_manned,
            **sky,
        )
        if r.status != "ok":
            raise ValueError(f"C safety filter fault: {r.status}")
        return r.vel_m_s

    def _filtered(self, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s, **sky):
        """One C filter call (with zones: covey_safety_filter_zones); a csafety.FilterResult."""
        if self.zones is not None:
            return self.zones.evaluate(
                self.safety_cfg, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s, **sky
            )
        return self._filter.evaluate(pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s, **sky)

    def onboard(self, decision_period_s: float | None = None) -> csafety.COnboard:
        """One vehicle's guidance tick (covey_guidance_step) with its own hold state;
        None = the trained period, 0 = decide every tick."""
        p = self.decision_period_s if decision_period_s is None else float(decision_period_s)
        return csafety.COnboard(
            self._lib,
            self._cfg,
            self.safety_cfg,
            p,
            self.safety_filter,
            self.sparse_rule,
            self.told_sigma_free_m,
        )

    def told_scale(
        self, pos_sigma_m: float, nbr_pos_sigma_m=None, nbr_cooperative=None, nbr_manned=None
    ) -> float:
        """covey_told_scale at these sigmas and flags (the C twin of policy.runtime.told_scale
        with Sky.nbr_sigma_max_m)."""
        if nbr_pos_sigma_m is None:  # exact neighbours: none counts, whatever their kinds
            nbr_pos_sigma_m, nbr_cooperative, nbr_manned = (), None, None
        nbr = np.ascontiguousarray(nbr_pos_sigma_m, dtype=np.float32).reshape(-1)
        kinds = np.ascontiguousarray(csafety.track_kinds(nbr.size, nbr_cooperative, nbr_manned))
        free = -1.0 if self.told_sigma_free_m is None else self.told_sigma_free_m
        return float(
            self._lib.covey_told_scale(
                ctypes.byref(self._filter._ccfg),
                free,
                float(pos_sigma_m),
                nbr.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),
                kinds.ctypes.data,
                nbr.size,
            )
        )

    def _told_cfg(self, obs: Observation) -> _Config | None:
        """The network's config at this decision: its told separation times `told_scale`
        (None: as built), as covey_guidance_step tells it."""
        if self.told_sigma_free_m is None:
            return None
        sky = obs.sky
        scale = self.told_scale(
            sky.pos_sigma_m, sky.nbr_pos_sigma_m, sky.nbr_cooperative, sky.nbr_manned
        )
        if scale == 1.0:
            return None
        c = self._cfg
        return _Config(
            c.separation_m * scale,
            c.cruise_speed_m_s,
            c.max_neighbour_age_us,
            c.max_own_age_us,
            c.max_neighbours,
        )

    def evaluate(
        self,
        obs: Observation,
        now_s=None,
        stamp_s=None,
        nbr_stamp_s=None,
        cfg: _Config | None = None,
    ) -> CPolicyResult:
        """One call of covey_command on `obs` (Observation.shaped: the core checks the
        values); faults come back in `status`, never raised."""
        st = self._run(obs, now_s, stamp_s, nbr_stamp_s, cfg)
        out = self._out
        return CPolicyResult(
            STATUS_NAMES.get(st, str(st)),
            np.array([out.vel_n_m_s, out.vel_e_m_s], dtype=np.float64),
            np.array(out.action[:], dtype=np.float64),
            out.n_used,
            out.n_stale,
            out.n_far,
            out.n_excess,
        )

    def _run(self, obs: Observation, now_s, stamp_s, nbr_stamp_s, cfg: _Config | None) -> int:
        """One covey_command call on the kept arguments, refilled: its status; the output is
        in self._out until the next call."""
        now_us = csafety.micros(now_s) if now_s is not None else 0
        k = self._vehicles.fill(obs, now_us, stamp_s, nbr_stamp_s)
        self._goal[:] = obs.goal_m
        own, goal, nbrs, out = self._args
        return self._lib.covey_command(
            ctypes.byref(cfg or self._cfg), own, goal, nbrs, k, now_us, self._scratch, out
        )

    def command(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        now_s=None,
        stamp_s=None,
        nbr_stamp_s=None,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> np.ndarray:
        """Velocity command (2,) in m/s (north, east); raises CPolicyError on a fault.

        With the filter on, it sees the neighbours the network kept fresh (stale ones dropped).
        For the decision hold, hold `preferred` and `filter` it every tick (`onboard()` does).
        pos_sigma_m, nbr_pos_sigma_m (K,), nbr_cooperative (K,) and nbr_manned (K,): as
        GuidancePolicy.command takes them (the C filter's covey_track_t fields)."""
        sky = Sky.checked(  # as GuidancePolicy
            pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned=nbr_manned
        )
        obs = Observation.shaped(
            pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, sky
        )
        return self._command(obs, now_s, stamp_s, nbr_stamp_s, filtered=True)

    def preferred(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        now_s=None,
        stamp_s=None,
        nbr_stamp_s=None,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> np.ndarray:
        """GuidancePolicy.preferred in C: the velocity to hold for one decision period (the
        network's, or the sparse rule's straight line), not yet filtered."""
        sky = Sky.checked(  # as GuidancePolicy
            pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned=nbr_manned
        )
        obs = Observation.shaped(
            pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, sky
        )
        return self._command(obs, now_s, stamp_s, nbr_stamp_s, filtered=False)

    def _command(self, obs: Observation, now_s, stamp_s, nbr_stamp_s, filtered: bool):
        if self.router is not None:
            try:
                pad = self.safety_cfg.sigma_k * obs.sky.pos_sigma_m  # as GuidancePolicy
                obs = obs.with_goal(self.router.next_waypoint(obs.pos_m, obs.goal_m, pad))
            except (TypeError, ValueError):
                pass  # the core names the bad input
        st = self._run(obs, now_s, stamp_s, nbr_stamp_s, self._told_cfg(obs))
        if st != 0:
            raise CPolicyError(st)
        v = (self._out.vel_n_m_s, self._out.vel_e_m_s)  # Python floats, as the core gave them
        if not self.safety_filter or (
            obs.nbr_pos_m.shape[0] == 0 and not self.sparse_rule and self.zones is None
        ):
            return np.array(v)
        if nbr_stamp_s is not None and now_s is not None:
            age_s = now_s - np.asarray(nbr_stamp_s, dtype=np.float64).reshape(-1)
            obs = obs.neighbours(age_s * 1e6 <= self._cfg.max_neighbour_age_us)
        tracks = (obs.pos_m, obs.vel_m_s)
        nbrs = (obs.nbr_pos_m, obs.nbr_vel_m_s)
        sky = obs.sky.kwargs()
        if self.sparse_rule:
            status, vn, ve = self._filter.sparse_velocity(*tracks, obs.goal_m, v, *nbrs, **sky)
            if status != "ok":
                raise CPolicyError(STATUS_NAMES_INV[status])
            v = (vn, ve)
        if not filtered:
            return np.array(v)
        f = self._filtered(*tracks, v, *nbrs, **sky)
        if f.status != "ok":
            raise CPolicyError(STATUS_NAMES_INV[f.status])
        return f.vel_m_s

    def action(self, obs: Observation) -> np.ndarray:
        """Clipped network action (fwd, right) of `obs` in metres, as
        GuidancePolicy.actor.action (policy.actor) takes it; raises CPolicyError on a fault."""
        r = self.evaluate(obs)
        if r.status != "ok":
            raise CPolicyError(STATUS_NAMES_INV[r.status])
        return r.action

    def network(self, seq, goal_feat) -> np.ndarray:
        """covey_action: the network alone on an encoded sequence (L, X) and goal features."""
        seq = np.ascontiguousarray(seq, dtype=np.float32)
        g = np.ascontiguousarray(goal_feat, dtype=np.float32).reshape(-1)
        a = (ctypes.c_float * 2)()
        fp = ctypes.POINTER(ctypes.c_float)
        st = self._lib.covey_action(
            seq.ctypes.data_as(fp), seq.shape[0], g.ctypes.data_as(fp), self._scratch, a
        )
        if st != 0:
            raise CPolicyError(st)
        return np.array(a[:], dtype=np.float64)


STATUS_NAMES_INV = {v: k for k, v in STATUS_NAMES.items()}
