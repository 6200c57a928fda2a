"""ctypes bindings of the C separation filter (covey_safety.h) and guidance tick (covey_guidance.h).

    filt = CSafetyFilter(lib, SafetyConfig())            # policy.safety's config, world units
    v_m_s = filt(pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s)

    tick = COnboard(lib, policy_cfg, safety_cfg, decision_period_s=1.0)
    r = tick.step(obs, now_s)       # obs: policy.observation.Observation.shaped(...)

`firmware.cpolicy.CPolicy` builds these from its library; the structures mirror the headers
field for field. Arrays cross as numpy structured arrays (no per-neighbour Python loop).
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np

from policy.observation import Observation

STATUS_NAMES = {0: "ok", 1: "null", 2: "nonfinite", 3: "range", 4: "stale"}
_F64, _I64 = np.dtype(np.float64), np.dtype(np.int64)
MAX_INPUTS = 64
"""COVEY_MAX_INPUTS: most neighbours per call."""

VEHICLE_DTYPE = np.dtype(
    [("pos_n_m", "<f4"), ("pos_e_m", "<f4"), ("heading_rad", "<f4"), ("stamp_us", "<u8")],
    align=True,
)
"""covey_vehicle_t (24 bytes: 4 of padding before the stamp)."""
TRACK_DTYPE = np.dtype(
    [
        ("pos_n_m", "<f4"),
        ("pos_e_m", "<f4"),
        ("vel_n_m_s", "<f4"),
        ("vel_e_m_s", "<f4"),
        ("id", "<u4"),
        ("pos_sigma_m", "<f4"),
        ("non_cooperative", "<u4"),
    ]
)
"""covey_track_t (id 0: unknown; pos_sigma_m 0: exact; non_cooperative 0: a covey vehicle, 1:
traffic, 2: a manned aircraft, covey_safety.h COVEY_TRACK_*)."""


class ConfigC(ctypes.Structure):
    """covey_config_t."""

    _fields_ = [
        ("separation_m", ctypes.c_float),
        ("cruise_speed_m_s", ctypes.c_float),
        ("max_neighbour_age_us", ctypes.c_uint64),
        ("max_own_age_us", ctypes.c_uint64),
        ("max_neighbours", ctypes.c_int32),
    ]


class CommandC(ctypes.Structure):
    """covey_command_t."""

    _fields_ = [
        ("vel_n_m_s", ctypes.c_float),
        ("vel_e_m_s", ctypes.c_float),
        ("action", ctypes.c_float * 2),
        ("n_used", ctypes.c_int32),
        ("n_stale", ctypes.c_int32),
        ("n_far", ctypes.c_int32),
        ("n_excess", ctypes.c_int32),
    ]


class SafetyConfigC(ctypes.Structure):
    """covey_safety_config_t."""

    _fields_ = [
        ("radius_m", ctypes.c_float),
        ("margin", ctypes.c_float),
        ("time_horizon_s", ctypes.c_float),
        ("dt_s", ctypes.c_float),
        ("max_speed_m_s", ctypes.c_float),
        ("responsibility", ctypes.c_float),
        ("sigma_k", ctypes.c_float),
        ("non_cooperative_radius_m", ctypes.c_float),
        ("manned_radius_m", ctypes.c_float),
        ("recover_speed_share", ctypes.c_float),
    ]

    @classmethod
    def of(cls, cfg) -> SafetyConfigC:
        """From a policy.safety.SafetyConfig (non_cooperative_radius_m and manned_radius_m
        None: 0 here)."""
        return cls(
            cfg.radius_m,
            cfg.margin,
            cfg.time_horizon_s,
            cfg.dt_s,
            cfg.max_speed_m_s,
            cfg.responsibility,
            cfg.sigma_k,
            cfg.non_cooperative_radius_m or 0.0,
            cfg.manned_radius_m or 0.0,
            cfg.recover_speed_share,
        )


class TrackC(ctypes.Structure):
    """covey_track_t."""

    _fields_ = [
        ("pos_n_m", ctypes.c_float),
        ("pos_e_m", ctypes.c_float),
        ("vel_n_m_s", ctypes.c_float),
        ("vel_e_m_s", ctypes.c_float),
        ("id", ctypes.c_uint32),
        ("pos_sigma_m", ctypes.c_float),
        ("non_cooperative", ctypes.c_uint32),
    ]


class SafetyOutC(ctypes.Structure):
    """covey_safety_out_t."""

    _fields_ = [
        ("vel_n_m_s", ctypes.c_float),
        ("vel_e_m_s", ctypes.c_float),
        ("n_lines", ctypes.c_int32),
        ("changed", ctypes.c_int32),
        ("infeasible", ctypes.c_int32),
    ]


class HoldC(ctypes.Structure):
    """covey_hold_t."""

    _fields_ = [
        ("vel_n_m_s", ctypes.c_float),
        ("vel_e_m_s", ctypes.c_float),
        ("goal_n_m", ctypes.c_float),
        ("goal_e_m", ctypes.c_float),
        ("decided_us", ctypes.c_uint64),
        ("valid", ctypes.c_int32),
    ]


class GuidanceConfigC(ctypes.Structure):
    """covey_guidance_config_t."""

    _fields_ = [
        ("policy", ConfigC),
        ("safety", SafetyConfigC),
        ("decision_period_s", ctypes.c_float),
        ("safety_filter", ctypes.c_int32),
        ("sparse_rule", ctypes.c_int32),
        ("told_sigma_free_m", ctypes.c_float),
    ]


class GuidanceOutC(ctypes.Structure):
    """covey_guidance_out_t."""

    _fields_ = [
        ("vel_n_m_s", ctypes.c_float),
        ("vel_e_m_s", ctypes.c_float),
        ("decided", ctypes.c_int32),
        ("command", CommandC),
        ("filter", SafetyOutC),
        ("straight", ctypes.c_int32),
    ]


class SparseOutC(ctypes.Structure):
    """covey_sparse_out_t."""

    _fields_ = [
        ("vel_n_m_s", ctypes.c_float),
        ("vel_e_m_s", ctypes.c_float),
        ("straight", ctypes.c_int32),
        ("n_encounters", ctypes.c_int32),
    ]


def bind(lib: ctypes.CDLL) -> None:
    """Declares the filter and guidance functions of `lib`."""
    vp = ctypes.c_void_p
    fp = ctypes.POINTER(ctypes.c_float)
    lib.covey_safety_filter.restype = ctypes.c_int
    lib.covey_safety_filter.argtypes = [
        ctypes.POINTER(SafetyConfigC),
        ctypes.POINTER(TrackC),
        fp,
        vp,
        ctypes.c_int32,
        vp,
        ctypes.POINTER(SafetyOutC),
    ]
    lib.covey_safety_defaults.restype = SafetyConfigC
    lib.covey_safety_defaults.argtypes = [ctypes.c_float, ctypes.c_float]
    lib.covey_safety_scratch_bytes.restype = ctypes.c_uint32
    lib.covey_safety_scratch_bytes.argtypes = []
    lib.covey_guidance_scratch_bytes.restype = ctypes.c_uint32
    lib.covey_guidance_scratch_bytes.argtypes = []
    lib.covey_told_separation_m.restype = ctypes.c_float
    lib.covey_told_separation_m.argtypes = [ctypes.c_float, ctypes.c_int32, ctypes.c_float]
    lib.covey_told_scale.restype = ctypes.c_float
    lib.covey_told_scale.argtypes = [
        ctypes.POINTER(SafetyConfigC),
        ctypes.c_float,
        ctypes.c_float,
        fp,
        vp,
        ctypes.c_int32,
    ]
    lib.covey_trained_period_s.restype = ctypes.c_float
    lib.covey_trained_period_s.argtypes = [ctypes.POINTER(ConfigC)]
    lib.covey_sparse_choose.restype = ctypes.c_int
    lib.covey_sparse_choose.argtypes = [
        ctypes.POINTER(SafetyConfigC),
        ctypes.POINTER(TrackC),
        fp,
        fp,
        vp,
        ctypes.c_int32,
        vp,
        ctypes.POINTER(SparseOutC),
    ]
    lib.covey_guidance_step.restype = ctypes.c_int
    lib.covey_guidance_step.argtypes = [
        vp,
        ctypes.POINTER(HoldC),
        vp,
        fp,
        vp,
        vp,
        vp,
        ctypes.c_int32,
        ctypes.c_uint64,
        vp,
        vp,
    ]
    lib.covey_guidance_step_sky.restype = ctypes.c_int
    lib.covey_guidance_step_sky.argtypes = [
        vp,
        ctypes.POINTER(HoldC),
        vp,
        fp,
        ctypes.c_float,
        vp,
        vp,
        vp,
        vp,
        vp,
        ctypes.c_int32,
        ctypes.c_uint64,
        vp,
        vp,
    ]
    lib.covey_guidance_step_zones.restype = ctypes.c_int
    lib.covey_guidance_step_zones.argtypes = [
        *lib.covey_guidance_step_sky.argtypes[:11],
        vp,
        ctypes.c_uint64,
        vp,
        vp,
    ]


def micros(t_s: float) -> int:
    """Seconds as the core's microseconds; a ValueError unless finite and >= 0."""
    if not np.isfinite(t_s) or t_s < 0:
        raise ValueError(f"times must be finite and >= 0 s, got {t_s}")
    return int(round(float(t_s) * 1e6))


def vehicles(
    obs: Observation, now_us: int, stamp_s=None, nbr_stamp_s=None
) -> tuple[np.ndarray, np.ndarray]:
    """covey_vehicle_t arrays of the own state (1,) and the K neighbours (at least one row);
    stamps default to now (fresh)."""
    rows = VehicleRows(obs.nbr_pos_m.shape[0])
    rows.fill(obs, now_us, stamp_s, nbr_stamp_s)
    return rows.own, rows.nbrs


class VehicleRows:
    """covey_vehicle_t arrays, the own state (1,) and room for k neighbours (at least one
    row), that `fill` writes: kept from call to call where the calls are many (CPolicy).
    Their float32 (n, 6) and uint64 (n, 3) views write a block of fields in one assignment:
    pos_n_m, pos_e_m and heading_rad are float32 columns 0 to 2, 4 bytes of padding follow,
    and stamp_us is uint64 column 2."""

    def __init__(self, k: int = MAX_INPUTS) -> None:
        self.own = np.zeros(1, VEHICLE_DTYPE)
        self.nbrs = np.zeros(max(k, 1), VEHICLE_DTYPE)
        self._own = (
            self.own.view(np.float32).reshape(1, 6),
            self.own.view(np.uint64).reshape(1, 3),
        )
        self._nbrs = (
            self.nbrs.view(np.float32).reshape(-1, 6),
            self.nbrs.view(np.uint64).reshape(-1, 3),
        )

    def fill(self, obs: Observation, now_us: int, stamp_s=None, nbr_stamp_s=None) -> int:
        """The own state and obs's K neighbours written (every field the core reads); K.
        Stamps default to now (fresh); a ValueError where they or K do not fit."""
        k = obs.nbr_pos_m.shape[0]
        if k > min(MAX_INPUTS, len(self.nbrs)):
            raise ValueError(f"the C core takes at most {MAX_INPUTS} neighbour reports, got {k}")
        own_f32, own_u64 = self._own
        own_f32[0, 0:2] = obs.pos_m
        own_f32[0, 2] = obs.heading_rad
        own_u64[0, 2] = now_us if stamp_s is None else micros(stamp_s)
        nb_f32, nb_u64 = self._nbrs
        nb_f32[:k, 0:2] = obs.nbr_pos_m
        nb_f32[:k, 2] = obs.nbr_heading_rad
        if nbr_stamp_s is None:
            nb_u64[:k, 2] = now_us
        else:
            t = np.asarray(nbr_stamp_s, dtype=np.float64).reshape(-1)
            if t.shape[0] != k:
                raise ValueError(f"nbr_stamp_s has {t.shape[0]} entries for {k} neighbours")
            if not (np.isfinite(t).all() and (t >= 0).all()):
                raise ValueError(f"times must be finite and >= 0 s, got {t}")
            nb_u64[:k, 2] = np.round(t * 1e6).astype(np.uint64)
        return k


def pair_floats(xy) -> tuple[float, float] | list[float]:
    """A (2,) vector as two Python floats: a tuple of two floats as it is (one vehicle's tick
    passes them: no numpy call), a (2,) float64 array in one call, anything else through
    numpy (a ValueError unless 2 values)."""
    if type(xy) is tuple and len(xy) == 2 and type(xy[0]) is float and type(xy[1]) is float:
        return xy
    if type(xy) is np.ndarray and xy.dtype is _F64 and xy.shape == (2,):
        return xy.tolist()
    return np.asarray(xy, dtype=np.float64).reshape(2).tolist()


def own_track(
    pos_m, vel_m_s, own_id=0, pos_sigma_m: float = 0.0, into: TrackC | None = None
) -> TrackC:
    """The own covey_track_t: a new one, or `into` (one kept from call to call) refilled."""
    t = TrackC() if into is None else into
    t.pos_n_m, t.pos_e_m = pair_floats(pos_m)
    t.vel_n_m_s, t.vel_e_m_s = pair_floats(vel_m_s)
    t.id, t.pos_sigma_m, t.non_cooperative = int(own_id), float(pos_sigma_m), 0
    return t


def pair_c(xy) -> ctypes.Array:
    """A (2,) vector as float[2]."""
    return (ctypes.c_float * 2)(*pair_floats(xy))


def track_kinds(k: int, cooperative=None, manned=None) -> np.ndarray:
    """(k,) uint8 COVEY_TRACK_* kinds: 0 a covey vehicle, 1 traffic (cooperative False), 2 a
    manned aircraft (manned True; it never cooperates: policy.safety.effective_cooperative).
    None: all cooperative, none manned; a scalar stands for all k."""
    kind = np.zeros(k, np.uint8)
    if cooperative is not None:
        kind[~np.broadcast_to(np.asarray(cooperative, bool), (k,))] = 1
    if manned is not None:
        kind[np.broadcast_to(np.asarray(manned, bool), (k,))] = 2
    return kind


def tracks(pos_m, vel_m_s, ids=None, pos_sigma_m=None, cooperative=None, manned=None) -> np.ndarray:
    """covey_track_t array of the neighbours (ids, 1-sigma, cooperative and manned flags as
    policy.safety.pair_radius_m takes them; None: 0, exact, all cooperative, none manned)."""
    pos = np.asarray(pos_m, dtype=np.float64).reshape(-1, 2)
    t = np.zeros(max(pos.shape[0], 1), TRACK_DTYPE)[: pos.shape[0]]
    fill_tracks(t, pos, vel_m_s, ids, pos_sigma_m, cooperative, manned)
    return t


def fill_tracks(
    buf: np.ndarray, pos_m, vel_m_s, ids=None, pos_sigma_m=None, cooperative=None, manned=None
) -> np.ndarray:
    """`tracks` written into the first rows of `buf` (a TRACK_DTYPE array of at least
    MAX_INPUTS rows, reused call after call: every field of those rows is written); returns
    them."""
    k = _fill_columns(*track_columns(buf), pos_m, vel_m_s, ids, pos_sigma_m, cooperative, manned)
    return buf[:k]


def track_columns(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A TRACK_DTYPE array's rows as (n, 7) float32 and uint32 views of the same memory (the
    struct is seven 4-byte fields without padding): a block of columns is one assignment."""
    return buf.view(np.float32).reshape(-1, 7), buf.view(np.uint32).reshape(-1, 7)


def _rows2(x) -> np.ndarray:
    """x as (n, 2) float64: a float64 (n, 2) array as it is (a view is fine: the values are
    copied into the tracks), anything else through numpy."""
    if type(x) is np.ndarray and x.dtype is _F64 and x.ndim == 2 and x.shape[1] == 2:
        return x
    return np.asarray(x, dtype=np.float64).reshape(-1, 2)


def _fill_columns(
    f32: np.ndarray, u32: np.ndarray, pos_m, vel_m_s, ids, pos_sigma_m, cooperative, manned
) -> int:
    """`fill_tracks` into `track_columns`' views; the number of rows written. float64 inputs
    round to float32 and ids wrap to uint32 as the struct's fields take them."""
    pos, vel = _rows2(pos_m), _rows2(vel_m_s)
    k = pos.shape[0]
    if vel.shape != pos.shape:
        raise ValueError(f"{k} neighbour positions but {vel.shape[0]} velocities")
    if k > MAX_INPUTS:
        raise ValueError(f"the C core takes at most {MAX_INPUTS} neighbours, got {k}")
    f32[:k, 0:2] = pos
    f32[:k, 2:4] = vel
    if ids is None:
        u32[:k, 4] = 0
    elif type(ids) is np.ndarray and ids.dtype is _I64 and ids.ndim == 1:
        u32[:k, 4] = ids
    else:
        u32[:k, 4] = np.asarray(ids, dtype=np.int64).reshape(-1)
    if pos_sigma_m is None:
        f32[:k, 5] = 0.0
    elif type(pos_sigma_m) is np.ndarray and pos_sigma_m.dtype is _F64:
        f32[:k, 5] = pos_sigma_m
    else:
        f32[:k, 5] = np.asarray(pos_sigma_m, np.float64)
    u32[:k, 6] = (
        0 if cooperative is None and manned is None else track_kinds(k, cooperative, manned)
    )
    return k


@dataclass(frozen=True)
class FilterResult:
    """One covey_safety_filter call."""

    status: str
    """"ok" or the fault name."""
    vel_m_s: np.ndarray
    """Filtered (north, east) velocity; zero on a fault."""
    n_lines: int
    """Neighbours within reach (one half-plane each)."""
    changed: bool
    """The (speed-clipped) preference broke a half-plane."""
    infeasible: bool
    """No velocity met every half-plane; the worst violation was minimised."""

    @classmethod
    def of(cls, status: int, out: SafetyOutC) -> FilterResult:
        return cls(
            STATUS_NAMES.get(status, str(status)),
            np.array([out.vel_n_m_s, out.vel_e_m_s], dtype=np.float64),
            out.n_lines,
            bool(out.changed),
            bool(out.infeasible),
        )


@dataclass(frozen=True)
class SparseResult:
    """One covey_sparse_choose call."""

    status: str
    vel_m_s: np.ndarray
    """The velocity to hold: straight at the goal or the policy's; zero on a fault."""
    straight: bool
    n_encounters: int


class CSafetyFilter:
    """The C separation filter with a policy.safety.SafetyConfig. One call at a time: its
    scratch memory and the arguments of `evaluate` and `sparse` are reused from call to call
    (tests/test_csafety_kept_buffers.py holds them to arguments built anew)."""

    def __init__(self, lib: ctypes.CDLL, cfg):
        self._lib = lib
        self.cfg = cfg
        self._ccfg = SafetyConfigC.of(cfg)
        self._scratch = ctypes.create_string_buffer(lib.covey_safety_scratch_bytes())
        # `evaluate`'s arguments, made once: an agent calls it every tick, and building them
        # anew (ctypes objects, a numpy array's .ctypes) cost it more than the filter itself
        self._tracks = np.zeros(MAX_INPUTS, TRACK_DTYPE)
        self._columns = track_columns(self._tracks)
        self._own, self._pref, self._out = TrackC(), (ctypes.c_float * 2)(), SafetyOutC()
        self._args = (
            ctypes.byref(self._ccfg),
            ctypes.byref(self._own),
            self._pref,
            self._tracks.ctypes.data_as(ctypes.c_void_p),
        )
        self._out_ref = ctypes.byref(self._out)
        # `sparse`'s own: its goal and the policy's velocity, and its output
        self._pairs = (ctypes.c_float * 2)(), (ctypes.c_float * 2)()
        self._sparse_out = SparseOutC()
        self._sparse_out_ref = ctypes.byref(self._sparse_out)

    def evaluate(
        self,
        pos_m,
        vel_m_s,
        pref_vel_m_s,
        nbr_pos_m,
        nbr_vel_m_s,
        own_id=0,
        nbr_ids=None,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> FilterResult:
        """One call; faults come back in `status`, never raised. Ids (0: unknown) untie
        coincident neighbours as policy.safety.untie does; position uncertainties,
        cooperative and manned flags as policy.safety.pair_radius_m takes them."""
        st = self._run(
            pos_m,
            vel_m_s,
            pref_vel_m_s,
            nbr_pos_m,
            nbr_vel_m_s,
            own_id,
            nbr_ids,
            pos_sigma_m,
            nbr_pos_sigma_m,
            nbr_cooperative,
            nbr_manned,
        )
        return FilterResult.of(st, self._out)

    def velocity(
        self, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s, own_id=0, nbr_ids=None, **sky
    ) -> tuple[str, float, float]:
        """`evaluate`'s status and filtered (north, east) velocity as Python floats, without
        building a result (one vehicle's tick: pass the own vectors as tuples of two floats).
        `sky`: `evaluate`'s pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned."""
        st = self._run(pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s, own_id, nbr_ids, **sky)
        out = self._out
        return STATUS_NAMES.get(st, str(st)), out.vel_n_m_s, out.vel_e_m_s

    def _run(
        self,
        pos_m,
        vel_m_s,
        pref_vel_m_s,
        nbr_pos_m,
        nbr_vel_m_s,
        own_id=0,
        nbr_ids=None,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> int:
        """One covey_safety_filter call on the kept arguments, refilled: its status; the
        output is in self._out until the next call."""
        k = _fill_columns(
            *self._columns,
            nbr_pos_m,
            nbr_vel_m_s,
            nbr_ids,
            nbr_pos_sigma_m,
            nbr_cooperative,
            nbr_manned,
        )
        own_track(pos_m, vel_m_s, own_id, pos_sigma_m, into=self._own)
        pref = self._pref
        pref[0], pref[1] = pair_floats(pref_vel_m_s)
        cfg, own_ref, pref_c, tracks_p = self._args
        return self._lib.covey_safety_filter(
            cfg, own_ref, pref_c, tracks_p, k, self._scratch, self._out_ref
        )

    def sparse(
        self,
        pos_m,
        vel_m_s,
        goal_m,
        policy_vel_m_s,
        nbr_pos_m,
        nbr_vel_m_s,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> SparseResult:
        """covey_sparse_choose with this filter's config (policy.sparse.choose_one's twin);
        faults come back in `status`, never raised."""
        st = self._run_sparse(
            pos_m,
            vel_m_s,
            goal_m,
            policy_vel_m_s,
            nbr_pos_m,
            nbr_vel_m_s,
            pos_sigma_m,
            nbr_pos_sigma_m,
            nbr_cooperative,
            nbr_manned,
        )
        out = self._sparse_out
        return SparseResult(
            STATUS_NAMES.get(st, str(st)),
            np.array([out.vel_n_m_s, out.vel_e_m_s], dtype=np.float64),
            bool(out.straight),
            int(out.n_encounters),
        )

    def sparse_velocity(
        self, pos_m, vel_m_s, goal_m, policy_vel_m_s, nbr_pos_m, nbr_vel_m_s, **sky
    ) -> tuple[str, float, float]:
        """`sparse`'s status and velocity to hold as Python floats, without building a result
        (`velocity`'s twin). `sky`: `sparse`'s pos_sigma_m and neighbour flags."""
        st = self._run_sparse(pos_m, vel_m_s, goal_m, policy_vel_m_s, nbr_pos_m, nbr_vel_m_s, **sky)
        out = self._sparse_out
        return STATUS_NAMES.get(st, str(st)), out.vel_n_m_s, out.vel_e_m_s

    def _run_sparse(
        self,
        pos_m,
        vel_m_s,
        goal_m,
        policy_vel_m_s,
        nbr_pos_m,
        nbr_vel_m_s,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> int:
        """One covey_sparse_choose call on `evaluate`'s kept tracks and own track, refilled
        (the neighbours without ids, as policy.sparse takes them): its status; the output is
        in self._sparse_out until the next call."""
        k = _fill_columns(
            *self._columns,
            nbr_pos_m,
            nbr_vel_m_s,
            None,
            nbr_pos_sigma_m,
            nbr_cooperative,
            nbr_manned,
        )
        own_track(pos_m, vel_m_s, 0, pos_sigma_m, into=self._own)
        goal, policy = self._pairs
        goal[0], goal[1] = pair_floats(goal_m)
        policy[0], policy[1] = pair_floats(policy_vel_m_s)
        cfg, own_ref, _, tracks_p = self._args
        return self._lib.covey_sparse_choose(
            cfg, own_ref, goal, policy, tracks_p, k, self._scratch, self._sparse_out_ref
        )

    def __call__(
        self, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s, own_id=0, nbr_ids=None, **sky
    ) -> np.ndarray:
        """Filtered velocity (2,); raises ValueError on a fault. `sky`: `evaluate`'s
        pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned."""
        r = self.evaluate(
            pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s, own_id, nbr_ids, **sky
        )
        if r.status != "ok":
            raise ValueError(f"C safety filter fault: {r.status}")
        return r.vel_m_s


@dataclass(frozen=True)
class StepResult:
    """One covey_guidance_step call."""

    status: str
    vel_m_s: np.ndarray
    """The velocity to fly (held decision, filtered); zero on a fault."""
    decided: bool
    """The policy ran this tick."""
    filtered: bool
    """The filter changed the held velocity."""
    straight: bool = False
    """This tick decided, by the sparse rule, to fly straight at the goal."""


class COnboard:
    """One vehicle's onboard guidance tick: its own hold state and scratch (covey_guidance.h)."""

    def __init__(
        self,
        lib,
        policy_cfg,
        safety_cfg,
        decision_period_s: float,
        safety_filter=True,
        sparse_rule=False,
        told_sigma_free_m: float | None = None,
    ):
        """`told_sigma_free_m` None: the told separation never grows (covey_told_scale)."""
        self._lib = lib
        self._cfg = GuidanceConfigC(
            policy_cfg,
            SafetyConfigC.of(safety_cfg),
            decision_period_s,
            int(bool(safety_filter)),
            int(bool(sparse_rule)),
            -1.0 if told_sigma_free_m is None else float(told_sigma_free_m),
        )
        self._hold = HoldC()
        self._scratch = ctypes.create_string_buffer(lib.covey_guidance_scratch_bytes())
        self._out = GuidanceOutC()

    def reset(self) -> None:
        """Forget the held decision (the next step decides)."""
        self._hold = HoldC()

    def step(
        self,
        obs: Observation,
        now_s: float,
        stamp_s: float | None = None,
        nbr_stamp_s=None,
        nbr_kind=None,
        zones=None,
    ) -> StepResult:
        """One tick at `now_s` (stamps default to now: fresh); obs.sky's uncertainties and
        cooperative and manned flags go to the filter. nbr_kind (K,) uint8: each neighbour's
        COVEY_TRACK_* kind (0 covey, 1 traffic, 2 manned), in place of obs.sky's flags; zones:
        keep-out zones (firmware.czones.CZones or firmware.cfence.CFence), through
        covey_guidance_step_zones. Values are the core's to check: a bad one comes back as a
        fault in `status`."""
        now_us = micros(now_s)
        own, nb = vehicles(obs, now_us, stamp_s, nbr_stamp_s)
        k = obs.nbr_pos_m.shape[0]
        nv = np.zeros((max(k, 1), 2), np.float32)
        nv[:k] = obs.nbr_vel_m_s
        goal = np.asarray(obs.goal_m, dtype=np.float32)
        sky = obs.sky
        ns = nc = None
        if sky.nbr_pos_sigma_m is not None:
            ns = np.zeros(max(k, 1), np.float32)
            ns[:k] = sky.nbr_pos_sigma_m
        if sky.nbr_cooperative is not None or sky.nbr_manned is not None:
            nc = np.zeros(max(k, 1), np.uint8)
            nc[:k] = track_kinds(k, sky.nbr_cooperative, sky.nbr_manned)
        if nbr_kind is not None:
            nc = np.zeros(max(k, 1), np.uint8)
            nc[:k] = np.broadcast_to(np.asarray(nbr_kind, np.uint8), (k,))
        out = self._out
        st = self._lib.covey_guidance_step_zones(
            ctypes.addressof(self._cfg),
            ctypes.byref(self._hold),
            own.ctypes.data,
            pair_c(obs.vel_m_s),
            sky.pos_sigma_m,
            goal.ctypes.data,
            nb.ctypes.data,
            nv.ctypes.data,
            None if ns is None else ns.ctypes.data,
            None if nc is None else nc.ctypes.data,
            k,
            None if zones is None else zones.ptr,
            now_us,
            self._scratch,
            ctypes.addressof(out),
        )
        return StepResult(
            STATUS_NAMES.get(st, str(st)),
            np.array([out.vel_n_m_s, out.vel_e_m_s], dtype=np.float64),
            bool(out.decided),
            bool(out.filter.changed),
            bool(out.straight),
        )
