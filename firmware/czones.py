"""ctypes bindings of the C keep-out zones (covey_zones.h): the filter's hard half-planes onboard.

    zones = CZones(lib, keep_out_m, radius_m=1.8)                 # [(K, 2) arrays], north/east m
    v_m_s = zones.filter(safety_cfg, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s)

The twin of policy.zone_lines.ZoneSet with policy.safety.filter_one(..., zones=...); the
parity tests are tests/test_zones_filter.py.
"""

from __future__ import annotations

import ctypes

import numpy as np

from firmware.csafety import (
    STATUS_NAMES,
    FilterResult,
    SafetyConfigC,
    SafetyOutC,
    TrackC,
    own_track,
    pair_c,
    tracks,
)
from policy.zone_lines import ZONE_TIME_HORIZON_S

MAX_ZONE_VERTICES = 512
"""COVEY_MAX_ZONE_VERTICES: all polygons together."""
MAX_ZONE_POLYGONS = 64
"""COVEY_MAX_ZONE_POLYGONS."""


class HalfplaneC(ctypes.Structure):
    """covey_halfplane_t (double: COVEY_SAFETY_DOUBLE=1, the default build)."""

    _fields_ = [("point", ctypes.c_double * 2), ("dir", ctypes.c_double * 2)]


def bind(lib: ctypes.CDLL) -> None:
    """Declares the zone functions of `lib`."""
    vp = ctypes.c_void_p
    fp = ctypes.POINTER(ctypes.c_float)
    lib.covey_zones_bytes.restype = ctypes.c_uint32
    lib.covey_zones_bytes.argtypes = []
    lib.covey_zones_init.restype = ctypes.c_int
    lib.covey_zones_init.argtypes = [
        vp,
        fp,
        ctypes.POINTER(ctypes.c_int32),
        ctypes.c_int32,
        ctypes.c_int32,
        ctypes.c_float,
        ctypes.c_float,
    ]
    lib.covey_zones_lines.restype = ctypes.c_int32
    lib.covey_zones_lines.argtypes = [
        vp,
        ctypes.POINTER(TrackC),
        ctypes.c_float,
        ctypes.c_float,
        vp,
    ]
    lib.covey_safety_filter_zones.restype = ctypes.c_int
    lib.covey_safety_filter_zones.argtypes = [
        ctypes.POINTER(SafetyConfigC),
        vp,
        ctypes.POINTER(TrackC),
        fp,
        vp,
        ctypes.c_int32,
        vp,
        ctypes.POINTER(SafetyOutC),
    ]


class CZones:
    """Keep-out polygons (and an optional fence) prepared by covey_zones_init."""

    def __init__(
        self,
        lib: ctypes.CDLL,
        keep_out_m,
        radius_m: float,
        time_horizon_s: float = ZONE_TIME_HORIZON_S,
        fence_m=None,
    ):
        """Raises ValueError naming the covey_status_t when the core refuses the polygons."""
        bind(lib)
        self._lib = lib
        polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in keep_out_m]
        if fence_m is not None:
            polys.append(np.asarray(fence_m, dtype=np.float64).reshape(-1, 2))
        counts = (ctypes.c_int32 * max(len(polys), 1))(*[len(p) for p in polys])
        flat = np.ascontiguousarray(
            np.concatenate(polys).ravel() if polys else np.zeros(2), np.float32
        )
        self._flat = flat
        self._buf = ctypes.create_string_buffer(lib.covey_zones_bytes())
        self._scratch = ctypes.create_string_buffer(lib.covey_safety_scratch_bytes())
        st = lib.covey_zones_init(
            self._buf,
            flat.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),
            counts,
            len(polys),
            int(fence_m is not None),
            float(radius_m),
            float(time_horizon_s),
        )
        if st != 0:
            raise ValueError(f"C zones refused the polygons: {STATUS_NAMES.get(st, st)}")

    @property
    def ptr(self) -> int:
        """The address of the prepared covey_zones_t (covey_guidance_step_zones takes it)."""
        return ctypes.addressof(self._buf)

    def lines(self, pos_m, vel_m_s, max_speed_m_s: float, pad_m: float = 0.0) -> list:
        """covey_zones_lines: [((point_n, point_e), (dir_n, dir_e))], as ZoneSet.lines."""
        out = (HalfplaneC * 32)()
        n = self._lib.covey_zones_lines(
            self._buf,
            ctypes.byref(own_track(pos_m, vel_m_s)),
            float(max_speed_m_s),
            float(pad_m),
            out,
        )
        return [((ln.point[0], ln.point[1]), (ln.dir[0], ln.dir[1])) for ln in out[:n]]

    def evaluate(
        self,
        safety_cfg,
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
        """covey_safety_filter_zones, as CSafetyFilter.evaluate takes its inputs; faults come
        back in `status`, never raised."""
        t = tracks(nbr_pos_m, nbr_vel_m_s, nbr_ids, nbr_pos_sigma_m, nbr_cooperative, nbr_manned)
        out = SafetyOutC()
        st = self._lib.covey_safety_filter_zones(
            ctypes.byref(SafetyConfigC.of(safety_cfg)),
            self._buf,
            ctypes.byref(own_track(pos_m, vel_m_s, own_id, pos_sigma_m)),
            pair_c(pref_vel_m_s),
            t.ctypes.data,
            t.shape[0],
            self._scratch,
            ctypes.byref(out),
        )
        return FilterResult.of(st, out)

    def filter(self, safety_cfg, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s):
        """The filtered velocity (2,); ValueError on a fault."""
        r = self.evaluate(safety_cfg, pos_m, vel_m_s, pref_vel_m_s, nbr_pos_m, nbr_vel_m_s)
        if r.status != "ok":
            raise ValueError(f"C zone filter fault: {r.status}")
        return r.vel_m_s
